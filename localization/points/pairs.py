"""Covisible pairs of mapping images from their known poses (frustum overlap and viewing angle), for triangulation."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from lipmap import logger

from .. import hloc_io
from .config import PairsConfig


def frustum_overlap(view_a, view_b, conf: Optional[PairsConfig] = None) -> float:
    """Fraction of a grid of ``view_a``'s pixels, at nominal depths, that ``view_b`` sees in its image."""
    return float(_overlap_matrix([view_a, view_b], conf or PairsConfig())[0, 1])


def _view_samples(views, conf: PairsConfig) -> list:
    """Each view's grid of pixel rays at the nominal depths, in the world frame: (S, 3) per view."""
    from lipmap.poses import invert_T

    gx, gy = conf.grid
    samples = []
    for v in views:
        cam = v.camera
        u = (np.arange(gx) + 0.5) / gx * cam.width
        w = (np.arange(gy) + 0.5) / gy * cam.height
        uu, ww = np.meshgrid(u, w)
        rays = np.stack([(uu - cam.cx) / cam.fx, (ww - cam.cy) / cam.fy, np.ones_like(uu)], -1).reshape(-1, 3)
        pts_cam = np.concatenate([rays * d for d in conf.depths])
        T = invert_T(v.cam_from_world)
        samples.append(pts_cam @ T[:3, :3].T + T[:3, 3])
    return samples


def _overlap_from(samples_i: np.ndarray, view_j) -> np.ndarray:
    """Fraction of each set of samples (..., S, 3) that ``view_j`` sees inside its image: (...,)."""
    from lipmap.geometry import project_points

    uv, z = project_points(samples_i, view_j.cam_from_world, view_j.camera)
    cam = view_j.camera
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height)
    return inside.mean(-1)


def _overlap_matrix(views, conf: PairsConfig) -> np.ndarray:
    """Dense (N, N) frustum overlap, ov[i, j] = fraction of i's samples j sees; the reference for
    :func:`pairs_from_poses`' pruned search (O(N^2) projections)."""
    samples = _view_samples(views, conf)
    n = len(views)
    ov = np.eye(n)
    for j, vj in enumerate(views):
        for i in range(n):
            if i == j:
                continue
            ov[i, j] = _overlap_from(samples[i], vj)
    return ov


def _frustum_bounds(views, samples):
    """Per view: centre (3,), optical axis (3,), half-angle of the cone around the axis that holds
    the image (its widest corner) and the farthest sample from the centre."""
    centres = np.stack([_centre(v) for v in views])
    axes = np.stack([v.cam_from_world[2, :3] for v in views])
    half = []
    for v in views:
        cam = v.camera
        x = np.array([0.0, cam.width]) - cam.cx
        y = np.array([0.0, cam.height]) - cam.cy
        r = np.hypot(x[:, None] / cam.fx, y[None, :] / cam.fy).max()
        half.append(np.arctan(r))
    reach = np.array([np.linalg.norm(s - c, axis=1).max() for s, c in zip(samples, centres)])
    return centres, axes, np.array(half), reach


def _centre(view) -> np.ndarray:
    T = view.cam_from_world
    return -T[:3, :3].T @ T[:3, 3]


def _ball_meets_cone(mid, radius, apex, axis, half) -> np.ndarray:
    """Whether balls (mid, radius) can meet the infinite cones (apex, unit axis, half-angle); arrays
    of pairs. Conservative (1e-6 rad slack): a False is certain."""
    w = mid - apex
    dist = np.linalg.norm(w, axis=1)
    cosb = np.einsum("ij,ij->i", w, axis) / np.maximum(dist, 1e-12)
    beta = np.arccos(np.clip(cosb, -1, 1))
    spread = np.arcsin(np.clip(radius / np.maximum(dist, 1e-12), 0, 1))
    return (dist <= radius) | (beta <= half + spread + 1e-6)


def _candidate_pairs(views, samples, conf: PairsConfig, block: int = 512):
    """Pairs (i < j) that may pass the exact test, in blocks of i: an iterator of (I, J) arrays.

    A pair is kept by the exact test only if each view sees some of the other's samples (overlap
    >= min_overlap > 0 both ways) and their axes are within ``max_angle_deg``. A sample s_j of
    view j inside view i's image lies in i's cone (half-angle t_i to the widest image corner), and
    s_j is within R_j (the farthest sample, ~ the largest depth) of j's centre; likewise for i.
    With d = c_j - c_i and L = |d| this gives d.a_i >= (L - R_j) cos t_i - R_j and
    -d.a_j >= (L - R_i) cos t_j - R_i; their sum is at most L |a_i - a_j| <= 2 L sin(max_angle / 2),
    so  L <= 2 R / (cos t - sin(max_angle / 2))  with R the largest reach and t the widest cone.
    Candidates are the centres within that radius (a cKDTree), then the axis angle, then whether
    each view's sample ball can meet the other's cone at all. When the radius is unbounded
    (wide cones, large angles) or min_overlap <= 0 every pair of each block is a candidate.
    """
    from scipy.spatial import cKDTree

    n = len(views)
    centres, axes, half, reach = _frustum_bounds(views, samples)
    mids = np.stack([s.mean(0) for s in samples])
    balls = np.array([np.linalg.norm(s - m, axis=1).max() for s, m in zip(samples, mids)])
    denom = np.cos(half.max()) - np.sin(np.radians(min(conf.max_angle_deg, 180.0)) / 2)
    prune = conf.min_overlap > 0
    radius = 2 * reach.max() / denom * (1 + 1e-9) + 1e-9 if prune and denom > 0 else np.inf
    tree = cKDTree(centres) if np.isfinite(radius) else None
    cos_max = np.cos(np.radians(conf.max_angle_deg)) - 1e-9
    for start in range(0, n, block):
        rows = np.arange(start, min(n, start + block))
        if tree is None:
            I, J = np.triu_indices(n, 1)
            keep = (I >= start) & (I < rows[-1] + 1)
            I, J = I[keep], J[keep]
        else:
            near = tree.query_ball_point(centres[rows], radius)
            I = np.repeat(rows, [len(x) for x in near])
            J = np.concatenate([np.asarray(x, np.int64) for x in near]) if len(I) else np.zeros(0, np.int64)
            keep = J > I
            I, J = I[keep], J[keep]
        keep = np.einsum("ij,ij->i", axes[I], axes[J]) >= cos_max
        I, J = I[keep], J[keep]
        if prune:
            keep = _ball_meets_cone(mids[I], balls[I], centres[J], axes[J], half[J])
            keep &= _ball_meets_cone(mids[J], balls[J], centres[I], axes[I], half[I])
            I, J = I[keep], J[keep]
        yield I, J


