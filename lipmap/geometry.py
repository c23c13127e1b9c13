"""Projection and line-segment geometry: the ONE home of this math (mapping and localization import it).

Every function accepts numpy arrays, and the ones mapping needs gradients through also accept torch
tensors (same function, same formula; the backend follows the input). Shapes broadcast, so the
pairwise (N x M) versions are the element-wise ones called on ``a[:, None]`` and ``b[None]``.

Conventions:
- Poses are ``cam_from_world`` 4x4 (x_cam = R x_world + t). Pixels follow COLMAP: the centre of
  pixel (col i, row j) is at (i + 0.5, j + 0.5) (see :mod:`lipmap.scene`).
- A 2D segment is (..., 2, 2) = (endpoint, xy); (..., 4) = (x1, y1, x2, y2) is accepted everywhere
  and reshaped. A 3D segment is (..., 2, 3).
- Segment measures follow the LiP-Map paper, appendix "Geometric Consistency Measures", with
  ``a`` = the projected (reconstructed) segment L1 and ``b`` = the detected segment L2:
  angle distance, max (or mean) distance of a's endpoints to the infinite line of b, and the overlap
  ratio |inner projection of a onto b| / |b|. None of them is symmetric in (a, b) except the angle.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .errors import InputError

_EPS = 1e-12


# ----------------------------------------------------------------------------------------------
# backend helpers: numpy or torch, chosen by the input type (torch is imported only when used)
# ----------------------------------------------------------------------------------------------
def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def _xp(*xs):
    """The array namespace of the inputs: torch if any of them is a tensor, else numpy."""
    for x in xs:
        if _is_torch(x):
            import torch

            return torch
    return np


def _asarray_like(x, ref):
    """``x`` converted to the backend, dtype and device of ``ref``."""
    if _is_torch(ref):
        import torch

        if _is_torch(x):
            return x.to(dtype=ref.dtype, device=ref.device)
        return torch.as_tensor(np.asarray(x), dtype=ref.dtype, device=ref.device)
    ref = np.asarray(ref)
    return np.asarray(x, dtype=ref.dtype if ref.dtype.kind == "f" else np.float64)


def _as_float(x):
    if _is_torch(x):
        return x if x.is_floating_point() else x.float()
    x = np.asarray(x)
    return x if x.dtype.kind == "f" else x.astype(np.float64)


def _norm(v, keepdims: bool = False):
    """Euclidean norm over the last axis (gradient-safe at 0 for torch)."""
    sq = (v * v).sum(axis=-1, keepdims=keepdims)
    if _is_torch(sq):
        import torch

        # clamping (not adding) keeps exact values; the clamp zeroes the undefined gradient at 0
        return torch.sqrt(sq.clamp(min=1e-30))
    return np.sqrt(sq)


def _cross2(u, v):
    """z component of the 2D cross product, (..., 2) x (..., 2) -> (...)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _check_last(x, dims: tuple, name: str):
    if tuple(x.shape[-len(dims):]) != tuple(dims) or x.ndim < len(dims):
        raise InputError(f"{name} must have shape (..., {', '.join(map(str, dims))}), got {tuple(x.shape)}")


def as_segments2d(seg):
    """(..., 4) or (..., 2, 2) -> (..., 2, 2) float (a view when possible)."""
    seg = _as_float(seg)
    if seg.shape[-1] == 4:
        return seg.reshape(*seg.shape[:-1], 2, 2)
    _check_last(seg, (2, 2), "2D segments")
    return seg


def as_segments3d(seg):
    """(..., 6) or (..., 2, 3) -> (..., 2, 3) float."""
    seg = _as_float(seg)
    if seg.shape[-1] == 6:
        return seg.reshape(*seg.shape[:-1], 2, 3)
    _check_last(seg, (2, 3), "3D segments")
    return seg


