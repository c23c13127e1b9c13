"""Poses from lines where the point matches are too few for P3P, or too few to outvote their noise (a P3P pose of
three right matches lies tens of cm off as often as not): the rotation from the query's vanishing points,
aligned with the map's dominant line directions near a retrieved image's rotation, then the translation voted by
the line correspondences that rotation allows, along the ray of a point match.

An indoor map's lines run along a few directions, and a query's long lines meet at their vanishing points. A
retrieved image's rotation (some degrees off) says which map direction a vanishing point is; aligning them leaves
the rotation about that axis, which the query's lines through the other directions' vanishing points fix (a 1D
search). With the rotation known, a 2D line and a 3D line of the same direction are one linear constraint on the
translation: ``n . (R X + t) = 0`` for the line's interpretation-plane normal ``n`` and any point ``X`` of the 3D line.
Along the ray of one point match, ``t = d b - R X_p``, each such pair gives one depth ``d``; the right pairs agree on
it, the wrong ones scatter, so a histogram of the depths finds the translation. Without a point match, the pairs
of the direction most of the query's lines run along are lines in the plane across that direction, where they meet
at the camera centre (a 2D histogram around the retrieved image's centre); the pairs of the other directions then
vote for where along it. The poses join the P3P ones in the line scoring of :mod:`localization.hypotheses`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lipmap import geometry as geo
from lipmap.poses import camera_center, make_T, rotation_between


@dataclass
class LinesFirstConfig:
    # a query with fewer point matches than this also gets poses from lines (0: never). With ten matches P3P's
    # triples of right ones lie tens of cm off as often as not (their points' noise), and these poses still find
    # the room (held-out split, 10 matches: per query 43 better / 16 worse than with them below 6; docs/localization.md)
    below: int = 11
    views: int = 3  # the retrieved images whose rotations place the vanishing points among the map's directions
    max_prior_deg: float = 30.0  # a vanishing point within this of a map direction under a view's rotation is that one
    min_length_px: float = 40.0  # query lines that vote (the vanishing points' lines are HypothesisConfig's)
    line_tol_deg: float = 1.5  # a query line contains a direction when its interpretation plane does, within this
    step_deg: float = 0.25  # the search about the first vanishing point's axis
    # the turn about that axis is weighted by a Gaussian of this width (deg) around the view's own: the votes of the
    # other directions' lines are few, and a chance peak far from every view outvoted the right turn (0: unweighted)
    turn_sigma_deg: float = 10.0
    turns: int = 1  # the best-voted turns kept per view and vanishing point, at least 3 deg apart
    depth_range: tuple = (0.3, 8.0)  # m, the depths of a point match voted over
    depth_bin: float = 0.02  # m
    peaks: int = 4  # best-voted cells kept per rotation and ray (per stage without a point match): the line scoring picks
    search_m: float = 2.0  # without a point match: the camera centre is sought this far around the retrieved image's
    centre_bin: float = 0.05  # m, that search's histogram across the main direction
    min_projected_share: float = 0.3  # ... where a map line votes only if it projects at least this share of the detection
    # with fewer point matches than this, the retrieved image's own centre also stands with each rotation (0: never).
    # Without a match the centre vote misses even beside a view, and with one or two a wrong match's ray leads the
    # votes astray, while the line scoring tells a view's centre apart (held-out split: 0 matches 4 -> 12 % within
    # 5 cm / 5 deg, 1 match 34 -> 36 %; docs/localization.md, `-view-centres`)
    view_centres_below: int = 3


def interpretation_normals(lines2d: np.ndarray, camera) -> tuple:
    """Unit normals :math:`(M, 3)` of the planes through the camera centre and each segment (camera frame), and the
    segments' lengths (px)."""
    L = np.asarray(lines2d, dtype=float).reshape(-1, 4)
    if len(L) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    n = geo.backprojected_planes(L, geo.projection_matrices(np.eye(4), camera))[:, :3]
    return n / np.linalg.norm(n, axis=1, keepdims=True), geo.segment_lengths(L)


def _about(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations :math:`(A, 3, 3)` by ``angle`` (A,) radians about the unit ``axis``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(angle)[:, None] * axis[None]).as_matrix()


