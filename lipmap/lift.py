"""Baseline line map ``lift``: back-project each detected 2D line with its view's depth.

This is the paper's Fig. 1 first row ("lines lifted with depth"): no multi-view reasoning beyond
an optional merge of near-duplicates. Per detected segment:

1. sample ``n_samples`` points along it (a small margin inside the endpoints) and read depth at
   each as the median of the valid depths in a (2w+1)^2 window - on the line itself and on both
   sides (``side_offset`` px along the normal), because at an occluding edge the window on the
   line straddles two surfaces;
2. a depth profile is usable when enough samples are valid and consecutive valid depths never
   jump by more than ``max(jump_abs, jump_rel * z)`` (a discontinuity means the segment crosses
   surfaces); back-project it and fit a 3D line robustly (PCA, reject residuals above
   ``max(fit_abs, fit_rel * z)``, refit); the fit must keep ``min_inlier_ratio`` of the samples;
3. profile choice: the on-line profile if usable, else the nearer usable side (the occluding,
   foreground surface carries the edge);
4. the 3D endpoints are the points of the endpoint rays closest to the fitted line, so the lifted
   segment projects exactly onto the detection in its own view.

Each lifted line's track is its one observation. With ``merge=True`` near-duplicates across views
are merged with the track builder's test (projection of line a into view k vs the detection
behind line b: angle < 0.01 rad, endpoint distance < 2 px, overlap > 0.2; see
:func:`lipmap.geometry.match_segments_2d`) plus a 3D check (b's endpoints within ``merge_max_3d`` of
a's infinite line); connected groups are fused by PCA over their endpoints (paper Alg. 1, step 4)
and their tracks concatenated.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np
from tqdm import tqdm

from . import logger
from .errors import InputError
from .geometry import (
    fit_line,
    match_segments_2d,
    point_line_distance,
    project_segments,
    transform_points,
)
from .linemap import LineMap
from .lines2d import list_names, load_lines
from .poses import invert_T
from .presets import resolve


@dataclass(frozen=True)
class LiftConfig:
    n_samples: int = 32
    end_margin_px: float = 2.0  # samples start this far inside each endpoint (<= 10% of the length)
    window: int = 1  # median over a (2w+1)^2 window
    side_offset: float = 1.5  # px: the side strips lie 1 and 2 side_offsets off the line
    side_window: int = 0  # median window of the side strips (single pixels: no straddling)
    min_valid_ratio: float = 0.6
    jump_abs: float = 0.03  # m
    jump_rel: float = 0.04  # of the depth
    fit_abs: float = 0.01  # m
    fit_rel: float = 0.01  # of the depth
    min_inlier_ratio: float = 0.7
    max_depth: float = 10.0
    min_length_3d: float = 0.02  # m
    min_ray_angle_deg: float = 5.0  # reject lines seen almost end-on (angle between line and view ray)
    merge: bool = False
    merge_max_angle: float = 0.01  # rad (track builder)
    merge_max_dist: float = 2.0  # px (track builder)
    merge_min_overlap: float = 0.2  # (track builder)
    merge_max_3d: float = 0.05  # m


confs = {
    "lift": LiftConfig(),
    "lift-merge": LiftConfig(merge=True),
    # Kinect depth is too noisy for 0.01 rad across views: a looser merge for real RGB-D data
    "lift-merge-loose": LiftConfig(merge=True, merge_max_angle=0.03, merge_max_dist=3.0),
}


def get_conf(conf: Union[None, str, dict, LiftConfig] = None) -> LiftConfig:
    """A :class:`LiftConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "lift", default="lift")


# ----------------------------------------------------------------------------------------------
# single view
# ----------------------------------------------------------------------------------------------
def _window_median(depth: np.ndarray, uv: np.ndarray, w: int) -> np.ndarray:
    """Median of valid (> 0) depths around pixel positions uv (..., 2), COLMAP convention."""
    H, W = depth.shape
    col = np.floor(uv[..., 0]).astype(np.int64)
    row = np.floor(uv[..., 1]).astype(np.int64)
    offs = np.arange(-w, w + 1)
    cc = col[..., None, None] + offs[None, :]
    rr = row[..., None, None] + offs[:, None]
    inside = (cc >= 0) & (cc < W) & (rr >= 0) & (rr < H)
    vals = depth[np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)].astype(np.float64)
    vals = np.where(inside & (vals > 0), vals, np.nan).reshape(*uv.shape[:-1], -1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows -> NaN
        return np.nanmedian(vals, axis=-1)


def _fit_inverse_depth(A: np.ndarray, z: np.ndarray, conf: LiftConfig, check_jumps: bool = True):
    """Robust least squares of inverse depth 1/z = A @ p over the valid samples of a profile.

    Points on ONE 3D line (or plane) have an inverse depth that is affine in the image coordinates
    along the line (or in both), so this is the exact model, fitted in image space where the
    extrapolation to the endpoints is only the small end margin.

    Args:
        A: (n, k) design matrix (1 and image coordinates); z: (n,) depths, NaN = invalid.

    Returns:
        (params (k,), mean depth of the inliers) or None when too few valid / inlier samples,
        or when consecutive valid depths jump (the profile crosses surfaces).
    """
    valid = np.isfinite(z) & (z > 0) & (z < conf.max_depth)
    n = len(z)
    if valid.sum() < max(A.shape[1] + 1, conf.min_valid_ratio * n):
        return None
    zv = z[valid]
    if check_jumps and np.any(np.abs(np.diff(zv)) > np.maximum(conf.jump_abs, conf.jump_rel * zv[:-1])):
        return None
    Av, w = A[valid], 1.0 / zv
    inl = np.ones(len(zv), dtype=bool)
    thr = np.maximum(conf.fit_abs, conf.fit_rel * zv)
    for _ in range(3):
        p, *_ = np.linalg.lstsq(Av[inl], w[inl], rcond=None)
        pred = Av @ p
        with np.errstate(divide="ignore", invalid="ignore"):
            resid = np.abs(1.0 / pred - zv)
        inl = (pred > 0) & (resid <= thr)
        if inl.sum() < max(A.shape[1] + 1, conf.min_inlier_ratio * n):
            return None
    p, *_ = np.linalg.lstsq(Av[inl], w[inl], rcond=None)
    return p, float(np.mean(zv[inl]))


def lift_view_lines(lines2d: np.ndarray, depth: np.ndarray, camera, conf: Union[None, str, LiftConfig] = None):
    """Lift the 2D lines of one view into its camera frame.

    Args:
        lines2d: :math:`(N, 4)` segments, COLMAP pixel convention.
        depth: :math:`(H, W)` metres in this camera, 0 = invalid.
        camera: :class:`~lipmap.scene.Camera`.

    Returns:
        **segments_cam** :math:`(N, 2, 3)` (NaN for rejected lines) and **ok** :math:`(N,)` bool.
    """
    conf = get_conf(conf)
    L = np.asarray(lines2d, dtype=np.float64).reshape(-1, 4)
    N = len(L)
    out = np.full((N, 2, 3), np.nan)
    ok = np.zeros(N, dtype=bool)
    if N == 0:
        return out, ok
    t, uv, normal2 = _sample_along_lines(L, conf)
    offsets, depths = _depth_profiles(depth, uv, normal2, conf)
    fx, fy, cx, cy = camera.params
    end_rays = _rays_z1(L.reshape(N, 2, 2), camera.params)  # (N, 2, 3), z = 1
    end_xy = np.stack([(L[:, [0, 2]] - cx) / fx, (L[:, [1, 3]] - cy) / fy], -1)  # (N, 2, 2) normalised
    for i in range(N):
        profiles = [d[i] for d in depths]
        cands = _profile_candidates(t[i], uv[i], normal2[i], profiles, offsets, end_xy[i], camera.params, conf)
        best = _choose_profile(cands, profiles, conf)
        if best is None:
            continue
        seg = _segment_on_end_rays(best[1], end_rays[i], conf)
        if seg is None:
            continue
        out[i] = seg
        ok[i] = True
    return out, ok


def _sample_along_lines(L: np.ndarray, conf: LiftConfig):
    """Sample parameters t (N, n) and points uv (N, n, 2) inside each segment's end margins, and its 2D normal (N, 2)."""
    p0, p1 = L[:, :2], L[:, 2:]
    length = np.linalg.norm(p1 - p0, axis=1)
    dir2 = (p1 - p0) / np.maximum(length, 1e-9)[:, None]
    normal2 = np.stack([-dir2[:, 1], dir2[:, 0]], 1)
    margin = np.minimum(conf.end_margin_px, 0.1 * length) / np.maximum(length, 1e-9)
    t = margin[:, None] + (1 - 2 * margin[:, None]) * np.linspace(0.0, 1.0, conf.n_samples)[None]
    uv = p0[:, None] + t[..., None] * (p1 - p0)[:, None]  # (N, n, 2)
    return t, uv, normal2


def _depth_profiles(depth: np.ndarray, uv: np.ndarray, normal2: np.ndarray, conf: LiftConfig):
    """The profile offsets and the window-median depth profiles (5 arrays (N, n)) on and beside each line."""
    # profile k: offset (in side_offset units) along the 2D normal: 0 = on the line, +-1 near, +-2 far
    offsets = (0.0, -1.0, -2.0, 1.0, 2.0)
    depths = [
        _window_median(depth, uv + o * conf.side_offset * normal2[:, None], conf.window if o == 0 else conf.side_window)
        for o in offsets
    ]
    return offsets, depths


def _rays_z1(q: np.ndarray, params) -> np.ndarray:
    """Camera rays with z = 1 through pixel positions q (..., 2), COLMAP convention."""
    fx, fy, cx, cy = params
    return np.stack([(q[..., 0] - cx) / fx, (q[..., 1] - cy) / fy, np.ones(q.shape[:-1])], -1)


def _profile_candidates(t, uv, normal2, profiles, offsets, end_xy, params, conf: LiftConfig) -> list:
    """One line's usable depth profiles as (mean depth, inverse depth at the 2 endpoints, "center" | "side")."""
    fx, fy, cx, cy = params
    ones = np.ones(conf.n_samples)
    cands = []
    f = _fit_inverse_depth(np.stack([ones, t], 1), profiles[0], conf)
    if f is not None:
        cands.append((f[1], f[0][0] + f[0][1] * np.array([0.0, 1.0]), "center"))
    for near, far in ((1, 2), (3, 4)):
        # a plane's inverse depth is affine in the normalised image coordinates
        pts = np.concatenate([uv + offsets[k] * conf.side_offset * normal2 for k in (near, far)])
        xy = np.stack([(pts[:, 0] - cx) / fx, (pts[:, 1] - cy) / fy], 1)
        zs = np.concatenate([profiles[near], profiles[far]])
        A1 = np.stack([ones, t], 1)
        if any(_fit_inverse_depth(A1, profiles[k], conf) is None for k in (near, far)):
            continue  # each strip on its own must be one continuous straight profile
        fp = _fit_inverse_depth(np.column_stack([np.ones(len(xy)), xy]), zs, conf, check_jumps=False)
        if fp is not None:
            cands.append((fp[1], fp[0][0] + end_xy @ fp[0][1:], "side"))
    return cands


def _choose_profile(cands: list, profiles: list, conf: LiftConfig):
    """The candidate whose depth the line takes, or None (no candidate, or only background behind an edge)."""
    if not cands:
        return None
    # on-line profile unless a side surface is clearly nearer: then the line is that
    # surface's occluding edge and the on-line depth saw the background through it
    best = cands[0]
    nearest = min(cands, key=lambda c: c[0])
    if best[2] != "center" or nearest[0] < best[0] - max(conf.jump_abs, conf.jump_rel * best[0]):
        best = nearest
    # a surface nearer than the chosen one right next to the line (that could not be fitted)
    # means the chosen one is the background seen past an occluding edge: no reliable depth
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        evidence = np.nanmin([np.nanmedian(profiles[k]) for k in (0, 1, 3)])
    if np.isfinite(evidence) and evidence < best[0] - max(conf.jump_abs, conf.jump_rel * best[0]):
        return None
    return best


def _segment_on_end_rays(inv: np.ndarray, end_rays: np.ndarray, conf: LiftConfig):
    """The 3D segment (2, 3) at inverse depths ``inv`` on the endpoint rays; None if too far, too short or end-on."""
    if np.any(inv <= 1.0 / conf.max_depth):
        return None
    seg = end_rays / inv[:, None]
    # a line seen almost end-on has ill-defined endpoints
    cos_max = np.cos(np.deg2rad(conf.min_ray_angle_deg))
    dvec = seg[1] - seg[0]
    ln = np.linalg.norm(dvec)
    if ln < conf.min_length_3d or abs(seg.mean(0) @ dvec) / (np.linalg.norm(seg.mean(0)) * ln) > cos_max:
        return None
    return seg


# ----------------------------------------------------------------------------------------------
# map
# ----------------------------------------------------------------------------------------------
def lift_linemap(scene_views: Sequence, lines, conf: Union[None, str, dict, LiftConfig] = None,
                 depth_of: Optional[Callable] = None, skip: Optional[dict] = None) -> LineMap:
    """Lift the detected lines of every view with its depth into one world :class:`LineMap`.

    Args:
        scene_views: posed :class:`~lipmap.scene.View` objects with depth.
        lines: ``lines2d.h5`` holding lines for those views, or {view name: (N, 4) segments}.
        conf: preset ("lift", "lift-merge", "lift-merge-loose"), dict of overrides or :class:`LiftConfig`.
        depth_of: ``f(view) -> (H, W) depth`` (default: the view's sensor depth, ``view.load_depth()``);
            the mapping uses it to lift lines onto its optimized planes.
        skip: {view name: indices of 2D lines not to lift} (lines another method already explains).

    Returns:
        the line map; each track is the observation(s) that produced the line.
    """
    conf = get_conf(conf)
    if isinstance(lines, dict):
        source, stored = "the given lines", set(lines)
    else:
        source = Path(lines)
        stored = set(list_names(source))
    missing = [v.name for v in scene_views if v.name not in stored]
    if missing:
        raise InputError(f"no 2D lines for {len(missing)} views, e.g. {missing[0]!r}", source,
                         hint="run lines2d.detect_lines on these views first")
    seg_w, obs, n_det = [], [], 0
    per_view = []  # (view, 2D lines, index into seg_w for each 2D line or -1)
    for v in tqdm(scene_views, desc="lift", disable=len(scene_views) < 2):
        L = lines[v.name] if isinstance(lines, dict) else load_lines(source, v.name)
        L = np.asarray(L, dtype=np.float64).reshape(-1, 4)
        n_det += len(L)
        todo = np.ones(len(L), dtype=bool)
        if skip and v.name in skip:
            todo[np.asarray(list(skip[v.name]), dtype=np.int64)] = False
        segs_cam, ok = lift_view_lines(L[todo], v.load_depth() if depth_of is None else depth_of(v), v.camera, conf)
        world_from_cam = invert_T(v.cam_from_world)
        idx = np.full(len(L), -1)
        for j, i in enumerate(np.flatnonzero(todo)):
            if ok[j]:
                idx[i] = len(seg_w)
                seg_w.append(transform_points(world_from_cam, segs_cam[j]))
                obs.append([(v.name, int(i), L[i])])
        per_view.append((v, L, idx))
    lines = np.array(seg_w).reshape(-1, 2, 3)
    logger.info("Lifted %d of %d 2D lines (%.0f%%).", len(lines), n_det, 100.0 * len(lines) / max(n_det, 1))
    meta = {"method": "lift", "config": asdict(conf), "n_detections": int(n_det)}
    if conf.merge and len(lines):
        lines, obs = _merge(lines, obs, per_view, conf)
        meta["n_before_merge"] = int(len(seg_w))
        logger.info("Merged into %d lines.", len(lines))
    return LineMap(lines, obs, metadata=meta)


def _merge(lines: np.ndarray, obs: list, per_view: list, conf: LiftConfig):
    """Union near-duplicate lifted lines across views (track-builder test + 3D check)."""
    n = len(lines)
    parent = np.arange(n)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    src_view = np.array([o[0][0] for o in obs])
    for v, L, idx in tqdm(per_view, desc="merge", disable=len(per_view) < 2):
        has3d = np.flatnonzero(idx >= 0)
        if not len(has3d):
            continue
        others = np.flatnonzero(src_view != v.name)
        if not len(others):
            continue
        proj, valid = project_segments(lines[others], v.cam_from_world, v.camera)
        # only lines whose projection meets the image can match a detection
        W, H = v.camera.width, v.camera.height
        inside = valid & np.all(np.isfinite(proj.reshape(len(proj), -1)), 1)
        lo, hi = proj.min(1), proj.max(1)
        inside &= (hi[:, 0] >= 0) & (lo[:, 0] <= W) & (hi[:, 1] >= 0) & (lo[:, 1] <= H)
        cand = others[inside]
        if not len(cand):
            continue
        M = match_segments_2d(proj[inside], L[has3d], conf.merge_max_angle, conf.merge_max_dist, conf.merge_min_overlap)
        ai, bj = np.nonzero(M)
        if not len(ai):
            continue
        a = cand[ai]
        b = idx[has3d[bj]]
        d3 = point_line_distance(lines[b], lines[a][:, None]).max(1)
        for x, y in zip(a[d3 <= conf.merge_max_3d], b[d3 <= conf.merge_max_3d]):
            rx, ry = find(x), find(y)
            if rx != ry:
                parent[max(rx, ry)] = min(rx, ry)
    roots = np.array([find(i) for i in range(n)])
    out_lines, out_obs = [], []
    for r in np.unique(roots):
        members = np.flatnonzero(roots == r)
        if len(members) == 1:
            out_lines.append(lines[members[0]])
        else:
            pts = lines[members].reshape(-1, 3)
            c, d, _ = fit_line(pts)
            tt = (pts - c) @ d
            out_lines.append(np.stack([c + tt.min() * d, c + tt.max() * d]))
        out_obs.append(sorted((o for m in members for o in obs[m]), key=lambda o: (o[0], o[1])))
    return np.array(out_lines).reshape(-1, 2, 3), out_obs


def main(scene_views: Sequence, lines_h5, out_h5, conf: Union[None, str, dict, LiftConfig] = None,
         overwrite: bool = False) -> Path:
    """Step entry: lift lines and write ``linemap.h5`` (reused when the same settings and lines made it)."""
    from .artifacts import Stamp, mapping_code_digest, read_stamp, reuse, views_key

    out_h5 = Path(out_h5)
    conf = get_conf(conf)
    lines_stamp = read_stamp(lines_h5)
    stamp = Stamp("linemap", {"method": "lift", "lift": asdict(conf), "views": views_key(scene_views),
                              "lines": lines_stamp.digest if lines_stamp else str(Path(lines_h5).resolve()),
                              "code": mapping_code_digest()})
    if reuse(out_h5, stamp, overwrite, "lift"):
        return out_h5
    logger.info("Lifting lines with %s.", json.dumps(asdict(conf)))
    return lift_linemap(scene_views, lines_h5, conf).save(out_h5, stamp=stamp)


__all__ = ["LiftConfig", "confs", "get_conf", "lift_view_lines", "lift_linemap", "main"]
