"""One (pixel, plane) pair of the plane renderer, the torch definitions both backends share: the planes moved into the
camera (:func:`_planes_in_camera`; Warp's ``_setup_fwd``), their packed table, the pixel rays, and a ray's depth and
splat weight on a plane (:func:`_pair_terms`; Warp's ``_pair_geo``). Written out component by component in the order
the Warp kernels transcribe, so both backends see bit-identical pairs and select the same hits.
"""
from __future__ import annotations

import functools
import math

import torch

from ..errors import InputError
from .primitives import NEAR, R_MAX, R_MIN, WEIGHT_EPS, quat_to_rotmat

TILE_SIZE = 8
# screen boxes are dilated 1 % beyond the weight-1e-4 footprint, so that round-off in the per-pixel
# weight cannot put a selected pair outside its plane's box
BIN_SLACK = 1.01
# packed per-plane table: centre, X axis, Y axis, normal (camera frame, facing the camera), radii, n . c
_C, _AX, _AY, _N, _R, _NC = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 16), 16


def _planes_in_camera(center, quat, radii, cam_from_world):
    """Camera-frame centres (K,3), axes X, Y, normal (K,3 each; normal flipped to face the camera), radii (K,4).

    The per-plane setup, written out component by component in the order raster_warp's ``_setup_fwd`` transcribes
    (a matmul sums in an order of its own): both backends then see bit-identical planes, and so select the same
    hits. Differentiable (autograd here; the Warp kernel has its hand-derived reverse, ``_setup_bwd``).
    """
    T = cam_from_world.to(device=center.device, dtype=center.dtype)
    M = quat_to_rotmat(quat)
    cx, cy, cz = center.unbind(-1)

    def row(i, a, b, d):  # T[i, :3] . (a, b, d), left to right
        return T[i, 0] * a + T[i, 1] * b + T[i, 2] * d

    c = torch.stack([row(i, cx, cy, cz) + T[i, 3] for i in range(3)], -1)
    ax, ay, n = (torch.stack([row(i, M[:, 0, j], M[:, 1, j], M[:, 2, j]) for i in range(3)], -1) for j in range(3))
    n = torch.where((_dot3(n, c) > 0)[:, None], -n, n)
    return c, ax, ay, n, radii.clamp(R_MIN, R_MAX)


def _dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(K,3) . (K,3) -> (K,), summed left to right as the Warp kernels do."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _plane_table(c, ax, ay, n, r) -> torch.Tensor:
    """Detached (17, K+1) table, component-major: rows c, X, Y, n (3 each), r (4), n . c; column K is a dummy
    whose intersections lie behind the camera. Component-major, so that each gathered component is contiguous
    (elementwise ops on strided columns do not vectorize)."""
    with torch.no_grad():
        tab = torch.cat([c, ax, ay, n, r, _dot3(n, c)[:, None]], 1)
        dummy = torch.zeros(1, 17, dtype=tab.dtype, device=tab.device)
        dummy[0, 11], dummy[0, 12:16], dummy[0, _NC] = 1.0, R_MIN, -1.0  # normal +z, n . c = -1: t = -1 < NEAR
        return torch.cat([tab, dummy]).T.contiguous()


def _gather(tab: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """(17, *idx.shape): the table's columns ``idx``."""
    return tab.index_select(1, idx.reshape(-1)).reshape(tab.shape[0], *idx.shape)


@functools.lru_cache(maxsize=64)
def _pixel_axes(width: int, height: int, intrinsics: tuple, dtype, device):
    """x / z of each column's and y / z of each row's pixel centre (COLMAP convention): (W,), (H,). Cached per camera
    (a training loop renders the same few cameras thousands of times); read-only."""
    fx, fy, cx, cy = intrinsics
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5 - cx) / fx
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5 - cy) / fy
    return u, v


def _pair_terms(g: torch.Tensor, u: torch.Tensor, v: torch.Tensor, lam: float, full: bool = False):
    """Depth t and splat weight w of rays (u, v, 1) on planes ``g`` (columns of :func:`_plane_table`).

    ``g`` is :math:`(17, ...)`, ``u`` and ``v`` broadcast against ``g[0]``. The one definition of a
    (pixel, plane) pair, shared by the selection, the compositing and (transcribed) the Warp kernel;
    the explicit component order keeps the arithmetic, and so the hits, identical across them.
    Returns ``t, w`` or, with ``full``, also the terms the backward pass needs.
    """
    c0, c1, c2, x0, x1, x2, y0, y1, y2, n0, n1, n2, rxp, rxm, ryp, rym, nc = g.unbind(0)
    den = n0 * u + n1 * v + n2
    t = nc / den
    qx, qy, qz = t * u - c0, t * v - c1, t - c2  # intersection relative to the centre
    px = qx * x0 + qy * x1 + qz * x2
    py = qx * y0 + qy * y1 + qz * y2
    zx = lam * (torch.where(px > 0, rxp, rxm) - px.abs())
    zy = lam * (torch.where(py > 0, ryp, rym) - py.abs())
    # w = min(w(zx), w(zy)) = w(min(zx, zy)): one sigmoid per pair
    z = torch.minimum(zx, zy)
    s = torch.sigmoid(z)
    w = torch.where(z >= 0, 1.0, 2 * s)
    if not full:
        return t, w
    return t, w, dict(den=den, q=(qx, qy, qz), px=px, py=py, zx=zx, zy=zy, z=z, s=s)


def _valid(t: torch.Tensor, w: torch.Tensor, near: float = NEAR) -> torch.Tensor:
    """Pairs a pixel composites at most: in front of the near plane (z = ``near``), finite, splat weight above
    WEIGHT_EPS."""
    return (t > near) & (t < math.inf) & (w > WEIGHT_EPS)


def check_near(near: float) -> None:
    """Refuse a near plane that is not at a finite z > 0 (an :class:`~lipmap.errors.InputError`, a ValueError).

    The screen boxes project the corners of the rectangles clipped to z >= near and divide by that z: at z = 0 a
    plane through the camera plane projects to infinity, and no pixel could be binned.
    """
    if not (0.0 < near < math.inf):
        raise InputError(f"the near plane must lie at a finite z > 0, got {near}")


def _check_inputs(center, quat, radii, cam_from_world, width, height):
    if center.ndim != 2 or center.shape[1] != 3 or quat.shape != (len(center), 4) or radii.shape != (len(center), 4):
        raise InputError(
            f"planes must be center (K,3), quat (K,4), radii (K,4); got {tuple(center.shape)}, "
            f"{tuple(quat.shape)}, {tuple(radii.shape)}"
        )
    if tuple(cam_from_world.shape) != (4, 4):
        raise InputError(f"cam_from_world must be 4x4, got {tuple(cam_from_world.shape)}")
    if width <= 0 or height <= 0:
        raise InputError(f"image size must be positive, got {width}x{height}")