def vp_rotations(normals: np.ndarray, weights: np.ndarray, vps: np.ndarray, directions: np.ndarray,
                 priors: list, conf: LinesFirstConfig) -> list:
    """Rotations (cam_from_world, 3 x 3) that take a map direction onto a vanishing point near each prior's rotation,
    turned about that axis to put the query's lines through the other directions' vanishing points.

    Args:
        normals, weights: the query lines' interpretation normals :math:`(M, 3)` and their weights (length).
        vps: :math:`(V, 3)` the query's vanishing points (camera frame, sign arbitrary); directions: :math:`(K, 3)`.
        priors: rotations or poses ((3, 3) or (4, 4)) the rotation lies near (within ``conf.max_prior_deg``).

    Returns:
        list of ((3, 3), index of its prior), at most one per (prior, vanishing point), without repeats.
    """
    out = []
    tol = np.sin(np.radians(conf.line_tol_deg))
    cos_prior = np.cos(np.radians(conf.max_prior_deg))
    half = np.radians(conf.max_prior_deg)
    angles = np.arange(-half, half + 1e-12, np.radians(conf.step_deg))
    for i, P in enumerate(priors):
        R0 = np.asarray(P, dtype=float)[:3, :3]
        pred = directions @ R0.T  # the map directions in the camera frame under the prior
        for v in vps:
            c = pred @ v
            k = int(np.argmax(np.abs(c)))
            if abs(c[k]) < cos_prior:
                continue
            R1 = rotation_between(pred[k], np.sign(c[k]) * v) @ R0
            others = np.delete(directions, k, axis=0) @ R1.T  # (K-1, 3), turned about v below
            if len(others) == 0 or len(normals) == 0:
                out.append((R1, i))
                continue
            Ra = _about(v, angles)  # (A, 3, 3)
            score = turn_votes(Ra, others, normals, weights, v, tol)
            if conf.turn_sigma_deg > 0:
                score = score * np.exp(-0.5 * (angles / np.radians(conf.turn_sigma_deg)) ** 2)
            for (j,) in _peaks(score, conf.turns, int(round(3.0 / conf.step_deg))):
                R = refine_rotation(Ra[j] @ R1, normals, weights, directions, tol)
                if not any(np.linalg.norm(R - Q) < 0.02 for Q, _ in out):  # about 1 deg apart
                    out.append((R, i))
    return out


def turn_votes(turns: np.ndarray, others: np.ndarray, normals: np.ndarray, weights: np.ndarray, v: np.ndarray,
               tol: float) -> np.ndarray:
    """:math:`(A,)` the weight of the query lines that each turn :math:`(A, 3, 3)` about ``v`` puts through one of the
    ``others`` directions :math:`(K, 3)` (camera frame): their interpretation planes hold it within ``tol`` (a sine).

    The lines through ``v`` itself do not vote: a turn about ``v`` leaves them as they are, and the plane of each holds
    one other direction at one turn by chance, so a stack of them (a door frame) made a peak of its own."""
    off = np.abs(normals @ v) >= tol
    u = np.einsum("aij,kj->aki", turns, others)  # (A, K, 3)
    through = np.abs(np.einsum("akj,mj->akm", u, normals[off])) < tol  # (A, K, M')
    return (through.any(1) * weights[off][None]).sum(1)


def refine_rotation(R: np.ndarray, normals: np.ndarray, weights: np.ndarray, directions: np.ndarray, tol: float,
                    iterations: int = 3) -> np.ndarray:
    """``R`` refined so that the query lines it assigns to a map direction (interpretation plane within ``tol``, a
    sine, of the rotated direction) contain it: weighted Gauss-Newton on ``sum w (n . R d)^2`` over a small rotation
    (a grid search is flat within the lines' tolerance)."""
    from scipy.spatial.transform import Rotation

    for _ in range(iterations):
        u = directions @ R.T  # (K, 3) in the camera frame
        c = normals @ u.T  # (M, K)
        k = np.argmin(np.abs(c), axis=1)
        r = c[np.arange(len(c)), k]
        sel = np.abs(r) < tol
        if sel.sum() < 3:
            break
        J = np.cross(u[k[sel]], normals[sel])  # d r / d omega for R <- exp(omega) R
        w = weights[sel]
        A = (J * w[:, None]).T @ J
        if np.linalg.cond(A) > 1e8:
            break
        omega = -np.linalg.solve(A, (J * (w * r[sel])[:, None]).sum(0))
        R = Rotation.from_rotvec(omega).as_matrix() @ R
    return R


