"""Line-verified pose hypotheses for a query with too few point matches to trust its RANSAC pose.

With ten 2D-3D point matches, a wrong P3P pose often explains as many of them as the right one at RANSAC's
12 px threshold, and RANSAC keeps whichever it met first. The map's lines can tell them apart. Every P3P pose
of every triple of matches is scored by how many map lines it projects onto detected lines of the same
direction; the detections are looked up through one mask per direction bin of the pixels near them. The best few
poses then start the wide-gate line rescue (:func:`localization.query.rescue_pose`).

P3P needs three right matches among the few. Lines give two more constraints on their own: an indoor map's lines
run mostly along a few directions, and a query's long lines meet at their vanishing points. Aligning the query's
strongest vanishing point with one of the map's dominant directions leaves a rotation about that axis and the
translation, which two point matches fix (PoseLib's upright 2-point solver, ``up2p``, in frames where the aligned
direction is the y axis). Those poses join the P3P ones before the line scoring (``HypothesisConfig.upright``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import cv2
import numpy as np

from lipmap import geometry as geo
from lipmap.poses import rotation_between

from .linesfirst import LinesFirstConfig, lines_first_poses



@dataclass
class HypothesisConfig:
    max_triples: int = 200  # triples of point matches solved (all when fewer; a seeded sample otherwise)
    max_point_error: float = 12.0  # px: point inliers of a hypothesis (as the point-only RANSAC)
    max_hypotheses: int = 60  # the hypotheses with the most point inliers are scored by lines
    n_map_lines: int = 1500  # the longest map lines score them
    min_support: int = 1  # of those seen in at least this many mapping images (default: leave out lines no image verifies)
    samples: int = 5  # per map line
    max_dist_px: float = 3.0  # a sample agrees within this of a detection of its direction
    angle_bins: int = 8  # direction bins over 180 deg; a detection also counts in the bin next to its angle
    min_agree: float = 0.8  # share of a line's samples that must agree
    # best hypotheses handed on, each a PnPL RANSAC of the rescue (~25 ms): 5 rather than 3 gave held-out queries a right
    # start more often (10 matches: per query 30 better / 5 worse; docs/localization.md, `-keep`)
    keep: int = 5
    # > 0: a first pass scores every hypothesis with the ``coarse_lines`` longest lines and only its ``coarse_keep``
    # best go on to all ``n_map_lines``. 0 (one pass over all): a hypothesis some cm off lays few of the longest
    # lines within max_dist_px, and the first pass lost it (held-out split, 5 matches: 46 -> 52 % within 5 cm)
    coarse_lines: int = 0
    coarse_keep: int = 10
    min_length_px: float = 20.0  # shorter detections and projections are left out (as the line query)
    box_margin: float = 0.5  # m: a hypothesis' camera lies within the map lines' box grown by this
    # two-point poses with the query's strongest vanishing points aligned to the map's dominant line directions
    # (module docstring): a pose from two right matches where P3P needs three
    upright: bool = True
    vp_count: int = 2  # the query's strongest vanishing points tried (the first is usually right, docs/localization.md)
    map_directions: int = 3  # the map's dominant line directions each is aligned with (both signs)
    vp_tol_deg: float = 1.5  # a query line points at a vanishing point within this
    vp_min_length_px: float = 30.0  # shorter query lines do not vote for vanishing points
    vp_iterations: int = 500  # pairs of lines sampled per vanishing point
    direction_tol_deg: float = 3.0  # map lines within this of a direction count for it
    max_pairs: int = 45  # pairs of point matches per alignment (all when fewer; a seeded sample otherwise)
    max_upright: int = 40  # of those poses, the ones with the most point inliers are scored by lines
    # ... tried only when no P3P pose explains this many matches (0: always): a pose that explains more than
    # its own triple is usually right, and the two-point poses then cost time for nothing
    upright_below: int = 5
    # with fewer point matches than lines_first.below, also the poses of localization.linesfirst (rotation from the
    # vanishing points near the retrieved images', translation voted by the lines along each match's ray)
    lines_first: LinesFirstConfig = field(default_factory=LinesFirstConfig)


def _bearings(p2d: np.ndarray, camera) -> np.ndarray:
    x = geo.unproject_points(p2d, 1.0, camera)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def p3p_hypotheses(p2d: np.ndarray, p3d: np.ndarray, camera, conf: HypothesisConfig, seed: int = 0):
    """Every P3P pose of (a seeded sample of) the triples of matches, with its point inliers.

    Returns:
        poses :math:`(H, 4, 4)` cam_from_world, inliers :math:`(H,)` counts over all matches.
    """
    import poselib

    n = len(p2d)
    if n < 3:
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64)
    triples = np.array(list(combinations(range(n), 3))) if n <= 40 else None
    rng = np.random.default_rng(seed)
    if triples is None or len(triples) > conf.max_triples:
        triples = np.array([rng.choice(n, 3, replace=False) for _ in range(conf.max_triples)])
    x = _bearings(p2d, camera)
    poses = []
    for tri in triples:
        for pose in poselib.p3p(x[tri], p3d[tri]):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = pose.R, pose.t
            poses.append(T)
    if not poses:
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64)
    poses = np.array(poses)
    return poses, point_inliers(poses, p2d, p3d, camera, conf.max_point_error)


def _pairs(n: int, k: int, rng) -> np.ndarray:
    """All pairs of ``n`` indices when there are at most ``k``, else ``k`` seeded random ones: (P, 2)."""
    if n < 2:
        return np.zeros((0, 2), np.int64)
    if n * (n - 1) // 2 <= k:
        return np.array(list(combinations(range(n), 2)))
    out = np.array([rng.choice(n, 2, replace=False) for _ in range(k)])
    return np.sort(out, axis=1)


def dominant_directions(lines3d: np.ndarray, k: int, tol_deg: float = 3.0) -> np.ndarray:
    """The ``k`` line directions that the most line length runs along, each at least 10 deg from the earlier ones.

    Each direction is the principal axis of the (length-weighted) directions within ``tol_deg`` of the best
    candidate, the candidates being the 400 longest lines' own directions.

    Args:
        lines3d: :math:`(L, 2, 3)` segments.

    Returns:
        :math:`(K, 3)` unit directions (K <= k; fewer when the lines run along fewer).
    """
    L = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    d = L[:, 1] - L[:, 0]
    w = np.linalg.norm(d, axis=1)
    ok = w > 1e-9
    d, w = d[ok] / w[ok, None], w[ok]
    cand = d[np.argsort(-w, kind="stable")[:400]]
    close = np.abs(cand @ d.T) > np.cos(np.radians(tol_deg))  # (C, L)
    score = close.astype(float) @ w
    out = []
    for _ in range(k):
        if out:
            far = np.all(np.abs(cand @ np.array(out).T) < np.cos(np.radians(10.0)), axis=1)
            score = np.where(far, score, -1.0)
        if len(cand) == 0 or score.max() <= 0:
            break
        m = close[int(np.argmax(score))]
        out.append(np.linalg.eigh((d[m] * w[m, None]).T @ d[m])[1][:, -1])
    return np.array(out).reshape(-1, 3)


def vanishing_points(lines2d: np.ndarray, camera, conf: HypothesisConfig, seed: int = 0) -> np.ndarray:
    """The query's ``conf.vp_count`` strongest vanishing points, as unit directions in the camera frame.

    A vanishing point is the direction that the interpretation planes of the most line length (lines of at least
    ``vp_min_length_px``) contain within ``vp_tol_deg``: seeded RANSAC over pairs of lines, then the least-squares
    direction of its lines. Each next one is sought among the lines the earlier ones left.

    Returns:
        :math:`(V, 3)` (V <= vp_count), sign arbitrary.
    """
    L = np.asarray(lines2d, dtype=float).reshape(-1, 4)
    w = geo.segment_lengths(L)
    L, w = L[w >= conf.vp_min_length_px], w[w >= conf.vp_min_length_px]
    if len(L) < 2:
        return np.zeros((0, 3))
    n = geo.backprojected_planes(L, geo.projection_matrices(np.eye(4), camera))[:, :3]  # interpretation planes
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tol = np.sin(np.radians(conf.vp_tol_deg))
    rng = np.random.default_rng(seed)
    alive, out = np.ones(len(n), bool), []
    for _ in range(conf.vp_count):
        idx = np.flatnonzero(alive)
        if len(idx) < 2:
            break
        ij = rng.integers(0, len(idx), (conf.vp_iterations, 2))
        v = np.cross(n[idx[ij[:, 0]]], n[idx[ij[:, 1]]])
        nv = np.linalg.norm(v, axis=1)
        v = v[nv > 1e-9] / nv[nv > 1e-9, None]
        if len(v) == 0:
            break
        votes = (np.abs(n[idx] @ v.T) < tol).astype(float).T @ w[idx]
        inl = idx[np.abs(n[idx] @ v[int(np.argmax(votes))]) < tol]
        vp = np.linalg.eigh((n[inl] * w[inl, None]).T @ n[inl])[1][:, 0]  # the direction most orthogonal to their normals
        out.append(vp)
        alive &= np.abs(n @ vp) >= 2 * tol
    return np.array(out).reshape(-1, 3)


def upright_hypotheses(p2d: np.ndarray, p3d: np.ndarray, camera, vps: np.ndarray, directions: np.ndarray,
                       conf: HypothesisConfig, seed: int = 0) -> np.ndarray:
    """Poses that turn a map direction into a vanishing point, from pairs of point matches (PoseLib ``up2p``).

    For each vanishing point ``a`` (camera frame), map direction ``b`` and sign, rotations ``Qc`` and ``Qw`` take
    ``a`` and ``b`` to the y axis; ``up2p`` solves the rotation about y and the translation between the rotated
    frames, and the pose is ``R = Qc^T R_y Qw``, ``t = Qc^T t_y``, so that ``R b = a``.

    Returns:
        :math:`(H, 4, 4)` cam_from_world.
    """
    import poselib

    pairs = _pairs(len(p2d), conf.max_pairs, np.random.default_rng(seed))
    if len(pairs) == 0 or len(vps) == 0 or len(directions) == 0:
        return np.zeros((0, 4, 4))
    x = _bearings(p2d, camera)
    y = np.array([[0.0, 1.0, 0.0]])
    poses = []
    for a in vps:
        Qc = rotation_between(a, y[0])
        xr = x @ Qc.T
        for b in np.concatenate([directions, -directions]):
            Qw = rotation_between(b, y[0])
            Xr = p3d @ Qw.T
            for i, j in pairs:
                for pose in poselib.up2p(xr[[i, j]], Xr[[i, j]]):
                    T = np.eye(4)
                    T[:3, :3], T[:3, 3] = Qc.T @ pose.R @ Qw, Qc.T @ pose.t
                    poses.append(T)
    return np.array(poses).reshape(-1, 4, 4)


def point_inliers(poses: np.ndarray, p2d: np.ndarray, p3d: np.ndarray, camera, max_error: float) -> np.ndarray:
    """:math:`(H,)` matches each pose :math:`(H, 4, 4)` projects within ``max_error`` px, in front of it."""
    if len(poses) == 0:
        return np.zeros(0, np.int64)
    Xc = p3d @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
    uv, z = geo.project_cam_points(Xc, camera)
    err = np.linalg.norm(uv - p2d[None], axis=-1)
    return ((z > 0) & (err <= max_error)).sum(1)


class LineEvidence:
    """The detected lines of one query as per-direction masks of the pixels near them."""

    def __init__(self, lines2d: np.ndarray, camera, conf: HypothesisConfig):
        self.camera, self.conf = camera, conf
        L = np.asarray(lines2d, dtype=float).reshape(-1, 4)
        L = L[np.linalg.norm(L[:, 2:] - L[:, :2], axis=1) >= conf.min_length_px]
        B = conf.angle_bins
        width = np.pi / B
        ang = np.mod(np.arctan2(L[:, 3] - L[:, 1], L[:, 2] - L[:, 0]), np.pi)
        own = np.floor(ang / width).astype(int) % B
        frac = ang / width - np.floor(ang / width)
        nxt = np.where(frac >= 0.5, own + 1, own - 1) % B  # the neighbour bin nearest to the line's angle
        # OpenCV's thick line of width 2 * ceil(d) - 1 covers the pixels within d of the segment (and a sliver
        # more; tests/test_line_rescue.py checks against exact distances): 15x cheaper than a distance transform
        self.near = np.zeros((B, camera.height, camera.width), np.uint8)
        # COLMAP pixels: the centre of pixel (i, j) is (j + 0.5, i + 0.5); 4 fractional bits keep sub-pixel ends
        pts = np.round((L.reshape(-1, 2, 2) - 0.5) * 16).astype(np.int32)
        thick = max(1, 2 * int(np.ceil(conf.max_dist_px)) - 1)
        for b in range(B):
            sel = np.flatnonzero((own == b) | (nxt == b))
            if len(sel):
                cv2.polylines(self.near[b], list(pts[sel]), False, 1, thick, cv2.LINE_8, 4)
        # the masks as one bit per bin, with a pixel of border that samples outside the image land on
        self.bits = np.zeros((camera.height + 2, camera.width + 2), np.min_scalar_type(2 ** B - 1))
        for b in range(B):
            self.bits[1:-1, 1:-1] |= self.near[b].astype(self.bits.dtype) << b

    def score(self, poses: np.ndarray, lines3d: np.ndarray) -> np.ndarray:
        """:math:`(H,)` number of ``lines3d`` :math:`(L, 2, 3)` that each pose :math:`(H, 4, 4)` lays on detections.

        The same counts as :meth:`score_reference`, about 5x faster: only the endpoints are projected for every pose
        and line, and the samples only of the lines that land in the image, in front and long enough (projection is
        linear in homogeneous coordinates, so a sample's is the interpolation of its endpoints'); the last samples
        only of the lines the first ones left a chance; one bit per direction bin in one table."""
        c, cam = self.conf, self.camera
        L = len(lines3d)
        if L == 0 or len(poses) == 0:
            return np.zeros(len(poses), np.int64)
        Xh = np.concatenate([np.asarray(lines3d, float).reshape(-1, 3), np.ones((2 * L, 1))], 1).astype(np.float32)
        # one float32 product with K [R | t] per pose: pixels to within 1e-3 px
        uvw = (Xh @ geo.projection_matrices(poses, cam).astype(np.float32).transpose(0, 2, 1)).reshape(len(poses), L, 2, 3)
        z0, z1 = uvw[:, :, 0, 2], uvw[:, :, 1, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u0, v0, u1, v1 = uvw[:, :, 0, 0] / z0, uvw[:, :, 0, 1] / z0, uvw[:, :, 1, 0] / z1, uvw[:, :, 1, 1] / z1
            du, dv = u1 - u0, v1 - v0
            # a pose far from the scene sees it small: short projections land on detections by chance
            keep = (z0 > 0) & (z1 > 0) & (np.hypot(du, dv) >= c.min_length_px)
            if c.min_agree > 0:  # a line whose endpoints' box misses the image has no sample in it
                keep &= (np.maximum(u0, u1) >= 0) & (np.minimum(u0, u1) < cam.width)
                keep &= (np.maximum(v0, v1) >= 0) & (np.minimum(v0, v1) < cam.height)
        idx = np.flatnonzero(keep)
        e = uvw.reshape(-1, 6)[idx]  # (K, 6): both endpoints' homogeneous pixels
        b = (np.floor(np.mod(np.arctan2(dv.ravel()[idx], du.ravel()[idx]), np.pi) / (np.pi / c.angle_bins))
             .astype(np.int64) % c.angle_bins).astype(self.bits.dtype)
        t = np.linspace(0.1, 0.9, c.samples).astype(np.float32)
        need = next(k for k in range(c.samples + 1) if k / c.samples >= c.min_agree)  # hits a line must have
        # most lines miss: the first few samples, as many as a line may miss plus one, drop those already out
        first = min(c.samples, c.samples - need + 1)
        hits = self._hits(e, b, t[:first])
        alive = np.flatnonzero(hits + (c.samples - first) >= need)
        if first < c.samples and len(alive):
            hits[alive] += self._hits(e[alive], b[alive], t[first:])
        return np.bincount(idx[hits >= need] // L, minlength=len(poses)).astype(np.int64)

    def _hits(self, e: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
        """:math:`(K,)` samples at ``t`` :math:`(S,)` along each projected line (``e`` :math:`(K, 6)`, its endpoints'
        homogeneous pixels) that land on a detection of its direction bin ``b`` :math:`(K,)`."""
        cam = self.camera
        t = t[None]
        x, y, w = (e[:, j, None] + t * (e[:, 3 + j, None] - e[:, j, None]) for j in range(3))  # (K, S) each
        with np.errstate(divide="ignore", invalid="ignore"):
            # fmin / fmax send NaN to the table's border, as they do samples outside the image
            ui = np.fmax(np.fmin(x / w + 1, np.float32(cam.width + 1)), 0).astype(np.intp)
            vi = np.fmax(np.fmin(y / w + 1, np.float32(cam.height + 1)), 0).astype(np.intp)
        return ((self.bits[vi, ui] >> b[:, None]) & 1).sum(-1)

    def score_reference(self, poses: np.ndarray, lines3d: np.ndarray) -> np.ndarray:
        """:meth:`score` as plainly as it reads: every sample of every line projected under every pose, looked up in
        its direction bin's mask."""
        c, cam = self.conf, self.camera
        L = len(lines3d)
        if L == 0 or len(poses) == 0:
            return np.zeros(len(poses), np.int64)
        t = np.linspace(0.1, 0.9, c.samples)
        pts = lines3d[:, None, 0] + t[None, :, None] * (lines3d[:, None, 1] - lines3d[:, None, 0])  # (L, S, 3)
        allp = np.concatenate([lines3d, pts], 1).reshape(-1, 3)  # endpoints first, then the samples
        # one float32 product with K [R | t] per pose: pixels to within 1e-3 px, the cost of this function
        Xh = np.concatenate([allp, np.ones((len(allp), 1))], 1).astype(np.float32)
        uvw = Xh @ geo.projection_matrices(poses, cam).astype(np.float32).transpose(0, 2, 1)  # (H, P, 3)
        z = uvw[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[..., 0] / z, uvw[..., 1] / z
        u, v, z = (a.reshape(len(poses), L, 2 + c.samples) for a in (u, v, z))
        ang = np.mod(np.arctan2(v[..., 1] - v[..., 0], u[..., 1] - u[..., 0]), np.pi)
        b = (np.floor(ang / (np.pi / c.angle_bins)).astype(np.int64) % c.angle_bins)  # (H, L)
        us, vs, zs = u[..., 2:], v[..., 2:], z[..., 2:]
        ok = (zs > 0) & (z[..., :2] > 0).all(-1, keepdims=True) & (us >= 0) & (us < cam.width) & (vs >= 0) & (vs < cam.height)
        flat = (b[..., None] * cam.height + np.where(ok, vs, 0).astype(np.int64)) * cam.width + np.where(ok, us, 0).astype(np.int64)
        near = self.near.reshape(-1)[flat].astype(bool)
        agree = (ok & near).mean(-1) >= c.min_agree  # (H, L)
        # a pose far from the scene sees it small: short projections land on detections by chance
        long_enough = np.hypot(u[..., 1] - u[..., 0], v[..., 1] - v[..., 0]) >= c.min_length_px
        return (agree & long_enough).sum(1)


def scoring_lines(lines3d: np.ndarray, n: int) -> np.ndarray:
    """The ``n`` longest of ``lines3d`` (N, 2, 3): long lines are the ones a wrong pose does not lay on detections
    by chance."""
    lines3d = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    length = np.linalg.norm(lines3d[:, 1] - lines3d[:, 0], axis=1)
    return lines3d[np.sort(np.argsort(-length, kind="stable")[:n])]


def line_verified_poses(p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, map_lines: np.ndarray, camera,
                        conf: HypothesisConfig, seed: int = 0, directions: np.ndarray | None = None,
                        views: list = ()) -> list:
    """The ``conf.keep`` poses of the point matches (P3P, with ``conf.upright`` the vanishing-point-aligned
    two-point ones, and with fewer matches than ``conf.lines_first.below`` those of :mod:`localization.linesfirst`
    near ``views``) that the most map lines agree with, best first.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3) world points; lines2d: (M, 4) query detections;
        map_lines: (L, 2, 3) the lines that score (:func:`scoring_lines`);
        directions: (K, 3) the map's dominant directions (default: :func:`dominant_directions` of ``map_lines``).
        views: poses (4, 4) whose rotations the lines-first rotations lie near (the retrieved images').

    Returns:
        list of (4, 4) cam_from_world.
    """
    p2d = np.asarray(p2d, dtype=float).reshape(-1, 2)
    p3d = np.asarray(p3d, dtype=float).reshape(-1, 3)
    # the camera must stand within the map (its lines' box, with a margin)
    lo, hi = map_lines.reshape(-1, 3).min(0) - conf.box_margin, map_lines.reshape(-1, 3).max(0) + conf.box_margin

    def best_inside(poses, inl, k):
        C = -np.einsum("hji,hj->hi", poses[:, :3, :3], poses[:, :3, 3])
        inside = np.flatnonzero(np.all((C >= lo) & (C <= hi), axis=1))
        top = inside[np.argsort(-inl[inside], kind="stable")[:k]]
        return poses[top], inl[top]

    poses, inl = best_inside(*p3p_hypotheses(p2d, p3d, camera, conf, seed), conf.max_hypotheses)
    lines_first = len(p2d) < conf.lines_first.below and len(views) > 0
    upright = conf.upright and not (conf.upright_below > 0 and len(inl) and inl.max() >= conf.upright_below)
    if lines_first or upright:
        if directions is None:
            directions = dominant_directions(map_lines, conf.map_directions, conf.direction_tol_deg)
        vps = vanishing_points(lines2d, camera, conf, seed)
    if upright:
        up = upright_hypotheses(p2d, p3d, camera, vps, directions, conf, seed)
        up, up_inl = best_inside(up, point_inliers(up, p2d, p3d, camera, conf.max_point_error), conf.max_upright)
        poses, inl = np.concatenate([poses, up]), np.concatenate([inl, up_inl])
    if lines_first:
        lf = lines_first_poses(p2d, p3d, lines2d, camera, list(views), map_lines, directions, vps, conf.lines_first)
        lf, lf_inl = best_inside(lf, point_inliers(lf, p2d, p3d, camera, conf.max_point_error), len(lf))
        poses, inl = np.concatenate([poses, lf]), np.concatenate([inl, lf_inl])
    if len(poses) == 0:
        return []
    evidence = LineEvidence(lines2d, camera, conf)
    if 0 < conf.coarse_lines < len(map_lines) and conf.coarse_keep < len(poses):
        coarse = evidence.score(poses, scoring_lines(map_lines, conf.coarse_lines))
        first = np.lexsort((-inl, -coarse))[: conf.coarse_keep]
        poses, inl = poses[first], inl[first]
    score = evidence.score(poses, map_lines)
    order = np.lexsort((-inl, -score))[: conf.keep]
    return [poses[i] for i in order if score[i] > 0]
