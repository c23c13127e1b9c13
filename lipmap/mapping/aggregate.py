"""The last step of a LiP-Map map: one 3D line per physical line, spanning what its track sees.

The plane edges of one physical edge come from many small planes: the global merge (paper, appendix) joins
those within ``dbscan_eps`` (1 cm), and the others stay separate lines that the track builder then finds in the
same detections. And each line keeps the extent it was made with (its plane edge, or the one detection it was
lifted from), although its track holds detections that see more of it. Here, after the tracks:

1. ``merge``: lines whose tracks share a detection and that agree in 3D (angle within ``merge_max_angle_deg``,
   each one's endpoints within ``merge_max_dist`` of the other's infinite line) become one line, fitted to their
   endpoints (length-weighted) with the union of their tracks;
2. ``extend``: each line then spans its track. Every tracked detection's endpoints are moved onto the line's
   projection in that view and cast back onto the 3D line (LIMAP's ``GetLineSegmentFromInfiniteLine3d``); the
   segment grows to the extreme values, past ``num_outliers`` of them at each end, and never shrinks below the
   extent it had;
3. ``absorb``: a line seen in one image that lies along a line seen in more (direction within
   ``absorb_max_angle_deg``, ``absorb_cover`` of its length within ``absorb_max_dist``) is that line, found once
   more by a detection the 2D track test missed (short lines' angles are noisier than its 0.01 rad): its detection
   joins that line's track, and it goes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .. import geometry as geo
from ..poses import invert_T
from .depth_lookup import depth_pixels, nearest_depth_residual


@dataclass(frozen=True)
class AggregateConfig:
    # off in every preset (--aggregate): the maps gain, and the held-out split's weak queries localize worse
    # (docs/design.md)
    enabled: bool = False
    merge: bool = True
    merge_max_angle_deg: float = 2.0
    merge_max_dist: float = 0.02  # m
    extend: bool = True
    num_outliers: int = 0  # extreme endpoint values left out at each end (LIMAP: 2, but it may also shrink a line)
    min_ray_angle_deg: float = 5.0  # an endpoint whose ray runs this close to the line's direction has no position on it
    # m: an endpoint counts only where the line's point lies this close to that view's sensor depth (0: no check);
    # among parallel lines a few px apart, a distant view's detection of a neighbour can pass the 2D track test
    extend_depth_tol: float = 0.0
    absorb: bool = True
    absorb_max_dist: float = 0.02  # m
    absorb_max_angle_deg: float = 3.0
    absorb_cover: float = 0.7  # share of the single-image line within absorb_max_dist of the other


def _rows(tracks, index: dict) -> np.ndarray:
    """(T, 3) int rows (line, view index, 2D line index) of ``tracks``."""
    rows = [(l, index[o.image_name], o.line2d_index) for l, t in enumerate(tracks) for o in t]
    return np.array(rows, dtype=np.int64).reshape(-1, 3)


def shared_detection_pairs(rows: np.ndarray) -> np.ndarray:
    """(P, 2) pairs of lines (a < b) whose tracks hold the same detection, from track ``rows`` (T, 3)."""
    if len(rows) == 0:
        return np.zeros((0, 2), np.int64)
    _, det, counts = np.unique(rows[:, 1:], axis=0, return_inverse=True, return_counts=True)
    det = det.reshape(-1)
    order = np.argsort(det, kind="stable")
    bounds = np.flatnonzero(np.diff(det[order])) + 1
    pairs = []
    for grp in np.split(order, bounds):
        if len(grp) > 1:
            ls = np.unique(rows[grp, 0])
            i, j = np.triu_indices(len(ls), 1)
            pairs.append(np.stack([ls[i], ls[j]], 1))
    return np.unique(np.concatenate(pairs), axis=0) if pairs else np.zeros((0, 2), np.int64)


def merge_groups(lines: np.ndarray, pairs: np.ndarray, max_angle_deg: float, max_dist: float) -> np.ndarray:
    """(L,) group label of each line: connected components of the ``pairs`` that agree in 3D.

    Args:
        lines: :math:`(L, 2, 3)`; pairs: :math:`(P, 2)` candidate pairs (lines sharing a detection).
    """
    n = len(lines)
    if len(pairs):
        a, b = lines[pairs[:, 0]], lines[pairs[:, 1]]
        ua, ub = a[:, 1] - a[:, 0], b[:, 1] - b[:, 0]
        cos = np.abs((ua * ub).sum(1)) / np.maximum(np.linalg.norm(ua, axis=1) * np.linalg.norm(ub, axis=1), 1e-12)
        dist = np.maximum(geo.point_line_distance(a, b[:, None]).max(1), geo.point_line_distance(b, a[:, None]).max(1))
        ok = (cos >= np.cos(np.radians(max_angle_deg))) & (dist <= max_dist)
        pairs = pairs[ok]
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def track_extents(lines: np.ndarray, rows: np.ndarray, segments: np.ndarray, views,
                  min_ray_angle_deg: float = 5.0, depth_by_view=None, depth_tol: float = 0.0) -> tuple:
    """Where each tracked detection's endpoints fall along its 3D line.

    Each endpoint is moved onto the line's projection in the detection's view (its foot on that 2D line), and the
    ray through it meets the 3D line; the value is the signed distance from the line's first endpoint (metres,
    towards the second).

    Args:
        lines: :math:`(L, 2, 3)`; rows: :math:`(T, 3)` (line, view index, 2D line index);
        segments: :math:`(T, 4)` the detections of ``rows``.

    With ``depth_tol`` > 0 and ``depth_by_view`` ({view name: (H, W) depth, 0 = invalid}), a value counts only
    where the line's point at it lies within ``depth_tol`` of the view's sensor depth (the nearest of the 3x3 pixels
    around its projection; no valid depth there: it counts).

    Returns:
        **line** :math:`(V,)` and **value** :math:`(V,)`: two per usable detection (in front of the view, the ray
        not within ``min_ray_angle_deg`` of the line).
    """
    d3 = lines[:, 1] - lines[:, 0]
    u = d3 / np.maximum(np.linalg.norm(d3, axis=1, keepdims=True), 1e-12)
    cos_max = np.cos(np.radians(min_ray_angle_deg))
    by_view = np.argsort(rows[:, 1], kind="stable")
    out_line, out_val = [], []
    for m in np.split(by_view, np.flatnonzero(np.diff(rows[by_view, 1])) + 1):
        if not len(m):
            continue
        v = views[rows[m[0], 1]]
        li = rows[m, 0]
        proj, valid = geo.project_segments(lines[li], v.cam_from_world, v.camera)
        a, b = proj[:, 0], proj[:, 1]
        dd = b - a
        dd = dd / np.maximum(np.linalg.norm(dd, axis=1, keepdims=True), 1e-9)
        q = segments[m].reshape(-1, 2, 2)
        foot = a[:, None] + ((q - a[:, None]) * dd[:, None]).sum(-1, keepdims=True) * dd[:, None]  # (M, 2, 2)
        world_from_cam = invert_T(v.cam_from_world)
        rays = geo.unproject_points(foot.reshape(-1, 2), 1.0, v.camera) @ world_from_cam[:3, :3].T  # (2M, 3)
        rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        uu = np.repeat(u[li], 2, axis=0)
        s, _ = geo.closest_point_params(np.repeat(lines[li, 0], 2, axis=0), uu, world_from_cam[:3, 3], rays)
        ok = np.repeat(valid, 2) & (np.abs((uu * rays).sum(1)) < cos_max) & np.isfinite(s)
        depth = depth_by_view.get(v.name) if (depth_tol > 0 and depth_by_view) else None
        if depth is not None and ok.any():
            X = np.repeat(lines[li, 0], 2, axis=0) + np.where(ok, s, 0.0)[:, None] * uu
            uv, z = geo.project_points(X, v.cam_from_world, v.camera)
            row, col, inside = depth_pixels(uv, z, v.camera, depth.shape)
            res = np.where(inside, nearest_depth_residual(depth, row, col, z), np.inf)
            ok &= ~np.isfinite(res) | (res <= depth_tol)
        out_line.append(np.repeat(li, 2)[ok])
        out_val.append(s[ok])
    if not out_line:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(out_line), np.concatenate(out_val)


def extended(lines: np.ndarray, line: np.ndarray, value: np.ndarray, num_outliers: int = 0) -> np.ndarray:
    """``lines`` :math:`(L, 2, 3)` grown to the extreme ``value`` of each (from :func:`track_extents`), past
    ``num_outliers`` of them at each end; a line never shrinks, and one with at most ``2 num_outliers`` values
    stays as it is."""
    out = np.array(lines, dtype=float)
    if len(value) == 0:
        return out
    order = np.lexsort((value, line))
    line, value = line[order], value[order]
    ids, start, count = np.unique(line, return_index=True, return_counts=True)
    ok = count > 2 * num_outliers
    ids, start, count = ids[ok], start[ok], count[ok]
    length = np.linalg.norm(out[ids, 1] - out[ids, 0], axis=1)
    d = (out[ids, 1] - out[ids, 0]) / np.maximum(length, 1e-12)[:, None]
    lo = np.minimum(value[start + num_outliers], 0.0)
    hi = np.maximum(value[start + count - 1 - num_outliers], length)
    p0 = out[ids, 0].copy()
    out[ids, 0] = p0 + lo[:, None] * d
    out[ids, 1] = p0 + hi[:, None] * d
    return out


def absorb_targets(lines: np.ndarray, n_images: np.ndarray, max_dist: float, max_angle_deg: float,
                   cover: float, samples: int = 11) -> np.ndarray:
    """For each line seen in one image, the line seen in more that it lies along, or -1.

    A line lies along another when their directions are within ``max_angle_deg`` and at least ``cover`` of its
    ``samples`` points lie within ``max_dist`` of the other segment; of several, the nearest on average.

    Args:
        lines: :math:`(L, 2, 3)`; n_images: :math:`(L,)` images per line.

    Returns:
        :math:`(L,)` int.
    """
    from scipy.spatial import cKDTree

    target = np.full(len(lines), -1, np.int64)
    multi, single = np.flatnonzero(n_images >= 2), np.flatnonzero(n_images == 1)
    if not len(multi) or not len(single):
        return target
    d = lines[:, 1] - lines[:, 0]
    length = np.linalg.norm(d, axis=1)
    u = d / np.maximum(length, 1e-12)[:, None]
    n_ref = 41
    ref = geo.sample_segments(lines[multi], n_ref).reshape(-1, 3)
    owner = np.repeat(multi, n_ref)
    tree = cKDTree(ref)
    radius = max_dist + 0.5 * length[multi].max() / (n_ref - 1)  # a sample of a candidate lies this close
    pts = geo.sample_segments(lines[single], samples)  # (S, n, 3)
    cos_min = np.cos(np.radians(max_angle_deg))
    for k, i in enumerate(single):
        near = tree.query_ball_point(pts[k], radius)
        cand = np.unique(owner[np.concatenate([np.asarray(h, np.int64) for h in near])])
        cand = cand[np.abs(u[cand] @ u[i]) >= cos_min]
        if not len(cand):
            continue
        dist = geo.point_segment_distance(pts[k][None], lines[cand][:, None])  # (C, n)
        ok = (dist <= max_dist).mean(1) >= cover
        if ok.any():
            target[i] = cand[ok][np.argmin(dist[ok].mean(1))]
    return target


def aggregate_linemap(lm, views, conf: AggregateConfig, depth_by_view=None):
    """``lm`` (a LiP-Map LineMap: plane edges first, then on-plane lines) merged, extended and with its single-image
    lines absorbed (module docstring); plane edges stay first, and the planes' edge -> line table follows."""
    from ..linemap import LineMap, edge_line_mask

    if not conf.enabled or len(lm) == 0:
        return lm
    index = {v.name: i for i, v in enumerate(views)}
    lines = np.asarray(lm.lines, dtype=float)
    is_edge = edge_line_mask(lm)
    n0, len0 = len(lm), float(np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1).sum())
    # 1. groups of lines that share detections and agree in 3D
    labels = (merge_groups(lines, shared_detection_pairs(_rows(lm.tracks, index)), conf.merge_max_angle_deg,
                           conf.merge_max_dist) if conf.merge else np.arange(len(lm)))
    n_groups = labels.max() + 1
    by_label = np.argsort(labels, kind="stable")
    members = np.split(by_label, np.flatnonzero(np.diff(labels[by_label])) + 1)  # members[g]: lines of group g
    g_lines, g_tracks = [], []
    for mem in members:
        if len(mem) == 1:
            seg = lines[mem[0]]
        else:
            w = np.linalg.norm(lines[mem, 1] - lines[mem, 0], axis=1)
            seg = geo.fit_segment(lines[mem].reshape(-1, 3), np.repeat(w, 2))
        g_lines.append(seg)
        g_tracks.append({(o.image_name, o.line2d_index): o for m in mem for o in lm.tracks[m]})
    g_lines = np.array(g_lines, dtype=float).reshape(-1, 2, 3)
    g_edge = np.zeros(n_groups, bool)
    np.logical_or.at(g_edge, labels, is_edge)
    # 2. each spans its track
    if conf.extend:
        tracks = [list(t.values()) for t in g_tracks]
        rows = _rows(tracks, index)
        segs = np.array([o.segment for t in tracks for o in t], dtype=float).reshape(-1, 4)
        g_lines = extended(g_lines, *track_extents(g_lines, rows, segs, views, conf.min_ray_angle_deg, depth_by_view,
                                                   conf.extend_depth_tol), conf.num_outliers)
    # 3. a line seen in one image along one seen in more is that line, seen once more
    target = np.full(n_groups, -1, np.int64)
    if conf.absorb:
        n_img = np.array([len({k[0] for k in t}) for t in g_tracks])
        target = absorb_targets(g_lines, n_img, conf.absorb_max_dist, conf.absorb_max_angle_deg, conf.absorb_cover)
        for g in np.flatnonzero(target >= 0):
            g_tracks[target[g]].update(g_tracks[g])
            g_edge[target[g]] |= g_edge[g]
    kept = np.flatnonzero(target < 0)
    # plane edges first (the planes' table points at them), each kind in the order of its first member
    first = np.array([m[0] for m in members])
    order = kept[np.lexsort((first[kept], ~g_edge[kept]))]
    new_of_group = np.full(n_groups, -1, np.int64)
    new_of_group[order] = np.arange(len(order))
    new_of_group[target >= 0] = new_of_group[target[target >= 0]]
    new_id = new_of_group[labels]
    out_lines = g_lines[order]
    out_tracks = [[g_tracks[g][k] for k in sorted(g_tracks[g])] for g in order]
    planes = lm.planes
    if planes is not None and "edge_line" in planes:
        el = np.asarray(planes["edge_line"])
        planes = {**planes, "edge_line": np.where(el >= 0, new_id[np.clip(el, 0, None)], -1)}
    meta = dict(lm.metadata)
    n_edges = int(g_edge[order].sum())
    meta.update({"n_edge_lines": n_edges, "n_on_plane_lines": len(order) - n_edges,
                 "aggregate": {"lines_before": n0, "merged_groups": int(n_groups), "absorbed": int((target >= 0).sum()),
                               "lines_after": len(order), "length_before_m": len0,
                               "length_after_m": float(np.linalg.norm(out_lines[:, 1] - out_lines[:, 0], axis=1).sum())}})
    return LineMap(out_lines, out_tracks, planes=planes, metadata=meta)