def voted_translations(R: np.ndarray, p2d: np.ndarray, p3d: np.ndarray, segments: np.ndarray, normals: np.ndarray,
                       weights: np.ndarray, lines3d: np.ndarray, camera, conf: LinesFirstConfig) -> list:
    """Poses :math:`(4, 4)` with rotation ``R`` whose translations the line correspondences vote for along the ray of
    each point match (the ``conf.peaks`` best depths of each).

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3); segments: (M, 4) the query lines; normals, weights: their
        interpretation normals and vote weights; lines3d: (L, 2, 3) the map lines that vote.
    """
    if len(p2d) == 0 or len(normals) == 0 or len(lines3d) == 0:
        return []
    d = lines3d[:, 1] - lines3d[:, 0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    same = np.abs(normals @ (d @ R.T).T) < np.sin(np.radians(conf.line_tol_deg))  # (M, L) pairs of one direction
    qi, li = np.nonzero(same)
    if len(qi) == 0:
        return []
    RL = lines3d @ R.T  # the map lines' ends, rotated (L, 2, 3): a pair's camera-frame ends are these minus R C
    nq = normals[qi]
    nRX = (nq * RL[li, 0]).sum(1)  # n . R X for a point X of each paired map line
    s0, sd, sl = _segment_frames(segments)
    b = geo.unproject_points(np.asarray(p2d, dtype=float).reshape(-1, 2), 1.0, camera)
    b /= np.linalg.norm(b, axis=1, keepdims=True)  # (N, 3) the matches' rays
    RX = np.asarray(p3d, dtype=float).reshape(-1, 3) @ R.T
    lo, hi = conf.depth_range
    nbins = int(np.ceil((hi - lo) / conf.depth_bin))
    # every pair along every ray at once: (P, N)
    nb = nq @ b.T
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (nq @ RX.T - nRX[:, None]) / nb
    # a ray almost in the line's plane gives no depth
    pj, ray = np.nonzero((np.abs(nb) > 0.05) & (depth > lo) & (depth < hi))
    depth = depth[pj, ray]
    # the camera centre C = X - depth R^T b, so R (E - C) = R E - R X + depth b for a map line's end E; the ends'
    # depths first, as most pairs put the map line behind the camera or beyond the range
    lz = RL[li[pj], :, 2]
    z0, z1 = (lz[:, e] - (RX[ray, 2] - depth * b[ray, 2]) for e in (0, 1))
    ahead = (np.minimum(z0, z1) > lo) & (np.maximum(z0, z1) < hi)
    pj, ray, depth = pj[ahead], ray[ahead], depth[ahead]
    Y = RL[li[pj]] - (RX[ray] - depth[:, None] * b[ray])[:, None]
    pq = qi[pj]
    seen = _alike(Y, s0[pq], sd[pq], sl[pq], camera, conf)
    cells = ray[seen] * nbins + ((depth[seen] - lo) / conf.depth_bin).astype(np.int64)
    hists = _votes(cells, pq[seen], weights, len(b) * nbins).reshape(len(b), nbins)
    poses = []
    for hist, ray_b, RXp in zip(hists, b, RX):
        hist = hist + np.r_[hist[1:], 0] + np.r_[0, hist[:-1]]  # a vote's neighbours: a peak split by a bin edge
        for _ in range(conf.peaks):
            j = int(np.argmax(hist))
            if hist[j] <= 0:
                break
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, (lo + (j + 0.5) * conf.depth_bin) * ray_b - RXp
            poses.append(T)
            hist[max(0, j - 5): j + 6] = 0  # the next peak at least 10 cm deeper or shallower
    return poses


def seen_alike(R: np.ndarray, centres: np.ndarray, ends3d: np.ndarray, segments: np.ndarray, camera,
               conf: LinesFirstConfig) -> np.ndarray:
    """Whether each 3D segment :math:`(P, 2, 3)`, seen from its camera centre :math:`(P, 3)` with rotation ``R``, can be
    the detected segment :math:`(P, 4)`: both ends in front within the depth range, projected at least
    ``conf.min_projected_share`` of the detection's length, and overlapping the detection along its direction."""
    return _alike((ends3d - centres[:, None]) @ R.T, *_segment_frames(segments), camera, conf)


def _segment_frames(segments: np.ndarray) -> tuple:
    """First ends (M, 2), unit directions (M, 2) and lengths (M,) of the 2D segments (M, 4)."""
    s = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    d = s[:, 1] - s[:, 0]
    ln = np.linalg.norm(d, axis=1)
    return s[:, 0], d / np.maximum(ln, 1e-9)[:, None], ln


def _alike(Y: np.ndarray, s0: np.ndarray, d: np.ndarray, ln: np.ndarray, camera, conf: LinesFirstConfig) -> np.ndarray:
    """:func:`seen_alike` of the 3D segments' ends in the camera frame :math:`(P, 2, 3)` and the detections' frames
    (:func:`_segment_frames`, one row per segment)."""
    # each end's coordinates apart: numpy's reductions over an axis of two cost more than the arithmetic
    z0, z1 = Y[:, 0, 2], Y[:, 1, 2]
    ahead = (np.minimum(z0, z1) > conf.depth_range[0]) & (np.maximum(z0, z1) < conf.depth_range[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        # the projected ends along the detection, 0 at its first end
        a0, a1 = ((Y[:, e, 0] / z * camera.fx + camera.cx - s0[:, 0]) * d[:, 0]
                  + (Y[:, e, 1] / z * camera.fy + camera.cy - s0[:, 1]) * d[:, 1] for e, z in ((0, z0), (1, z1)))
        long_enough = np.abs(a1 - a0) >= conf.min_projected_share * ln
        overlap = (np.maximum(a0, a1) > 0) & (np.minimum(a0, a1) < ln)
        return ahead & long_enough & overlap


def _votes(cells: np.ndarray, voters: np.ndarray, weights: np.ndarray, n: int) -> np.ndarray:
    """A histogram of ``n`` cells in which each voter (a query line) counts once per cell however many of its pairs
    land there: the map lines coplanar with the camera (a wall seen from its own plane) would otherwise pile up."""
    key = np.unique(voters.astype(np.int64) * n + cells.astype(np.int64))
    return np.bincount(key % n, weights[key // n], n)


def _peaks(hist: np.ndarray, k: int, radius: int) -> list:
    """Indices of the ``k`` highest cells of ``hist`` (any shape), each at least ``radius`` cells from the earlier."""
    hist = hist.astype(float).copy()
    out = []
    for _ in range(k):
        j = np.unravel_index(int(np.argmax(hist)), hist.shape)
        if hist[j] <= 0:
            break
        out.append(j)
        hist[tuple(slice(max(0, c - radius), c + radius + 1) for c in j)] = 0
    return out


def voted_centres(R: np.ndarray, segments: np.ndarray, normals: np.ndarray, weights: np.ndarray, lines3d: np.ndarray,
                  directions: np.ndarray, centre0: np.ndarray, camera, conf: LinesFirstConfig) -> list:
    """Poses :math:`(4, 4)` with rotation ``R`` whose camera centres the line correspondences alone vote for, within
    ``conf.search_m`` of ``centre0`` (world): across the direction most query lines run along, then along it.

    Args:
        segments: (M, 4) the query lines; normals, weights: their interpretation normals and vote weights;
        lines3d: (L, 2, 3) the voting map lines; directions: (K, 3) the map's dominant directions.
    """
    if len(normals) == 0 or len(lines3d) == 0 or len(directions) == 0:
        return []
    m = normals @ R  # interpretation normals in the world frame: m . (X - C) = 0 for X on the matching 3D line
    d = lines3d[:, 1] - lines3d[:, 0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    tol = np.sin(np.radians(conf.line_tol_deg))
    q_of = np.abs(m @ directions.T) < tol  # (M, K): the query lines that run along each direction
    l_of = np.abs(d @ directions.T) > np.cos(np.radians(conf.line_tol_deg))  # (L, K)
    k = int(np.argmax((q_of * weights[:, None]).sum(0)))
    qi, li = np.nonzero(q_of[:, k][:, None] & l_of[:, k][None])
    if len(qi) == 0:
        return []
    dk = directions[k]
    e1 = np.cross(dk, [1.0, 0, 0] if abs(dk[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(dk, e1)
    a, b = m[qi] @ e1, m[qi] @ e2  # a x + b y = c: the pair's line across dk (x, y from centre0)
    c = (m[qi] * (lines3d[li, 0] - centre0)).sum(1)
    nb = int(round(2 * conf.search_m / conf.centre_bin))
    grid = (np.arange(nb) + 0.5) * conf.centre_bin - conf.search_m
    steep = np.abs(a) > np.abs(b)  # walk each line along the axis it changes least with
    with np.errstate(divide="ignore", invalid="ignore"):
        other = np.where(steep[:, None], (c[:, None] - b[:, None] * grid) / a[:, None],
                         (c[:, None] - a[:, None] * grid) / b[:, None])  # (P, nb)
    cell = np.floor((other + conf.search_m) / conf.centre_bin)
    xs = np.where(steep[:, None], other, grid[None])  # (P, nb) the vote's position across dk
    ys = np.where(steep[:, None], grid[None], other)
    # the map line must stand in front of the camera at the vote's centre (its offset along dk taken as centre0's):
    # a plane through the query line holds many 3D lines, most of them behind or beside the camera
    # camera-frame ends of the map line from the vote's centre; projected, the line is at least about as long as a
    # good share of the detection (a far line projects short, and meets the detection's plane by chance)
    Re1, Re2 = R @ e1, R @ e2
    Y = [(lines3d[li, e] - centre0) @ R.T for e in (0, 1)]
    Y = [y[:, None, :] - xs[..., None] * Re1 - ys[..., None] * Re2 for y in Y]  # 2 x (P, nb, 3)
    fx, fy = camera.fx, camera.fy
    with np.errstate(divide="ignore", invalid="ignore"):
        du = fx * (Y[1][..., 0] / Y[1][..., 2] - Y[0][..., 0] / Y[0][..., 2])
        dv = fy * (Y[1][..., 1] / Y[1][..., 2] - Y[0][..., 1] / Y[0][..., 2])
    ahead = (np.minimum(Y[0][..., 2], Y[1][..., 2]) > conf.depth_range[0]) & (np.maximum(Y[0][..., 2], Y[1][..., 2]) < conf.depth_range[1])
    long_enough = np.hypot(du, dv) >= conf.min_projected_share * geo.segment_lengths(segments)[qi][:, None]
    ok = np.isfinite(cell) & (cell >= 0) & (cell < nb) & ahead & long_enough
    j = np.broadcast_to(np.arange(nb), cell.shape)
    ix = np.where(steep[:, None], cell, j)[ok].astype(np.int64)
    iy = np.where(steep[:, None], j, cell)[ok].astype(np.int64)
    hist = _votes(ix * nb + iy, np.broadcast_to(qi[:, None], cell.shape)[ok], weights, nb * nb).reshape(nb, nb)
    # along dk: the pairs of the other directions, each a depth s of C = P0 + s dk
    oq, ol = np.nonzero(q_of[:, np.arange(len(directions)) != k].any(1)[:, None] & ~l_of[:, k][None]
                        & (np.abs(m @ dk) > 0.1)[:, None])
    poses = []
    for px, py in _peaks(hist, conf.peaks, 2):
        P0 = centre0 + grid[px] * e1 + grid[py] * e2
        if len(oq) == 0:
            continue
        mo = m[oq]
        same = np.abs((d[ol] * mo).sum(1)) < tol  # the pair's 3D line lies in the query line's plane direction
        q2, l2 = oq[same], ol[same]
        s = (mo[same] * (lines3d[l2, 0] - P0)).sum(1) / (mo[same] @ dk)
        inr = np.abs(s) < conf.search_m
        inr[inr] = seen_alike(R, P0 + s[inr, None] * dk, lines3d[l2[inr]], segments[q2[inr]], camera, conf)
        if not inr.any():
            continue
        hs = _votes(((s[inr] + conf.search_m) / conf.centre_bin).astype(np.int64), q2[inr], weights, nb)
        hs = hs + np.r_[hs[1:], 0] + np.r_[0, hs[:-1]]
        for (js,) in _peaks(hs, conf.peaks, 2):
            C = P0 + ((js + 0.5) * conf.centre_bin - conf.search_m) * dk
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, -R @ C
            poses.append(T)
    return poses


def lines_first_poses(p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, camera, views: list,
                      map_lines: np.ndarray, directions: np.ndarray, vps: np.ndarray,
                      conf: LinesFirstConfig) -> np.ndarray:
    """Every pose of :func:`voted_translations` (:func:`voted_centres` without a point match; with fewer matches than
    ``conf.view_centres_below`` also the view's own centre) for every rotation of :func:`vp_rotations` near ``views``.

    Returns:
        :math:`(H, 4, 4)` cam_from_world.
    """
    if not len(views) or not len(vps) or not len(directions):
        return np.zeros((0, 4, 4))
    segs = np.asarray(lines2d, dtype=float).reshape(-1, 4)
    n, length = interpretation_normals(segs, camera)
    keep = length >= conf.min_length_px
    segs, n, length = segs[keep], n[keep], length[keep]
    w = np.minimum(length, 200.0) / 200.0  # long lines count more, a wall-long one no more than 200 px
    poses = []
    for R, i in vp_rotations(n, w, vps, directions, views, conf):
        C0 = camera_center(np.asarray(views[i], dtype=float))
        if len(p2d):
            poses += voted_translations(R, p2d, p3d, segs, n, w, map_lines, camera, conf)
        else:
            poses += voted_centres(R, segs, n, w, map_lines, directions, C0, camera, conf)
        if len(p2d) < conf.view_centres_below:
            poses.append(make_T(R, -R @ C0))
    return np.array(poses).reshape(-1, 4, 4)
