"""A PnPL RANSAC about a start pose: minimal samples solved linearly for a small rotation from the start and the
translation, thousands at once in NumPy.

The line rescue starts from poses within a few degrees of the truth when they are right at all (line-verified P3P
poses, vanishing-point rotations, the point-only pose). Near such a rotation ``R0`` the pose is
``R = exp([w]x) R0, t`` with small ``w``, and each point or line match gives two equations that are linear in
``(w, t)`` once ``exp([w]x)`` is replaced by ``I + [w]x``: three matches fix a pose. Two matches fix the
translation at ``R0`` itself (``w = 0``), which needs one right match fewer - with a quarter of the wide gate's
line candidates right, 1 sample in 17 instead of 1 in 70. Every sample's pose is scored exactly at the rotation
``exp([w]x) R0`` by MSAC, as PoseLib's RANSAC scores (:func:`msac_costs`: an inlier count kept poses that lay many wrong
candidates loosely); the best few distinct ones are refined over their inliers by PoseLib's point+line refinement
(:func:`~localization.estimate.pnpl_pose`'s weighted one), which also undoes the linearisation, and the cheapest of
them at the final thresholds is the pose.

PoseLib's own PnPL RANSAC samples uniformly among all matches, solves each sample in C++ with no prior and always
ran its 1,000 iterations over the wide gate's hundreds of candidates; this one uses the start, as the wide gate
around it already does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from lipmap import geometry as geo
from lipmap.poses import make_T

from .estimate import (PointLinePoseConfig, _camera_pose, _point_line_input, _pose_result, _weighted_refinement,
                       _within_thresholds, pnpl_residuals)


@dataclass
class NearRansacConfig:
    translation_samples: int = 300  # pairs of matches solved for the translation at the start's rotation
    pose_samples: int = 600  # triples solved for a small rotation from the start's and the translation
    max_rotation_deg: float = 15.0  # a triple's rotation farther from the start's is dropped (the linearisation fails)
    # px: a sample pose's line inliers (wider than the final threshold: its rotation is linearised, or the start's)
    score_line_error: float = 8.0
    lo_best: int = 8  # the best this many samples are refined once (lines within score_line_error); the cheapest wins
    lo_rounds: int = 2  # refinements of the winner in all, the later ones over its lines within the final threshold
    distinct_m: float = 0.05  # ... each this far (or distinct_deg) from the better ones: the same pose twice refines to itself
    distinct_deg: float = 1.0
    passes: int = 1  # sampling rounds; each later one linearises about the previous round's refined pose


def match_equations(p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, lines3d: np.ndarray, R0: np.ndarray,
                    camera) -> tuple:
    """Two linear equations in ``(w, t)`` per match, for the pose ``(I + [w]x) R0, t``.

    A match constrains the camera-frame point ``Xc = Z + w x Z + t`` (``Z = R0 X``) to a plane through the camera
    centre with unit normal ``n``: ``n . Xc = 0``, i.e. ``-(n x Z) . w + n . t = -n . Z``. A point gives the planes
    of its pixel's row and column, a line each of its 3D endpoints on the plane of its 2D segment.

    Args:
        p2d: :math:`(N, 2)` pixels; p3d: :math:`(N, 3)` world.
        lines2d: :math:`(M, 2, 2)` segments, pixels; lines3d: :math:`(M, 2, 3)` their 3D segments, world.
        R0: :math:`(3, 3)` the start's rotation (cam_from_world); camera: pinhole (``K``).

    Returns:
        A :math:`(N + M, 2, 6)` and b :math:`(N + M, 2)`: rows ``A[c, k] . (w, t) = b[c, k]``, points first. Each
        row's residual is a distance to its plane (metres).
    """
    N, M = len(p2d), len(lines2d)
    n = np.zeros((N + M, 2, 3))
    Z = np.zeros((N + M, 2, 3))
    x = geo.unproject_points(p2d, 1.0, camera)
    n[:N, 0, 0], n[:N, 0, 2] = 1.0, -x[:, 0]
    n[:N, 1, 1], n[:N, 1, 2] = 1.0, -x[:, 1]
    n[:N] /= np.linalg.norm(n[:N], axis=2, keepdims=True)
    Z[:N] = (p3d @ R0.T)[:, None]
    nl = _segment_planes(lines2d, np.asarray(camera.K, dtype=np.float64))
    n[N:] = (nl / np.linalg.norm(nl, axis=1, keepdims=True))[:, None]
    Z[N:] = lines3d @ R0.T
    A = np.concatenate([-np.cross(n, Z), n], 2)
    b = -np.einsum("ckd,ckd->ck", n, Z)
    return A, b


def _segment_planes(lines2d: np.ndarray, K: np.ndarray) -> np.ndarray:
    """:math:`(M, 3)` normals of the planes through the camera centre and each segment, in the camera frame, scaled so
    that ``n . Xc`` is the depth of ``Xc`` times its projection's pixel distance from the segment's line."""
    return geo.backprojected_planes(lines2d, np.c_[K, np.zeros(3)])[:, :3]


def solve_samples(A: np.ndarray, b: np.ndarray, pairs: np.ndarray, triples: np.ndarray,
                  max_rotation_deg: float) -> tuple:
    """The poses of minimal samples: ``pairs`` :math:`(P, 2)` of match indices solved for ``t`` at ``w = 0`` (least
    squares over their 4 equations), ``triples`` :math:`(Q, 3)` for ``(w, t)`` (6 equations).

    Returns:
        w :math:`(H, 3)` and t :math:`(H, 3)` of the samples whose systems are well posed (and, for triples, whose
        rotation stays within ``max_rotation_deg``), pairs first.
    """
    As, bs = A[pairs].reshape(len(pairs), 4, 6)[..., 3:], b[pairs].reshape(len(pairs), 4)
    AtA, Atb = np.einsum("hki,hkj->hij", As, As), np.einsum("hki,hk->hi", As, bs)
    ok2 = _well_posed(AtA)
    t2 = np.linalg.solve(AtA[ok2], Atb[ok2][..., None])[..., 0]
    A3, b3 = A[triples].reshape(len(triples), 6, 6), b[triples].reshape(len(triples), 6)
    ok3 = _well_posed(A3)
    x3 = np.linalg.solve(A3[ok3], b3[ok3][..., None])[..., 0]
    x3 = x3[np.linalg.norm(x3[:, :3], axis=1) <= np.deg2rad(max_rotation_deg)]
    return np.concatenate([np.zeros_like(t2), x3[:, :3]]), np.concatenate([t2, x3[:, 3:]])


def _well_posed(A: np.ndarray) -> np.ndarray:
    """Which square systems :math:`(H, k, k)` are far from singular: |det| against the product of the row norms
    (Hadamard's bound; 1 for orthogonal rows) above 1e-9."""
    bound = np.prod(np.linalg.norm(A, axis=2), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(np.linalg.det(A)) > 1e-9 * bound


def solve_sample_reference(A: np.ndarray, b: np.ndarray, idx) -> np.ndarray:
    """One sample's ``(w, t)`` by NumPy's least squares (readable twin of :func:`solve_samples`; a pair gives
    ``w = 0``)."""
    rows, rhs = A[list(idx)].reshape(-1, 6), b[list(idx)].reshape(-1)
    if len(idx) == 2:
        return np.concatenate([np.zeros(3), np.linalg.lstsq(rows[:, 3:], rhs, rcond=None)[0]])
    return np.linalg.lstsq(rows, rhs, rcond=None)[0]


def msac_costs(w: np.ndarray, t: np.ndarray, R0: np.ndarray, p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray,
               lines3d: np.ndarray, K: np.ndarray, max_point_error: float, max_line_error: float) -> np.ndarray:
    """MSAC costs :math:`(H,)` of the poses ``(exp([w]x) R0, t)`` (rows of ``w``, ``t`` :math:`(H, 3)`), as PoseLib's
    RANSAC scores its samples: a point costs its squared reprojection error, at most ``max_point_error**2`` (the
    most behind the camera); a line the square of the sum of its two projected 3D endpoints' distances to the
    detection's infinite line (:func:`~localization.estimate.pnpl_residuals`), at most ``max_line_error**2``. Lower
    is better: unlike an inlier count, a pose that lays many candidates loosely costs more than one that lays the
    right ones exactly."""
    N, M = len(p2d), len(lines2d)
    R = Rotation.from_rotvec(w).as_matrix() @ R0 if len(w) else np.zeros((0, 3, 3))
    cost = np.zeros(len(w))
    if N:
        proj = np.matmul(K @ R, p3d.T) + (t @ K.T)[:, :, None]  # (H, 3, N)
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = (proj[:, 0] / proj[:, 2] - p2d[:, 0]) ** 2 + (proj[:, 1] / proj[:, 2] - p2d[:, 1]) ** 2
        cost += np.where((proj[:, 2] > 0) & (sq < max_point_error ** 2), sq, max_point_error ** 2).sum(1)
    if M:
        nrm = np.repeat(_segment_planes(lines2d, K), 2, axis=0)  # (2M, 3)
        X = lines3d.reshape(-1, 3).astype(np.float32)
        Y = np.matmul(R.astype(np.float32), X.T)  # (H, 3, 2M): the camera-frame endpoints less t
        t32 = t.astype(np.float32)
        depth = Y[:, 2] + t32[:, 2:3]
        # a pixel distance times the endpoint's depth is linear in the camera-frame endpoint
        dist = np.einsum("hkp,pk->hp", Y, nrm.astype(np.float32)) + t32 @ nrm.T.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(depth > 0, np.abs(dist) / depth, np.inf).reshape(len(w), M, 2).sum(2)
        cost += np.minimum(r * r, max_line_error ** 2).sum(1)
    return cost


def _samples(n: int, k: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` draws of ``k`` distinct indices below ``n`` (k = 2 or 3), uniform."""
    if n < k or count <= 0:
        return np.zeros((0, k), np.int64)
    i = rng.integers(0, n, count)
    j = rng.integers(0, n - 1, count)
    j += j >= i
    if k == 2:
        return np.stack([i, j], 1)
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    m = rng.integers(0, n - 2, count)
    m += m >= lo
    m += m >= hi
    return np.stack([i, j, m], 1)


def pnpl_near_start(p2d, p3d, lines2d, lines3d, camera, start: np.ndarray, conf: Optional[NearRansacConfig] = None,
                    pose_conf: Optional[PointLinePoseConfig] = None) -> dict:
    """PnPL RANSAC about ``start`` (module docstring), then PoseLib's refinement over the best sample's inliers.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3); lines2d: (M, 2, 2); lines3d: (M, 2, 3) (candidates, any share wrong).
        start: (4, 4) cam_from_world near the pose.
        pose_conf: the final thresholds (``max_reproj_error``, ``max_line_error``), the refinement and ``seed``.

    Returns:
        the dict of :func:`~localization.estimate.pnpl_pose`; never raises for a bad query.
    """
    conf = conf or NearRansacConfig()
    pc = pose_conf or PointLinePoseConfig()
    p2d, p3d, l2, l3, fail = _point_line_input(p2d, p3d, lines2d, lines3d)
    okp = np.isfinite(p2d).all(1) & np.isfinite(p3d).all(1)
    okl = np.isfinite(l2).all((1, 2)) & np.isfinite(l3).all((1, 2)) & (np.abs(l2[:, 1] - l2[:, 0]).sum(1) > 0)
    if okl.sum() < pc.min_lines:
        return {**fail, "reason": f"{int(okl.sum())} line matches < {pc.min_lines}"}
    if okp.sum() + okl.sum() < 4:
        return {**fail, "reason": "fewer than 4 correspondences"}
    start = np.asarray(start, dtype=np.float64)
    R0, K = start[:3, :3], np.asarray(camera.K, dtype=np.float64)
    P2, P3, L2, L3 = p2d[okp], p3d[okp], l2[okl], l3[okl]
    rng = np.random.default_rng(pc.seed)
    best_T, best_cost = None, np.inf
    for _ in range(max(1, conf.passes)):
        A, b = match_equations(P2, P3, L2, L3, R0, camera)
        n = len(A)
        w, t = solve_samples(A, b, _samples(n, 2, conf.translation_samples, rng),
                             _samples(n, 3, conf.pose_samples, rng), conf.max_rotation_deg)
        if len(w) == 0:
            break
        cost = msac_costs(w, t, R0, P2, P3, L2, L3, K, pc.max_reproj_error, conf.score_line_error)
        # each of the best distinct samples refined once over its inliers; the cheapest at the final thresholds goes on
        picks = _distinct_best(w, t, -cost, max(1, conf.lo_best), conf.distinct_m, np.deg2rad(conf.distinct_deg))
        Ts = [_locally_optimised(make_T(Rotation.from_rotvec(w[k]).as_matrix() @ R0, t[k]), p2d, p3d, l2, l3, okp, okl,
                                 camera, conf.score_line_error, 1, pc) for k in picks]
        Ts = np.stack([T for T in Ts if np.isfinite(T).all()] or [np.full((4, 4), np.nan)])
        c = msac_costs(Rotation.from_matrix(Ts[:, :3, :3] @ R0.T).as_rotvec(), Ts[:, :3, 3], R0, P2, P3, L2, L3, K,
                       pc.max_reproj_error, pc.max_line_error) if np.isfinite(Ts).all() else np.full(1, np.inf)
        if c.min() < best_cost:
            best_T, best_cost = Ts[int(np.argmin(c))], float(c.min())
        if best_T is None:
            break
        R0 = best_T[:3, :3]
    if best_T is not None:
        best_T = _locally_optimised(best_T, p2d, p3d, l2, l3, okp, okl, camera, pc.max_line_error, conf.lo_rounds - 1, pc)
    if best_T is None:
        return {**fail, "reason": "no well-posed minimal sample"}
    return _pose_result(best_T, p2d, p3d, l2, l3, camera, pc.max_reproj_error, pc.max_line_error, fail)


def _distinct_best(w: np.ndarray, t: np.ndarray, score: np.ndarray, k: int, max_m: float, max_rad: float) -> list:
    """Indices of the ``k`` best-scoring samples, each farther than ``max_m`` in translation or ``max_rad`` in rotation
    (from the start, to first order) from the better ones chosen."""
    out = []
    for i in np.argsort(-score, kind="stable"):
        if all(np.linalg.norm(t[i] - t[j]) > max_m or np.linalg.norm(w[i] - w[j]) > max_rad for j in out):
            out.append(int(i))
            if len(out) == k:
                break
    return out


def _locally_optimised(T, p2d, p3d, l2, l3, okp, okl, camera, line_error: float, rounds: int,
                       pc: PointLinePoseConfig) -> np.ndarray:
    """``T`` after ``rounds`` weighted refinements, each over the inliers at the last pose (lines within
    ``line_error``)."""
    for _ in range(rounds):
        rp, rl = pnpl_residuals(p2d, p3d, l2, l3, T, camera)
        pi, li = _within_thresholds(rp, rl, pc.max_reproj_error, line_error)
        pi &= okp
        li &= okl
        if pi.sum() + li.sum() < 4:
            break
        pose = _weighted_refinement(p2d[pi], p3d[pi], l2[li], l3[li], _camera_pose(T), camera, pc,
                                    residuals=(rp[pi], rl[li]))
        T = make_T(np.asarray(pose.R), np.asarray(pose.t))
    return T