def _intrinsics(camera, ref):
    """(fx, fy, cx, cy) from a :class:`~lipmap.scene.Camera`, a 3x3 K or a 4-vector."""
    if hasattr(camera, "params"):
        return tuple(float(p) for p in camera.params)
    K = camera
    if _is_torch(K):
        if K.shape == (3, 3):
            return K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        return K[0], K[1], K[2], K[3]
    K = np.asarray(K, dtype=float)
    if K.shape == (3, 3):
        return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    if K.shape == (4,):
        return tuple(float(k) for k in K)
    raise InputError(f"camera must be a Camera, a 3x3 K or (fx, fy, cx, cy); got shape {K.shape}")


# ----------------------------------------------------------------------------------------------
# projection
# ----------------------------------------------------------------------------------------------
def transform_points(T, points):
    """Apply a 4x4 rigid transform to points (..., 3) -> (..., 3)."""
    points = _as_float(points)
    T = _asarray_like(T, points)
    if isinstance(points, np.ndarray) and points.ndim > 2:
        # one (N, 3) product instead of a stack of small ones (segments are (N, 2, 3)): 3x faster, the same bits
        return (points.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]).reshape(points.shape)
    return points @ T[:3, :3].T + T[:3, 3]


def project_points(points_world, cam_from_world, camera):
    """Project world points into a pinhole camera.

    Args:
        points_world: :math:`(..., 3)` world points (numpy or torch).
        cam_from_world: :math:`(4, 4)` pose.
        camera: :class:`~lipmap.scene.Camera`, 3x3 K or (fx, fy, cx, cy).

    Returns:
        **uv** :math:`(..., 2)` pixel coordinates (COLMAP convention) and **depth** :math:`(...)`,
        the camera-frame z. Points with depth <= 0 get meaningless uv: mask them with ``depth``.
    """
    points_world = _as_float(points_world)
    _check_last(points_world, (3,), "points_world")
    p = transform_points(cam_from_world, points_world)
    return project_cam_points(p, camera)


def project_cam_points(points_cam, camera):
    """Camera-frame points (..., 3) -> (uv (..., 2), depth (...)); no clipping."""
    fx, fy, cx, cy = _intrinsics(camera, points_cam)
    z = points_cam[..., 2]
    xp = _xp(points_cam)
    zs = xp.where(xp.abs(z) > _EPS, z, xp.full_like(z, _EPS))
    u = fx * points_cam[..., 0] / zs + cx
    v = fy * points_cam[..., 1] / zs + cy
    return xp.stack([u, v], axis=-1), z


def projection_matrices(cam_from_world, camera) -> np.ndarray:
    """``K [R | t]``: :math:`(..., 4, 4)` poses and a Camera / K (or :math:`(..., 3, 3)` Ks) -> :math:`(..., 3, 4)`."""
    K = np.asarray(camera.K if hasattr(camera, "K") else camera, dtype=float)
    return K @ np.asarray(cam_from_world, dtype=float)[..., :3, :]


def backprojected_planes(segments2d, projections) -> np.ndarray:
    """World planes through each camera centre and the infinite line of its 2D segment (numpy).

    Scaled so that ``planes[i] @ [X, 1]`` is camera i's depth of ``X`` times the pixel distance of X's
    projection from the segment's line: divided by that depth it is a reprojection error in pixels.

    Args:
        segments2d: :math:`(M, 2, 2)` (or (M, 4)) pixel segments.
        projections: :math:`(M, 3, 4)` or :math:`(3, 4)` (:func:`projection_matrices`).

    Returns:
        **planes** :math:`(M, 4)`.
    """
    seg = np.asarray(as_segments2d(segments2d), dtype=float)
    h = np.concatenate([seg, np.ones_like(seg[..., :1])], -1)
    line = np.cross(h[:, 0], h[:, 1])
    line /= np.maximum(np.linalg.norm(line[:, :2], axis=-1, keepdims=True), _EPS)
    P = np.broadcast_to(np.asarray(projections, dtype=float), (len(seg), 3, 4))
    return np.einsum("mi,mij->mj", line, P)


