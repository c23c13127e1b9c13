"""Surface normals from a depth map, for views that come without normal maps.

Convention: normals are unit vectors in the camera frame (x right, y down, z forward), oriented
towards the camera (n . X < 0 for the back-projected point X); invalid pixels are 0 - the same
convention as :func:`lipmap.imageio.read_normals` and :meth:`lipmap.scene.View.load_normals`.
"""
from __future__ import annotations

import numpy as np

from .errors import InputError


def normals_from_depth(depth: np.ndarray, camera, step: int = 1, max_rel_jump: float = 0.05) -> np.ndarray:
    """Camera-frame normals (H, W, 3) from a z-depth map (H, W) in metres (0 = invalid).

    Each pixel's 3D point X is joined to its neighbours ``step`` pixels right, down, left and up;
    each of the four quadrants (right-down, down-left, left-up, up-right) whose two neighbours are
    valid and on the same surface (relative depth jump <= ``max_rel_jump``) gives a cross-product
    normal, and the unit quadrant normals are averaged. So one-sided differences are used next to
    holes and depth discontinuities, and a pixel with no usable quadrant gets 0.

    Args:
        depth: :math:`(H, W)` metres, 0 (or non-finite) where invalid.
        camera: :class:`~lipmap.scene.Camera` of the depth map (COLMAP pixel centres).
        step: neighbour distance in pixels (larger = smoother, coarser).
        max_rel_jump: neighbours whose depth differs by more than this fraction are a different surface.

    Returns:
        :math:`(H, W, 3)` float32 unit normals facing the camera, 0 where undefined.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise InputError(f"depth must be (H, W), got shape {depth.shape}")
    if depth.shape != (camera.height, camera.width):
        raise InputError(f"depth is {depth.shape[1]}x{depth.shape[0]} but the camera is {camera.width}x{camera.height}")
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    X = camera.pixel_rays() * z[..., None]  # (H, W, 3)
    H, W = z.shape
    s = int(step)

    def shifted(a, dy, dx, fill=0.0):
        """out[j, i] = a[j + dy, i + dx] (``fill`` outside the image)."""
        out = np.full_like(a, fill)
        ys, yd = (slice(dy, H), slice(0, H - dy)) if dy >= 0 else (slice(0, H + dy), slice(-dy, H))
        xs, xd = (slice(dx, W), slice(0, W - dx)) if dx >= 0 else (slice(0, W + dx), slice(-dx, W))
        out[yd, xd] = a[ys, xs]
        return out

    ok_c = z > 0
    nbrs = {}
    for name, (dy, dx) in {"r": (0, s), "d": (s, 0), "l": (0, -s), "u": (-s, 0)}.items():
        zn = shifted(z, dy, dx)
        ok = ok_c & (zn > 0) & (np.abs(zn - z) <= max_rel_jump * np.maximum(z, 1e-9))
        nbrs[name] = (shifted(X, dy, dx) - X, ok)
    acc = np.zeros_like(X)
    for a, b in (("r", "d"), ("d", "l"), ("l", "u"), ("u", "r")):
        (va, oka), (vb, okb) = nbrs[a], nbrs[b]
        n = np.cross(va, vb)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        use = (oka & okb)[..., None] & (norm > 0)
        acc += np.where(use, n / np.maximum(norm, 1e-30), 0.0)
    norm = np.linalg.norm(acc, axis=-1, keepdims=True)
    n = np.where(norm > 1e-6, acc / np.maximum(norm, 1e-30), 0.0)
    # face the camera: the view ray to X is X itself
    flip = (n * X).sum(-1, keepdims=True) > 0
    n = np.where(flip, -n, n)
    return n.astype(np.float32)
