"""Multi-view refinement of 3D lines with fixed poses: each line moves to agree with the detections its
projection meets in the mapping views (LIMAP's line refinement, in a linear form).

A line lifted from one view carries that view's depth noise, so it reprojects a few pixels off in the
others and the track builder's 2 px / 0.01 rad test finds it in few of them. Here:

1. every mapping view that sees the line (frustum and planes) offers the detection nearest its projection
   within a loose gate (``max_angle``, ``max_dist``, ``min_overlap``); the line's own evidence is kept;
2. each detection back-projects to a plane through its camera (:func:`lipmap.geometry.backprojected_planes`);
   each endpoint moves to minimise its Cauchy-weighted pixel distances to those planes plus a prior
   ``|X - X0|^2 / prior_m^2`` that holds what the views cannot fix (depth along narrow baselines, and the
   endpoints' slide along the line): a 3x3 solve per endpoint, re-weighted ``iterations`` times.

The caller rebuilds the tracks with the strict test afterwards. Lines seen in fewer than two views do not move.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import geometry as geo
from .. import logger
from ..errors import InputError

REFINE_LINES = ("on-plane", "edges", "all")


@dataclass(frozen=True)
class RefineConfig:
    enabled: bool = True
    max_angle: float = 0.05  # rad: the gate that gathers a line's detections (the track test is 0.01)
    max_dist: float = 5.0  # px
    min_overlap: float = 0.2
    robust_px: float = 1.0  # Cauchy scale of the reprojection residuals
    prior_m: float = 0.02  # an endpoint this far from where it was weighs as much as 1 px in one view
    iterations: int = 5
    # which lines of a LiP-Map map (MappingConfig.refine): "on-plane", "edges" or "all"
    lines: str = "on-plane"

    def __post_init__(self):
        if self.lines not in REFINE_LINES:
            raise InputError(f"refine.lines must be one of {', '.join(REFINE_LINES)}, got {self.lines!r}")


def reprojection_residuals(lines: np.ndarray, line_index: np.ndarray, segments2d, projections) -> np.ndarray:
    """Pixel distances of each observed line's projected endpoints to its detection's infinite line.

    Args:
        lines: :math:`(N, 2, 3)`; line_index: :math:`(M,)`; segments2d: :math:`(M, 2, 2)`; projections:
            :math:`(M, 3, 4)`.

    Returns:
        :math:`(M, 2)` signed distances in pixels.
    """
    P = np.broadcast_to(np.asarray(projections, dtype=float), (len(line_index), 3, 4))
    planes = geo.backprojected_planes(segments2d, P)
    X = np.asarray(lines, dtype=float).reshape(-1, 2, 3)[np.asarray(line_index, dtype=np.int64)]
    return _residuals(X, planes, P)[0]


def _residuals(X: np.ndarray, planes: np.ndarray, P: np.ndarray):
    """(residuals in px, the observing cameras' depths), both :math:`(M, 2)`."""
    depth = np.maximum(np.einsum("mj,mkj->mk", P[:, 2, :3], X) + P[:, 2, 3][:, None], 1e-6)
    return (np.einsum("mj,mkj->mk", planes[:, :3], X) + planes[:, 3][:, None]) / depth, depth


def refine_segments(lines: np.ndarray, line_index: np.ndarray, segments2d, projections,
                    conf: RefineConfig = RefineConfig()) -> np.ndarray:
    """Segments moved to agree with their observations (module docstring, step 2).

    Args:
        lines: :math:`(N, 2, 3)` world segments, also the prior.
        line_index: :math:`(M,)` the line of each observation.
        segments2d: :math:`(M, 2, 2)` the observed detections, in pixels.
        projections: :math:`(M, 3, 4)` the observing cameras' ``K [R | t]``.

    Returns:
        :math:`(N, 2, 3)`; lines with fewer than two observations are returned unchanged.
    """
    X0 = np.asarray(lines, dtype=float).reshape(-1, 2, 3)
    li = np.asarray(line_index, dtype=np.int64)
    n_obs = np.bincount(li, minlength=len(X0))
    keep = n_obs[li] >= 2
    if not keep.any():
        return X0.copy()
    li = li[keep]
    seg = np.asarray(geo.as_segments2d(segments2d), dtype=float)[keep]
    P = np.asarray(projections, dtype=float)[keep]
    planes = geo.backprojected_planes(seg, P)
    X = X0.copy()
    n = len(X0)
    for _ in range(conf.iterations):
        r, depth = _residuals(X[li], planes, P)
        w = 1.0 / (1.0 + (np.abs(r).max(1) / conf.robust_px) ** 2)  # one weight per observation (Cauchy)
        A = np.tile(np.eye(3) / conf.prior_m ** 2, (n, 2, 1, 1))
        b = X0 / conf.prior_m ** 2
        for k in range(2):
            a = planes[:, :3] / depth[:, k : k + 1]
            np.add.at(A[:, k], li, w[:, None, None] * a[:, :, None] * a[:, None, :])
            np.add.at(b[:, k], li, -(w * planes[:, 3] / depth[:, k])[:, None] * a)
        X = np.linalg.solve(A, b[..., None])[..., 0]
    return X


def gather_observations(lines: np.ndarray, views, lines_by_view: dict, conf: RefineConfig, caster=None,
                        tracks=None):
    """Each line's observations for the refinement: per view that sees it, the detection nearest its projection
    within the loose gate, plus the evidence already in ``tracks`` (one list of observations per line).

    Returns:
        ``line_index`` :math:`(M,)`, ``segments2d`` :math:`(M, 2, 2)`, ``projections`` :math:`(M, 3, 4)`.
    """
    from .extract import ExtractConfig, build_tracks

    vidx = {v.name: i for i, v in enumerate(views)}
    obs = {}
    for l, t in enumerate(tracks or []):
        for o in t:
            if o.image_name in vidx:
                obs[(l, vidx[o.image_name])] = np.asarray(o.segment, dtype=float).reshape(2, 2)
    gate = replace(ExtractConfig(), track_max_angle=conf.max_angle, track_max_dist=conf.max_dist,
                   track_min_overlap=conf.min_overlap)
    rows = build_tracks(lines, views, lines_by_view, gate, caster=caster, progress=False)
    if len(rows):
        L = np.asarray(lines, dtype=float)
        for vi in np.unique(rows[:, 1]):
            r = rows[rows[:, 1] == vi]
            v = views[vi]
            det = np.asarray(geo.as_segments2d(lines_by_view[v.name]), dtype=float)[r[:, 2]]
            proj, _ = geo.project_segments(L[r[:, 0]], v.cam_from_world, v.camera)
            dist = geo.perpendicular_distance(proj, det, "max")
            for j in np.argsort(dist, kind="stable"):  # nearest first: it takes the (line, view) slot
                obs.setdefault((int(r[j, 0]), int(vi)), det[j])
    if not obs:
        return np.zeros(0, np.int64), np.zeros((0, 2, 2)), np.zeros((0, 3, 4))
    keys = np.array(list(obs.keys()), dtype=np.int64)
    P = np.stack([geo.projection_matrices(views[vi].cam_from_world, views[vi].camera) for vi in range(len(views))])
    return keys[:, 0], np.stack(list(obs.values())), P[keys[:, 1]]


def refine_linemap(linemap, views, lines_by_view: dict, conf: RefineConfig, caster=None, which=None):
    """``linemap`` with the lines ``which`` (default: all) refined against the mapping views; tracks unchanged
    (rebuild them with :func:`lipmap.mapping.extract.add_tracks`)."""
    from ..linemap import LineMap

    idx = np.arange(len(linemap)) if which is None else np.asarray(which, dtype=np.int64)
    if not conf.enabled or len(idx) == 0:
        return linemap
    li, seg, P = gather_observations(linemap.lines[idx], views, lines_by_view, conf, caster,
                                     [linemap.tracks[i] for i in idx])
    new = refine_segments(linemap.lines[idx], li, seg, P, conf)
    moved = np.linalg.norm(new - linemap.lines[idx], axis=-1).max(-1)
    n_seen = int((np.bincount(li, minlength=len(idx)) >= 2).sum())
    logger.info("line refinement: %d of %d lines seen in >= 2 views, median move %.1f mm", n_seen, len(idx),
                1e3 * float(np.median(moved[moved > 0])) if (moved > 0).any() else 0.0)
    lines = linemap.lines.copy()
    lines[idx] = new
    meta = {**linemap.metadata, "n_refined": int((moved > 0).sum())}
    return LineMap(lines, linemap.tracks, linemap.supports, linemap.planes, meta)


__all__ = ["RefineConfig", "gather_observations", "refine_linemap", "refine_segments", "reprojection_residuals"]
