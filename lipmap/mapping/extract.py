"""Line extraction after optimization (paper Sec. 3.4): accepted plane edges, merging, track building.

1. ``extract_observations``: every pixel of every 1-pixel region is cast against the planes; the hit
   plane's best edge is kept when its projection is within ``max_dist`` px and ``max_angle`` rad of
   the detected line (paper: 1 px, 0.01 rad).
2. ``merge_edges``: the accepted edges become 3D lines - one per edge (``none``), one per detected line
   (``local``), or the paper's global merge: per detected line DBSCAN over its edges, identifiers
   propagated through shared edges, one PCA-fitted segment per group (``global``).
3. ``build_tracks``: the paper's track builder - a line is tracked in a view by every detected segment
   its projection matches (angle < 0.01 rad, distance < 2 px, overlap > 0.2), if not occluded.
4. ``verify_tracks``: the finished map's tracks keep only the detections that pass that test against the line
   as it ends: a line's supports are the paper's, whatever made the line or moved it since.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from tqdm import tqdm

from .. import geometry as geo
from .assign import PlaneRaycaster, assign_lines, corner_edges
from .depth_lookup import depth_pixels, nearest_depth_residual


@dataclass
class ExtractConfig:
    max_dist: float = 1.0  # px, paper tau_d for extraction
    max_angle: float = 0.01  # rad, paper tau_alpha
    dist_reduce: str = "max"  # of the two endpoint distances: "max" (the paper's d_orth), "mean" (reference code)
    merge: str = "global"  # none | local | global
    dbscan_eps: float = 0.01  # m, paper tau_dbscan
    # the global merge's groups: "components" (ours: DBSCAN over the symmetrised distance, then the connected
    # components of the edges that share a cluster, so groups join through shared edges) or "reference" (its
    # forward_global_3dlines_theta_dist: DBSCAN over the one-sided distance, the detections in order; a cluster's
    # new edges take a new group, or the group of one of its edges already grouped; groups never join)
    global_rule: str = "components"
    track_max_angle: float = 0.01
    track_max_dist: float = 2.0
    track_min_overlap: float = 0.2
    occlusion_tol: float = 0.05  # relative depth tolerance of the visibility test
    # a pixel in several lines' regions votes for the nearest line only (reference: its attraction field labels each
    # pixel with one line); off: for each
    exclusive_pixels: bool = False
    min_views: int = 1  # drop merged lines seen in fewer mapping views
    min_length: float = 0.02  # m
    # Drop a line whose median |line depth - sensor depth| over its tracked views exceeds this (m);
    # 0 disables. Not in the paper: planes that float a few cm off the surface (weakly observed, or
    # bent by the line term) yield edges that pass the 2D tests but sit off the geometry.
    max_depth_residual: float = 0.0


def extract_observations(corners, views, lines_by_view: dict, conf: ExtractConfig, progress: bool = True) -> dict:
    """Accepted (view, detected line, plane, edge) observations over all views.

    Args:
        corners: :math:`(K, 4, 3)` numpy plane corners.
        views: views with ``name``, ``camera``, ``cam_from_world``.
        lines_by_view: {view name: (N, 4) detected segments in that view's camera pixels}.

    Returns:
        dict of equal-length int arrays ``view``, ``line``, ``plane``, ``edge`` (unique rows) and
        ``n_pixels`` (how many region pixels voted for that row).
    """
    caster = PlaneRaycaster(corners)
    rows = []
    for vi, v in enumerate(tqdm(views, desc="extract lines", disable=not progress, leave=False)):
        lines = np.asarray(lines_by_view.get(v.name, np.zeros((0, 4))), dtype=float)
        if len(lines) == 0:
            continue
        a = assign_lines(caster, corners, lines, v.cam_from_world, v.camera, dist_reduce=conf.dist_reduce,
                         exclusive=conf.exclusive_pixels)
        ok = (a["angle"] <= conf.max_angle) & (a["dist"] <= conf.max_dist)
        if ok.any():
            rows.append(np.stack([np.full(ok.sum(), vi), a["line"][ok], a["plane"][ok], a["edge"][ok]], 1))
    if not rows:
        z = np.zeros(0, dtype=np.int64)
        return {"view": z, "line": z, "plane": z, "edge": z, "n_pixels": z}
    allr = np.concatenate(rows).astype(np.int64)
    uniq, counts = np.unique(allr, axis=0, return_counts=True)
    return {"view": uniq[:, 0], "line": uniq[:, 1], "plane": uniq[:, 2], "edge": uniq[:, 3], "n_pixels": counts}


def _pca_segment(points: np.ndarray) -> np.ndarray:
    """Segment (2, 3) spanning points along their principal direction."""
    c = points.mean(0)
    if len(points) < 2:
        return np.stack([c, c])
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    d = vt[0]
    t = (points - c) @ d
    return np.stack([c + t.min() * d, c + t.max() * d])


def _edge_distance_matrix(edges: np.ndarray, n: int = 10, symmetric: bool = True) -> np.ndarray:
    """Mean perpendicular distance between 3D edges (M, 2, 3) -> (M, M), by sampling n points: entry (a, b) from
    the points of a to the line of b, or with ``symmetric`` the mean of (a, b) and (b, a)."""
    pts = geo.sample_segments(edges, n)  # (M, n, 3)
    p0 = edges[:, 0]
    d = edges[:, 1] - p0
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    rel = pts[:, None] - p0[None, :, None]  # (M_a, M_b, n, 3) points of a vs line of b
    perp = rel - (rel * d[None, :, None]).sum(-1, keepdims=True) * d[None, :, None]
    D = np.linalg.norm(perp, axis=-1).mean(-1)
    return 0.5 * (D + D.T) if symmetric else D


def _reference_groups(det_groups, e_of_obs, E, eps: float) -> np.ndarray:
    """The group of each edge by the reference's global merge: each detection's edges (in order of the detections)
    clustered by DBSCAN (min_samples 1) over the one-sided distance; a cluster none of whose edges is grouped yet
    takes a new group, otherwise its new edges join the group of its last grouped edge (by edge id). Existing groups
    are never joined together."""
    from sklearn.cluster import DBSCAN

    group = np.full(len(E), -1, dtype=np.int64)
    n_groups = 0
    for grp in det_groups:
        es = np.unique(e_of_obs[grp])
        labels = np.zeros(len(es), dtype=np.int64) if len(es) == 1 else \
            DBSCAN(eps=eps, min_samples=1, metric="precomputed").fit_predict(_edge_distance_matrix(E[es], symmetric=False))
        for lab in np.unique(labels):
            members = es[labels == lab]
            old = members[group[members] >= 0]
            if len(old) == 0:
                group[members] = n_groups
                n_groups += 1
            else:
                group[members[group[members] < 0]] = group[old[-1]]
    return group


def merge_edges(corners, obs: dict, conf: ExtractConfig):
    """Turn accepted plane edges into 3D lines.

    Returns:
        **lines** :math:`(L, 2, 3)`, **obs_line** :math:`(O,)` the line of each observation, and
        **edge_line** :math:`(K, 4)` the line each plane edge belongs to (-1: none).
    """
    K = len(corners)
    edge_line = np.full((K, 4), -1, dtype=np.int64)
    if len(obs["plane"]) == 0:
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=np.int64), edge_line
    all_edges = corner_edges(np.asarray(corners, dtype=float))  # (K, 4, 2, 3)
    eid = obs["plane"] * 4 + obs["edge"]
    uniq_e, e_of_obs = np.unique(eid, return_inverse=True)
    E = all_edges.reshape(-1, 2, 3)[uniq_e]
    det_key = obs["view"] * 1_000_000 + obs["line"]
    _, det_of_obs = np.unique(det_key, return_inverse=True)

    if conf.merge == "none":
        group_of_edge = np.arange(len(uniq_e))
    elif conf.merge in ("local", "global"):
        from sklearn.cluster import DBSCAN

        order = np.argsort(det_of_obs, kind="stable")
        bounds = np.flatnonzero(np.diff(det_of_obs[order])) + 1
        if conf.merge == "global" and conf.global_rule == "reference":
            group_of_edge = _reference_groups(np.split(order, bounds), e_of_obs, E, conf.dbscan_eps)
            return _grouped(E, group_of_edge, e_of_obs, uniq_e, obs, edge_line, conf)
        if conf.global_rule not in ("components", "reference"):
            raise ValueError(f"unknown global merge rule {conf.global_rule!r}")
        src, dst = [], []
        local_lines, local_obs = [], []
        for grp in np.split(order, bounds):
            es = np.unique(e_of_obs[grp])
            if conf.merge == "local":
                local_lines.append(_pca_segment(E[es].reshape(-1, 3)))
                local_obs.append(grp)
                continue
            if len(es) == 1:
                continue
            labels = DBSCAN(eps=conf.dbscan_eps, min_samples=1, metric="precomputed").fit_predict(_edge_distance_matrix(E[es]))
            for lab in np.unique(labels):
                members = es[labels == lab]
                src.extend(members[:-1])
                dst.extend(members[1:])
        if conf.merge == "local":
            lines = np.stack(local_lines)
            obs_line = np.empty(len(eid), dtype=np.int64)
            for li, grp in enumerate(local_obs):
                obs_line[grp] = li
            return _finish(lines, obs_line, obs, edge_line, conf, allow_edge_conflicts=True)
        n = len(uniq_e)
        g = coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
        _, group_of_edge = connected_components(g, directed=False)
    else:
        raise ValueError(f"unknown merge mode {conf.merge!r}")

    return _grouped(E, group_of_edge, e_of_obs, uniq_e, obs, edge_line, conf)


def _grouped(E, group_of_edge, e_of_obs, uniq_e, obs, edge_line, conf):
    """One PCA-fitted line per group of edges; the observations and the edge table follow their edge's group."""
    n_groups = group_of_edge.max() + 1
    lines = np.stack([_pca_segment(E[group_of_edge == gi].reshape(-1, 3)) for gi in range(n_groups)])
    obs_line = group_of_edge[e_of_obs]
    edge_line.reshape(-1)[uniq_e] = group_of_edge
    return _finish(lines, obs_line, obs, edge_line, conf)


def _finish(lines, obs_line, obs, edge_line, conf, allow_edge_conflicts=False):
    """Drop short lines and lines seen in too few views; renumber."""
    n_views = np.zeros(len(lines), dtype=np.int64)
    pairs = np.unique(np.stack([obs_line, obs["view"]], 1), axis=0)
    np.add.at(n_views, pairs[:, 0], 1)
    length = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    keep = (n_views >= conf.min_views) & (length >= conf.min_length)
    new_id = np.full(len(lines), -1, dtype=np.int64)
    new_id[keep] = np.arange(keep.sum())
    if allow_edge_conflicts:
        for l_old in np.flatnonzero(keep):
            m = obs_line == l_old
            edge_line[obs["plane"][m], obs["edge"][m]] = new_id[l_old]
    else:
        flat = edge_line.reshape(-1)
        flat[flat >= 0] = new_id[flat[flat >= 0]]
    return lines[keep], new_id[obs_line], edge_line


def visible_mask(points_world: np.ndarray, view, depth: np.ndarray | None, tol: float) -> np.ndarray:
    """Which points (N, 3) are in view and not occluded according to the view's depth map (0: unknown)."""
    uv, z = geo.project_points(points_world, view.cam_from_world, view.camera)
    W, H = view.camera.width, view.camera.height
    inside = (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    if depth is None:
        return inside
    row, col, _ = depth_pixels(uv, z, view.camera, depth.shape)
    d = depth[row, col]
    return inside & ((d <= 0) | (z <= d * (1 + tol) + 0.02))


def depth_residuals(lines: np.ndarray, tracks: np.ndarray, views, depth_by_view: dict, n: int = 16) -> np.ndarray:
    """Median disagreement between each line and the sensor depth of the views that track it.

    Each line is sampled at ``n`` points; in every tracked view with a depth map, a sample's residual is
    the smallest |z - depth| over the 3x3 pixels around its projection (an occluding edge sits on a
    depth step, so one side of it must agree).

    Args:
        lines: :math:`(L, 2, 3)`; tracks: :math:`(T, 3)` (line, view index, 2D line index).
        depth_by_view: {view name: (H, W) metric depth, 0 = invalid}.

    Returns:
        :math:`(L,)` median residual in metres; NaN where no tracked view has valid depth there.
    """
    out = np.full(len(lines), np.nan)
    if len(lines) == 0 or len(tracks) == 0:
        return out
    samples = geo.sample_segments(lines, n)
    pairs = np.unique(tracks[:, :2], axis=0)
    per_line = [[] for _ in range(len(lines))]
    for vi in np.unique(pairs[:, 1]):
        v = views[vi]
        depth = depth_by_view.get(v.name) if depth_by_view else None
        if depth is None:
            continue
        ids = pairs[pairs[:, 1] == vi, 0]
        uv, z = geo.project_points(samples[ids].reshape(-1, 3), v.cam_from_world, v.camera)
        row, col, inside = depth_pixels(uv, z, v.camera, depth.shape)
        best = np.where(inside, nearest_depth_residual(depth, row, col, z), np.inf).reshape(len(ids), n)
        for li, r in zip(ids, best):
            per_line[li].append(r[np.isfinite(r)])
    for li, rs in enumerate(per_line):
        r = np.concatenate(rs) if rs else np.zeros(0)
        if len(r):
            out[li] = np.median(r)
    return out


def build_tracks(lines: np.ndarray, views, lines_by_view: dict, conf: ExtractConfig, depth_by_view=None,
                 progress: bool = True, caster=None):
    """The paper's track builder: (line, view, detected-line) triples where the projection matches.

    A line is looked for in every view that sees it - in front of the camera, inside the image and not
    hidden: by the planes when ``caster`` (the planes' :class:`~lipmap.mapping.assign.PlaneRaycaster`) is
    given, else by the view's depth map - and tracked by every detected segment its projection matches by
    the paper's angle, distance and overlap thresholds (``conf.track_*``).

    Returns:
        int array :math:`(T, 3)` of (line id, view index, 2D line index).
    """
    from .assign import visible_lines

    out = []
    lines = np.asarray(lines, dtype=float).reshape(-1, 2, 3)
    samples = geo.sample_segments(lines, 5) if len(lines) and caster is None else None
    for vi, v in enumerate(tqdm(views, desc="build tracks", disable=not progress, leave=False)):
        det = np.asarray(lines_by_view.get(v.name, np.zeros((0, 4))), dtype=float)
        if len(det) == 0 or len(lines) == 0:
            continue
        if caster is not None:
            cand = visible_lines(lines, v.cam_from_world, v.camera, caster, conf.occlusion_tol)
        else:
            depth = None if depth_by_view is None else depth_by_view.get(v.name)
            vis = visible_mask(samples.reshape(-1, 3), v, depth, conf.occlusion_tol).reshape(len(lines), -1)
            cand = np.flatnonzero(vis.sum(1) >= 3)
        if len(cand) == 0:
            continue
        proj, valid = geo.project_segments(lines[cand], v.cam_from_world, v.camera)
        m = geo.match_segments_2d(proj, det, conf.track_max_angle, conf.track_max_dist, conf.track_min_overlap)
        m &= valid[:, None]
        li, di = np.nonzero(m)
        out.append(np.stack([cand[li], np.full(len(li), vi), di], 1))
    if not out:
        return np.zeros((0, 3), dtype=np.int64)
    return np.unique(np.concatenate(out).astype(np.int64), axis=0)


def add_tracks(linemap, views, lines_by_view: dict, conf: ExtractConfig, caster=None, depth_by_view=None,
               which: np.ndarray | None = None):
    """``linemap`` with the track builder's observations (:func:`build_tracks`) added to the tracks of the lines
    ``which`` (default: all); the evidence already in the tracks is kept; supports are recounted."""
    from ..linemap import LineMap

    idx = np.arange(len(linemap)) if which is None else np.asarray(which, dtype=np.int64)
    if len(idx) == 0:
        return linemap
    rows = build_tracks(linemap.lines[idx], views, lines_by_view, conf, depth_by_view, caster=caster)
    tracks = [list(t) for t in linemap.tracks]
    have = [{(o[0], int(o[1])) for o in t} for t in tracks]
    for l, vi, di in rows:
        line, name = int(idx[l]), views[vi].name
        if (name, int(di)) not in have[line]:
            have[line].add((name, int(di)))
            tracks[line].append((name, int(di), lines_by_view[name][di]))
    tracks = [sorted(t, key=lambda o: (o[0], int(o[1]))) for t in tracks]
    return LineMap(linemap.lines, tracks, planes=linemap.planes, metadata=dict(linemap.metadata))


def track_test(projected, detected, conf: ExtractConfig) -> np.ndarray:
    """The track builder's test (:func:`lipmap.geometry.match_segments_2d` at ``conf.track_*``) for given pairs:
    (..., 2, 2) x (..., 2, 2) -> (...) bool; invalid (NaN) projections match nothing. (Here, not in geometry.py:
    that file is part of the planes' stamp, and a new helper there would re-optimize every cached plane set.)"""
    p, d = geo.as_segments2d(projected), geo.as_segments2d(detected)
    with np.errstate(invalid="ignore"):
        return ((geo.angle_distance(p, d) < conf.track_max_angle)
                & (geo.perpendicular_distance(p, d, "max") < conf.track_max_dist)
                & (geo.overlap_ratio(p, d) > conf.track_min_overlap))


def verify_tracks(linemap, views, conf: ExtractConfig):
    """``linemap`` with each track cut to the observations whose detection passes the track builder's test
    (``conf.track_*``) against the line's final projection in that view.

    A track also holds the evidence that made its line (extraction votes at the extraction gate, the detection an
    on-plane line was lifted from) and matches made before a refinement moved the line; without this step they
    would count as supports (M2) where they no longer agree with the line. A line none agrees with keeps its place
    with support 0. Observations of images not among ``views`` are kept untested (imported tracks).
    """
    from ..linemap import LineMap

    rows = [(l, o) for l, t in enumerate(linemap.tracks) for o in t]
    if not rows:
        return linemap
    view_of = {v.name: v for v in views}
    keep = np.ones(len(rows), dtype=bool)
    by_view = {}
    for i, (_, o) in enumerate(rows):
        if o.image_name in view_of:
            by_view.setdefault(o.image_name, []).append(i)
    for name, idx in by_view.items():
        v = view_of[name]
        proj, valid = geo.project_segments(linemap.lines[[rows[i][0] for i in idx]], v.cam_from_world, v.camera)
        det = np.stack([np.asarray(rows[i][1].segment, dtype=float).reshape(2, 2) for i in idx])
        keep[idx] = valid & track_test(proj, det, conf)
    tracks = [[] for _ in range(len(linemap))]
    for (l, o), k in zip(rows, keep):
        if k:
            tracks[l].append(o)
    meta = {**linemap.metadata, "n_unverified_observations": int((~keep).sum())}
    return LineMap(linemap.lines, tracks, planes=linemap.planes, metadata=meta)