def _top_per_row(rows, cols, vals, k):
    """Keep each row's k best (value descending, then column) of sparse (row, col, value) triples."""
    order = np.lexsort((cols, -vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    first = np.searchsorted(rows, rows, side="left")
    keep = np.arange(len(rows)) - first < k
    return rows[keep], cols[keep], vals[keep]


def pairs_from_poses(views: Sequence, out_path=None, conf: Optional[PairsConfig] = None) -> list[tuple[str, str]]:
    """Covisible pairs of posed images: for each image its ``num_neighbors`` best partners by
    symmetric frustum overlap (min of both directions), among those within ``max_angle_deg`` of
    viewing direction and with overlap >= ``min_overlap``. Each unordered pair is listed once, in
    the order of ``views``. Written as an hloc pairs file when ``out_path`` is given.

    The exact overlap is computed only for candidate pairs that can pass it (:func:`_candidate_pairs`:
    nearby centres, close axes, frusta that can meet), so the cost is ~N x the neighbours within
    reach rather than N^2, and memory stays ~N x num_neighbors; the pairs equal those of the dense
    test over every pair (:func:`_overlap_matrix`)."""
    conf = conf or PairsConfig()
    n = len(views)
    samples = _view_samples(views, conf)
    stack = np.stack(samples) if n else np.zeros((0, 0, 3))
    dirs = np.stack([v.cam_from_world[2, :3] for v in views]) if n else np.zeros((0, 3))
    k = conf.num_neighbors
    rows = np.zeros(0, np.int64)
    cols = np.zeros(0, np.int64)
    vals = np.zeros(0)
    n_cand = 0
    for I, J in _candidate_pairs(views, samples, conf) if n > 1 else ():
        n_cand += len(I)
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", dirs[I], dirs[J]), -1, 1)))
        I, J = I[ang <= conf.max_angle_deg], J[ang <= conf.max_angle_deg]
        ov_ij = np.empty(len(I))
        ov_ji = np.empty(len(I))
        for j in np.unique(J):  # i's samples seen by j
            sel = J == j
            ov_ij[sel] = _overlap_from(stack[I[sel]], views[j])
        for i in np.unique(I):  # j's samples seen by i
            sel = I == i
            ov_ji[sel] = _overlap_from(stack[J[sel]], views[i])
        sym = np.minimum(ov_ij, ov_ji)
        ok = sym >= conf.min_overlap
        I, J, sym = I[ok], J[ok], sym[ok]
        rows, cols, vals = np.concatenate([rows, I, J]), np.concatenate([cols, J, I]), np.concatenate([vals, sym, sym])
        rows, cols, vals = _top_per_row(rows, cols, vals, k)
    rows, cols, _ = _top_per_row(rows, cols, vals, k)
    chosen = set(zip(np.minimum(rows, cols).tolist(), np.maximum(rows, cols).tolist()))
    pairs = [(views[i].name, views[j].name) for i, j in sorted(chosen)]
    logger.info("%d covisible pairs among %d posed images (%d candidate pairs tested).", len(pairs), n, n_cand)
    if out_path is not None:
        hloc_io.write_pairs(out_path, pairs)
    return pairs


def _pairs_from_poses_dense(views: Sequence, conf: Optional[PairsConfig] = None) -> list[tuple[str, str]]:
    """The former all-pairs :func:`pairs_from_poses` (O(N^2) projections): the reference in tests
    and benchmarks."""
    conf = conf or PairsConfig()
    n = len(views)
    ov = _overlap_matrix(views, conf)
    sym = np.minimum(ov, ov.T)
    dirs = np.stack([v.cam_from_world[2, :3] for v in views])  # optical axes in the world frame
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))
    ok = (sym >= conf.min_overlap) & (ang <= conf.max_angle_deg) & ~np.eye(n, dtype=bool)
    chosen = set()
    for i in range(n):
        cand = np.flatnonzero(ok[i])
        # stable order: overlap descending, then index
        cand = cand[np.lexsort((cand, -sym[i, cand]))][: conf.num_neighbors]
        for j in cand:
            chosen.add((min(i, j), max(i, j)))
    return [(views[i].name, views[j].name) for i, j in sorted(chosen)]