def unproject_points(uv, depth, camera):
    """Pixels :math:`(..., 2)` (COLMAP convention) at camera-frame z ``depth`` :math:`(...)` -> camera-frame
    points :math:`(..., 3)`; the inverse of :func:`project_cam_points`."""
    uv = _as_float(uv)
    _check_last(uv, (2,), "uv")
    fx, fy, cx, cy = _intrinsics(camera, uv)
    xp = _xp(uv)
    z = _asarray_like(depth, uv) * xp.ones_like(uv[..., 0])
    return xp.stack([(uv[..., 0] - cx) / fx * z, (uv[..., 1] - cy) / fy * z, z], axis=-1)


def backproject_depth(depth: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame 3D points :math:`(N, 3)` of the valid (> 0) pixels of ``depth`` :math:`(H, W)`, and their
    flat pixel indices :math:`(N,)`; rays through the pixel centres (COLMAP convention)."""
    rays = camera.pixel_rays().reshape(-1, 3)
    d = depth.reshape(-1)
    idx = np.flatnonzero(d > 0)
    return rays[idx] * d[idx, None], idx


def clip_segments_near(segments_cam, near: float = 1e-3):
    """Clip camera-frame 3D segments to the half-space z >= near.

    A segment crossing the near plane keeps its visible part (its behind-camera endpoint moves to
    the crossing), so a projection never flips through infinity.

    Args:
        segments_cam: :math:`(..., 2, 3)` segments in the camera frame.

    Returns:
        **clipped** :math:`(..., 2, 3)` and **valid** :math:`(...)` bool (False: wholly behind;
        those keep their input coordinates).
    """
    s = as_segments3d(segments_cam)
    xp = _xp(s)
    p0, p1 = s[..., 0, :], s[..., 1, :]
    z0, z1 = p0[..., 2], p1[..., 2]
    in0, in1 = z0 >= near, z1 >= near
    dz = z1 - z0
    safe = xp.where(xp.abs(dz) > _EPS, dz, xp.ones_like(dz))
    t = ((near - z0) / safe)[..., None]
    crossing = p0 + t * (p1 - p0)
    q0 = xp.where((~in0 & in1)[..., None], crossing, p0)
    q1 = xp.where((in0 & ~in1)[..., None], crossing, p1)
    return xp.stack([q0, q1], axis=-2), in0 | in1


def project_segments(segments_world, cam_from_world, camera, near: float = 1e-3):
    """Project 3D segments into an image, clipping them to z >= near first.

    Args:
        segments_world: :math:`(N, 2, 3)` (or (..., 2, 3)) world segments.
        cam_from_world: :math:`(4, 4)`.
        camera: Camera, K or (fx, fy, cx, cy).
        near: near-plane depth in metres.

    Returns:
        **segments2d** :math:`(N, 2, 2)` in pixels (NaN where invalid) and **valid** :math:`(N,)`
        (False for segments wholly behind the near plane). No clipping to the image borders.
    """
    s = as_segments3d(segments_world)
    s_cam = transform_points(cam_from_world, s)
    s_cam, valid = clip_segments_near(s_cam, near)
    uv, _ = project_cam_points(s_cam, camera)
    xp = _xp(uv)
    nan = xp.full_like(uv, float("nan"))
    return xp.where(valid[..., None, None], uv, nan), valid


def clip_segments_to_image(segments2d, width: float, height: float):
    """Clip 2D segments (N, 2, 2) to the image rectangle [0, W] x [0, H] (Liang-Barsky).

    Returns the clipped segments and a validity mask (False: no part inside). numpy only.
    """
    s = np.asarray(as_segments2d(segments2d), dtype=float)
    p0, d = s[..., 0, :], s[..., 1, :] - s[..., 0, :]
    t0 = np.zeros(s.shape[:-2])
    t1 = np.ones(s.shape[:-2])
    valid = np.isfinite(s).all(axis=(-1, -2))
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, lo, hi in ((0, 0.0, float(width)), (1, 0.0, float(height))):
            for p, q in ((-d[..., k], p0[..., k] - lo), (d[..., k], hi - p0[..., k])):
                par = p == 0
                valid &= ~(par & (q < 0))
                r = q / np.where(par, 1.0, p)
                t0 = np.where(~par & (p < 0), np.maximum(t0, r), t0)
                t1 = np.where(~par & (p > 0), np.minimum(t1, r), t1)
    valid &= t0 <= t1
    out = np.stack([p0 + t0[..., None] * d, p0 + t1[..., None] * d], axis=-2)
    return out, valid


def segments_in_image(segments2d, width: float, height: float) -> np.ndarray:
    """Whether each 2D segment (N, 2, 2) has some part in the image rectangle [0, W] x [0, H]: the validity of
    :func:`clip_segments_to_image` without the clipped segments, by separating axes (the rectangle's two and the
    segment's normal), at a fifth of the cost. NaN segments are outside. numpy only."""
    s = np.asarray(as_segments2d(segments2d), dtype=float)
    p, q = s[..., 0, :], s[..., 1, :]
    lo, hi = np.minimum(p, q), np.maximum(p, q)
    with np.errstate(invalid="ignore"):
        ok = (hi[..., 0] >= 0) & (lo[..., 0] <= width) & (hi[..., 1] >= 0) & (lo[..., 1] <= height)
        d = q - p
        # the segment's line has the rectangle's corners on both sides (or on it)
        side = [d[..., 0] * (y - p[..., 1]) - d[..., 1] * (x - p[..., 0])
                for x, y in ((0.0, 0.0), (width, 0.0), (0.0, height), (width, height))]
        ok &= (np.minimum(np.minimum(side[0], side[1]), np.minimum(side[2], side[3])) <= 0)
        ok &= (np.maximum(np.maximum(side[0], side[1]), np.maximum(side[2], side[3])) >= 0)
    return ok


# ----------------------------------------------------------------------------------------------
# 2D segment measures (paper appendix "Geometric Consistency Measures")
# ----------------------------------------------------------------------------------------------
def segment_lengths(segments):
    """Lengths of 2D or 3D segments (..., 2, D) (or (..., 4) for 2D) -> (...)."""
    s = _as_float(segments)
    if s.shape[-1] == 4:
        s = as_segments2d(s)
    return _norm(s[..., 1, :] - s[..., 0, :])


def angle_distance(a, b):
    """Undirected angle between 2D segments, in [0, pi/2].

    Equals the paper's arccos(|d_a . d_b| / (|d_a| |d_b|)), computed as atan2(|d_a x d_b|, |d_a . d_b|)
    so that it is exact near 0 and has finite gradients there.

    Args:
        a: :math:`(..., 2, 2)` or (..., 4) segments; b: broadcastable with a.

    Returns:
        :math:`(...)` radians.
    """
    a, b = as_segments2d(a), as_segments2d(b)
    xp = _xp(a, b)
    da = a[..., 1, :] - a[..., 0, :]
    db = b[..., 1, :] - b[..., 0, :]
    return xp.arctan2(xp.abs(_cross2(da, db)), xp.abs((da * db).sum(axis=-1)))


def point_line_distance(points, segments):
    """Distance of points (..., D) to the INFINITE lines through segments (..., 2, D), D = 2 or 3.

    (2D segments may also be given as (..., 4).)
    """
    points = _as_float(points)
    if points.shape[-1] == 2:
        s = as_segments2d(segments)
        d = s[..., 1, :] - s[..., 0, :]
        xp = _xp(points, s)
        return xp.abs(_cross2(d, points - s[..., 0, :])) / _norm(d).clip(min=_EPS)
    s = _as_float(segments)
    d = s[..., 1, :] - s[..., 0, :]
    r = points - s[..., 0, :]
    t = (r * d).sum(axis=-1, keepdims=True) / (d * d).sum(axis=-1, keepdims=True).clip(min=_EPS)
    return _norm(r - t * d)


def perpendicular_distance(a, b, reduce: Optional[str] = "max"):
    """Distances of segment a's two endpoints to the infinite line of segment b (2D).

    The paper's orthogonal distance d_dist is ``reduce="max"`` with a = projection, b = detection.

    Args:
        a, b: :math:`(..., 2, 2)` broadcastable 2D segments.
        reduce: "max", "mean", or None for both endpoint distances.

    Returns:
        :math:`(...)` pixels, or :math:`(..., 2)` with ``reduce=None``.
    """
    a, b = as_segments2d(a), as_segments2d(b)
    d = point_line_distance(a, b[..., None, :, :])
    if reduce is None:
        return d
    if reduce == "max":
        return d.max(axis=-1) if not _is_torch(d) else d.amax(dim=-1)
    if reduce == "mean":
        return d.mean(axis=-1)
    raise ValueError(f"reduce must be 'max', 'mean' or None, got {reduce!r}")


def overlap_ratio(a, b):
    """Length of the part of a's projection onto b that lies inside b, divided by |b|, in [0, 1].

    Args:
        a, b: :math:`(..., 2, 2)` broadcastable 2D segments (a = projected L1, b = detected L2).

    Returns:
        :math:`(...)`. A degenerate b gives 0.
    """
    a, b = as_segments2d(a), as_segments2d(b)
    xp = _xp(a, b)
    db = b[..., 1, :] - b[..., 0, :]
    l2 = (db * db).sum(axis=-1)
    t = ((a - b[..., None, 0, :]) * db[..., None, :]).sum(axis=-1) / l2[..., None].clip(min=_EPS)
    lo = xp.minimum(t[..., 0], t[..., 1]).clip(0.0, 1.0)
    hi = xp.maximum(t[..., 0], t[..., 1]).clip(0.0, 1.0)
    return xp.where(l2 > _EPS, hi - lo, xp.zeros_like(l2))


def point_segment_distance(points, segments):
    """Distance of points (..., D) to segments (..., 2, D), D = 2 or 3, broadcasting.

    Pairwise P x M: ``point_segment_distance(points[:, None], segments[None])``.
    """
    points = _as_float(points)
    s = _as_float(segments)
    xp = _xp(points, s)
    p0 = s[..., 0, :]
    d = s[..., 1, :] - p0
    l2 = (d * d).sum(axis=-1)
    t = ((points - p0) * d).sum(axis=-1) / l2.clip(min=_EPS)
    t = xp.where(l2 > _EPS, t.clip(0.0, 1.0), xp.zeros_like(t))
    return _norm(points - (p0 + t[..., None] * d))


def endpoint_distance(a, b, reduce: Optional[str] = "mean"):
    """Distances between corresponding endpoints of segments a and b (..., 2, D); order as given."""
    a, b = _as_float(a), _as_float(b)
    d = _norm(a - b)
    if reduce is None:
        return d
    if reduce == "mean":
        return d.mean(axis=-1)
    if reduce == "max":
        return d.max(axis=-1) if not _is_torch(d) else d.amax(dim=-1)
    raise ValueError(f"reduce must be 'max', 'mean' or None, got {reduce!r}")


def align_endpoints(a, b):
    """Reorder the endpoints of a (..., 2, D) so that a[0] is the one nearer b[0] (swap if cheaper)."""
    a, b = _as_float(a), _as_float(b)
    xp = _xp(a, b)
    direct = _norm(a[..., 0, :] - b[..., 0, :]) + _norm(a[..., 1, :] - b[..., 1, :])
    swapped = _norm(a[..., 1, :] - b[..., 0, :]) + _norm(a[..., 0, :] - b[..., 1, :])
    flip = (swapped < direct)[..., None, None]
    a_flip = a.flip(-2) if xp is not np else a[..., ::-1, :]
    return xp.where(flip, a_flip, a)


def pairwise_angle_distance(a, b):
    """(N, 2, 2) x (M, 2, 2) -> (N, M) angle distances."""
    return angle_distance(as_segments2d(a)[:, None], as_segments2d(b)[None])


def pairwise_perpendicular_distance(a, b, reduce: str = "max"):
    """(N, 2, 2) x (M, 2, 2) -> (N, M): endpoints of a[i] to the line of b[j]."""
    return perpendicular_distance(as_segments2d(a)[:, None], as_segments2d(b)[None], reduce=reduce)


def pairwise_overlap_ratio(a, b):
    """(N, 2, 2) x (M, 2, 2) -> (N, M): overlap of a[i] on b[j] relative to |b[j]|."""
    return overlap_ratio(as_segments2d(a)[:, None], as_segments2d(b)[None])


def match_segments_2d(
    projected, detected, max_angle: float = 0.01, max_dist: float = 2.0, min_overlap: float = 0.2, chunk: int = 4096
) -> np.ndarray:
    """The paper's track-builder test between projected 3D lines and detected 2D lines (numpy).

    Pair (i, j) matches when angle(p_i, d_j) < max_angle, the max distance of p_i's endpoints to the
    line of d_j < max_dist (px) and overlap(p_i on d_j) > min_overlap. Defaults are the paper's
    (0.01 rad, 2 px, 0.2). Invalid (NaN) projections match nothing.

    Args:
        projected: :math:`(N, 2, 2)`; detected: :math:`(M, 2, 2)` (or (.., 4)).

    Returns:
        **matches** :math:`(N, M)` bool.
    """
    p = np.asarray(as_segments2d(projected), dtype=float)
    d = np.asarray(as_segments2d(detected), dtype=float)
    out = np.zeros((len(p), len(d)), dtype=bool)
    if len(p) == 0 or len(d) == 0:
        return out
    for i in range(0, len(p), chunk):
        pi = p[i : i + chunk]
        with np.errstate(invalid="ignore"):
            m = pairwise_angle_distance(pi, d) < max_angle
            if m.any():
                m &= pairwise_perpendicular_distance(pi, d, "max") < max_dist
            if m.any():
                m &= pairwise_overlap_ratio(pi, d) > min_overlap
        out[i : i + chunk] = m
    return out


# ----------------------------------------------------------------------------------------------
# 3D segments
# ----------------------------------------------------------------------------------------------
def sample_segments(segments, n: int):
    """``n`` evenly spaced points on each segment, endpoints included: (..., 2, D) -> (..., n, D)."""
    s = _as_float(segments)
    xp = _xp(s)
    if n < 1:
        raise ValueError("n must be >= 1")
    if xp is np:
        t = np.linspace(0.0, 1.0, n) if n > 1 else np.array([0.5])
        t = t.astype(s.dtype)
    else:
        t = xp.linspace(0.0, 1.0, n, dtype=s.dtype, device=s.device) if n > 1 else xp.full((1,), 0.5, dtype=s.dtype, device=s.device)
    p0 = s[..., 0:1, :]
    return p0 + t[:, None] * (s[..., 1:2, :] - p0)


def segment_to_segment_distance(a, b, n_samples: int = 10, reduce: str = "mean", symmetric: bool = False):
    """Distance between 3D (or 2D) segments by sampling ``n_samples`` points on a.

    Args:
        a, b: :math:`(..., 2, D)` broadcastable (pairwise: ``a[:, None], b[None]``).
        reduce: "mean" or "max" over the samples.
        symmetric: also sample b and take the larger of the two directed distances.

    Returns:
        :math:`(...)`.
    """
    a, b = _as_float(a), _as_float(b)

    def directed(x, y):
        d = point_segment_distance(sample_segments(x, n_samples), y[..., None, :, :])
        if reduce == "mean":
            return d.mean(axis=-1)
        if reduce == "max":
            return d.max(axis=-1) if not _is_torch(d) else d.amax(dim=-1)
        raise ValueError(f"reduce must be 'mean' or 'max', got {reduce!r}")

    d = directed(a, b)
    if symmetric:
        xp = _xp(d)
        d = xp.maximum(d, directed(b, a))
    return d


def fit_line(points, weights=None):
    """Least-squares 3D (or 2D) line through points (K, D) by PCA.

    Returns:
        **center** (D,), unit **direction** (D,), **rms** perpendicular residual.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or len(P) < 2:
        raise ValueError(f"fit_line needs (K>=2, D) points, got {P.shape}")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float)
    c = (w[:, None] * P).sum(0) / w.sum()
    Q = P - c
    _, s, vt = np.linalg.svd(Q * np.sqrt(w)[:, None], full_matrices=False)
    direction = vt[0]
    resid = Q - (Q @ direction)[:, None] * direction
    rms = float(np.sqrt((w * (resid**2).sum(1)).sum() / w.sum()))
    return c, direction, rms


def fit_segment(points, weights=None) -> np.ndarray:
    """PCA line through points (K, D), bounded by the extreme projections: (2, D)."""
    c, d, _ = fit_line(points, weights)
    t = (np.asarray(points, dtype=float) - c) @ d
    return np.stack([c + t.min() * d, c + t.max() * d])


def closest_point_params(p1, d1, p2, d2):
    """Parameters (s, t) of the mutually closest points p1 + s d1 and p2 + t d2 of two lines.

    Broadcasts over (..., 3). Parallel lines get s = 0 and t = projection of p1 (finite).
    """
    p1, d1, p2, d2 = (np.asarray(x, dtype=float) for x in (p1, d1, p2, d2))
    r = p1 - p2
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    b = (d1 * d2).sum(-1)
    c = (d1 * r).sum(-1)
    f = (d2 * r).sum(-1)
    den = a * e - b * b
    par = den <= 1e-12 * np.maximum(a * e, _EPS)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(par, 0.0, (b * f - c * e) / np.where(par, 1.0, den))
        t = np.where(par, f / np.maximum(e, _EPS), (a * f - b * c) / np.where(par, 1.0, den))
    return s, t


def ray_plane_intersection(origins, directions, plane_points, plane_normals):
    """Ray parameter t of the hit x = o + t d with the planes (n . (x - p) = 0); numpy or torch.

    Broadcasts (..., 3). Rays parallel to a plane get t = inf (nan for a ray inside the plane is
    also returned as inf). Negative t means the plane is behind the ray origin.
    """
    o, d = _as_float(origins), _as_float(directions)
    p, n = _asarray_like(plane_points, o), _asarray_like(plane_normals, o)
    xp = _xp(o, d)
    den = (d * n).sum(axis=-1)
    num = ((p - o) * n).sum(axis=-1)
    ok = xp.abs(den) > _EPS
    safe = xp.where(ok, den, xp.ones_like(den))
    inf = xp.full_like(den, float("inf"))
    return xp.where(ok, num / safe, inf)


__all__ = [
    "as_segments2d",
    "as_segments3d",
    "transform_points",
    "project_points",
    "project_cam_points",
    "clip_segments_near",
    "project_segments",
    "clip_segments_to_image",
    "segments_in_image",
    "segment_lengths",
    "angle_distance",
    "point_line_distance",
    "perpendicular_distance",
    "overlap_ratio",
    "point_segment_distance",
    "endpoint_distance",
    "align_endpoints",
    "pairwise_angle_distance",
    "pairwise_perpendicular_distance",
    "pairwise_overlap_ratio",
    "match_segments_2d",
    "sample_segments",
    "segment_to_segment_distance",
    "fit_line",
    "fit_segment",
    "closest_point_params",
    "ray_plane_intersection",
]
