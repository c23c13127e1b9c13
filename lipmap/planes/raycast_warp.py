"""The first rectangle each ray meets (hard borders) as one Warp kernel, on CPU and CUDA.

The fused twin of :func:`lipmap.mapping.assign.first_hit_in_render` (a render's hit lists first, every plane only
for the rays whose list may have been cut) and of :func:`~lipmap.mapping.assign.first_hit_torch` (every plane).
``_ray_rect`` transcribes :func:`~lipmap.mapping.assign._ray_rect_t` operation by operation, and ties go to the
earlier candidate as ``torch.min`` gives them, so both paths pick the same plane. One thread per ray: no (rays x
planes) tensor is ever made, which is what the torch twin spends its time allocating. Float32 only.
"""
from __future__ import annotations

import functools
import math

import torch

from .raster_warp import _kernels
from .warp_runtime import device_name, launch_chunks, n_chunks, stream, wrap


def unsupported(device: torch.device, dtype: torch.dtype) -> str | None:
    """Why the kernel cannot cast these rays (None: it can); the renderer's conditions."""
    from .raster_warp import unsupported as raster_unsupported

    return raster_unsupported(device, dtype, 1)


@functools.lru_cache(maxsize=None)
def _kernel():
    kn = _kernels()
    if kn is None:
        return None
    wp = kn["wp"]
    inf = wp.constant(math.inf)

    @wp.func
    def _ray_rect(v3: wp.vec3, X: wp.vec3, Y: wp.vec3, lx: float, ly: float, n: wp.vec3, o: wp.vec3, d: wp.vec3):
        # assign._ray_rect_t, in its order: inf where the ray misses the rectangle or meets it behind the origin
        denom = d[0] * n[0] + d[1] * n[1] + d[2] * n[2]
        safe = denom
        if not (wp.abs(denom) > 1.0e-12):
            safe = 1.0e-12
        t = ((v3[0] - o[0]) * n[0] + (v3[1] - o[1]) * n[1] + (v3[2] - o[2]) * n[2]) / safe
        rx = o[0] + t * d[0] - v3[0]
        ry = o[1] + t * d[1] - v3[1]
        rz = o[2] + t * d[2] - v3[2]
        u = rx * X[0] + ry * X[1] + rz * X[2]
        w = rx * Y[0] + ry * Y[1] + rz * Y[2]
        if t > 1.0e-6 and wp.abs(denom) > 1.0e-12 and u >= 0.0 and u <= lx and w >= 0.0 and w <= ly:
            return t
        return inf

    @wp.kernel(enable_backward=False)
    def _first_hit(
        v3: wp.array(dtype=wp.vec3), X: wp.array(dtype=wp.vec3), Y: wp.array(dtype=wp.vec3),
        lx: wp.array(dtype=float), ly: wp.array(dtype=float), n: wp.array(dtype=wp.vec3),
        cand: wp.array2d(dtype=wp.int64), complete: wp.array(dtype=wp.int32), o: wp.array(dtype=wp.vec3),
        d: wp.array(dtype=wp.vec3), n_rays: int, chunk: int, n_chunks: int, out: wp.array(dtype=wp.int64),
    ):
        i = wp.tid() * n_chunks + chunk  # rays interleaved over the CPU threads' launches
        if i >= n_rays:
            return
        oi, di = o[i], d[i]
        best_t = inf
        best = wp.int64(-1)
        for j in range(cand.shape[1]):
            k = cand[i, j]
            if k >= wp.int64(0):
                t = _ray_rect(v3[k], X[k], Y[k], lx[k], ly[k], n[k], oi, di)
                if t < best_t:
                    best_t = t
                    best = k
        if best < wp.int64(0) and complete[i] == 0:
            for kk in range(v3.shape[0]):
                t = _ray_rect(v3[kk], X[kk], Y[kk], lx[kk], ly[kk], n[kk], oi, di)
                if t < best_t:
                    best_t = t
                    best = wp.int64(kk)
        out[i] = best

    return wp, _first_hit


def first_hit(frames, origins: torch.Tensor, dirs: torch.Tensor, candidates: torch.Tensor | None = None,
              complete: torch.Tensor | None = None) -> torch.Tensor:
    """The first rectangle each ray meets: :math:`(P,)` int64, -1 where none.

    Args:
        frames: the rectangles as :func:`lipmap.mapping.assign._rect_frames` gives them (v3, X, Y, lx, ly, n).
        origins, dirs: :math:`(P, 3)` world rays (dirs unit).
        candidates: :math:`(P, M)` int64 planes to try first (-1 padded; None: none); complete: :math:`(P,)` bool,
            the rays whose candidates surely hold their first rectangle when they hold any (None: no ray's do).
            Rays without a hit among their candidates and not complete are cast against every rectangle.
    """
    wp, kernel = _kernel()
    dev = origins.device
    P = len(origins)
    out = torch.full((P,), -1, dtype=torch.int64, device=dev)
    if P == 0 or len(frames[0]) == 0:
        return out
    if candidates is None:
        candidates = torch.full((P, 1), -1, dtype=torch.int64, device=dev)
    cm = (torch.zeros(P, dtype=torch.int32, device=dev) if complete is None
          else complete.to(device=dev, dtype=torch.int32))
    v3 = wp.vec3
    f = [x.detach().to(torch.float32) for x in frames]
    args = [wrap(wp, f[0], v3), wrap(wp, f[1], v3), wrap(wp, f[2], v3), wrap(wp, f[3]), wrap(wp, f[4]),
            wrap(wp, f[5], v3), wrap(wp, candidates.to(device=dev, dtype=torch.int64)), wrap(wp, cm),
            wrap(wp, origins.detach().to(torch.float32), v3), wrap(wp, dirs.detach().to(torch.float32), v3), P]
    chunks = n_chunks(origins)
    launch_chunks(wp, kernel, -(-P // chunks), device_name(origins), chunks,
                  lambda h: args + [h, chunks, wrap(wp, out)], stream=stream(origins))
    return out
