"""The fused plane rasterizer: NVIDIA Warp kernels that run the same source on CPU and CUDA.

The shape of gsplat's rasterizer and of the reference's ``renderCUDA``:

1. per plane (``_bin_planes``): the rectangle dilated to its weight-1e-4 footprint, clipped to the
   near plane and projected; its screen box as a tile range, and its nearest depth;
2. tile binning: one (tile, depth) key per covered tile (``_emit_pairs``), sorted (``torch.sort``),
   so each tile holds its planes nearest first;
3. one program per pixel (``_raster_fwd``) walks its tile's planes, keeps the M nearest hits sorted
   by (depth, plane index) in registers, stops once no later plane can reach the pixel (its nearest
   depth lies behind the M-th hit or behind the point where the transmittance fell below 1e-4),
   and composites them front to back; under the reference's hit rule (``hit_rule="reference"``) the
   tile's planes are sorted by their centres' depth instead, and the program takes each hit that lies no
   nearer than the last one it took, as ``renderCUDA`` does;
4. one reverse program per pixel (``_raster_bwd``) accumulates the per-plane gradients.

Step 1 starts from the world-frame parameters: ``_setup_fwd`` moves each plane into the camera and ``_setup_bwd``
carries the reverse pass's gradients back to centre, quaternion and radii, so a step dispatches a few dozen torch
operations, not hundreds. The setup and every pair transcribe :mod:`lipmap.planes.pairs` (``_planes_in_camera``,
``_pair_terms``) operation by operation: the torch backend is this module's reference twin, and the tests hold both
to the same hits. Float32 only. Warp is imported on first use (:mod:`lipmap.planes.warp_runtime`, which also
launches the kernels): ``import lipmap`` works without it, and ``backend="auto"`` falls back to torch. Kernels
compile on first launch per device (a few seconds; cached on disk afterwards).
"""

import functools
import math

import torch

from . import warp_runtime
from .primitives import NEAR, R_MAX, R_MIN, SPLAT_MARGIN, TRANSMITTANCE_EPS, WEIGHT_EPS
from .warp_runtime import device_name as _device, launch_chunks as _launch_chunks, n_chunks as _n_chunks
from .warp_runtime import stream as _stream, view as _view

MAX_HITS_CAP = 32  # the per-pixel hit list lives in registers: M <= 32 (the reference composites up to 30)
INSTALL_HINT = "pip install warp-lang==1.19.0 (a dependency of lipmap), or pass backend='torch'"
# a plane's binned nearest depth, quantized into the sort key: 2^-16 m steps up to 32 km
_DEPTH_STEPS = 65536.0
# relative slack on the early exit: a pair's depth and its plane's nearest vertex depth round differently
_EXIT_SLACK = 1e-4


def unsupported(device: torch.device, dtype: torch.dtype, max_hits: int) -> str | None:
    """Why the Warp kernels cannot render these tensors (None: they can)."""
    if dtype != torch.float32:
        return f"it renders float32, not {dtype}"
    if max_hits > MAX_HITS_CAP:
        return f"it keeps at most {MAX_HITS_CAP} hits per pixel, not {max_hits}"
    device = torch.device(device)
    if device.type not in ("cpu", "cuda"):
        return f"it runs on CPU and CUDA, not {device.type}"
    kn = _kernels()
    if kn is None:
        return "the warp-lang package is not installed"
    if device.type == "cuda" and not kn["wp"].is_cuda_available():
        return "Warp finds no CUDA driver"
    return None


@functools.lru_cache(maxsize=None)
def _kernels():
    """The compiled-on-demand kernels, or None without warp-lang."""
    wp = warp_runtime.load()
    return None if wp is None else _define(wp)


def _define(wp):
    """Define the kernels (one Warp module); they compile on first launch per device."""
    vecM = wp.types.vector(length=MAX_HITS_CAP, dtype=wp.float32)
    vecMi = wp.types.vector(length=MAX_HITS_CAP, dtype=wp.int32)
    weps, teps = wp.constant(WEIGHT_EPS), wp.constant(TRANSMITTANCE_EPS)
    steps, slack = wp.constant(_DEPTH_STEPS), wp.constant(_EXIT_SLACK)
    inf = wp.constant(math.inf)
    # below this the splat weight is certainly under WEIGHT_EPS: such pairs skip the exponential
    z_reject = wp.constant(-1.01 * SPLAT_MARGIN)

    @wp.func
    def _pair_geo(c: wp.vec3, ax: wp.vec3, ay: wp.vec3, n: wp.vec3, r: wp.vec4, nc: float, u: float, v: float,
                  lam: float):
        # pairs._pair_terms, operation by operation (same order: same rounding, same hits), up to the weight
        den = n[0] * u + n[1] * v + n[2]
        t = nc / den
        qx = t * u - c[0]
        qy = t * v - c[1]
        qz = t - c[2]
        px = qx * ax[0] + qy * ax[1] + qz * ax[2]
        py = qx * ay[0] + qy * ay[1] + qz * ay[2]
        rx = r[1]
        if px > 0.0:
            rx = r[0]
        ry = r[3]
        if py > 0.0:
            ry = r[2]
        zx = lam * (rx - wp.abs(px))
        zy = lam * (ry - wp.abs(py))
        z = zy
        if zx < zy:
            z = zx
        return t, den, wp.vec3(qx, qy, qz), px, py, zx, zy, z

    @wp.func
    def _sigmoid(z: float):
        return 1.0 / (1.0 + wp.exp(-z))

    @wp.func
    def _weight(z: float, s: float):
        w = 2.0 * s
        if z >= 0.0:
            w = 1.0
        return w

    @wp.func
    def _tile_touches(tx: int, ty: int, tile: int, width: int, height: int, u_tab: wp.array(dtype=float),
                      v_tab: wp.array(dtype=float), c: wp.vec3, ax: wp.vec3, ay: wp.vec3, n: wp.vec3, r: wp.vec4,
                      nc: float, mg: float, near: float):
        # False when the rays of the tile's 4 corner pixels all meet the plane in front of the near plane and all
        # lie beyond one edge of its dilated rectangle: the hits of the tile's pixels are convex combinations of
        # the corners' (1 / depth is affine in the pixel), so none of them can reach the rectangle
        x0 = tx * tile
        y0 = ty * tile
        x1 = wp.min(x0 + tile - 1, width - 1)
        y1 = wp.min(y0 + tile - 1, height - 1)
        out_xp, out_xm, out_yp, out_ym = int(1), int(1), int(1), int(1)
        for i in range(4):
            col = x0
            if i == 1 or i == 2:
                col = x1
            row = y0
            if i >= 2:
                row = y1
            t, den, q, px, py, zx, zy, z = _pair_geo(c, ax, ay, n, r, nc, u_tab[col], v_tab[row], 1.0)
            if not (t > near and t < inf):
                return True
            if not (px > r[0] + mg):
                out_xp = 0
            if not (px < -(r[1] + mg)):
                out_xm = 0
            if not (py > r[2] + mg):
                out_yp = 0
            if not (py < -(r[3] + mg)):
                out_ym = 0
        return out_xp + out_xm + out_yp + out_ym == 0

    @wp.func
    def _rotation(q: wp.vec4):
        # primitives.quat_to_rotmat, operation by operation: the unit quaternion (w, x, y, z) and its matrix M
        qn = wp.float32(wp.sqrt(wp.float64(wp.max(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3], 1.0e-24))))
        w, x, y, z = q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn
        M = wp.mat33(
            1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
        return qn, wp.vec4(w, x, y, z), M

    @wp.func
    def _row_dot(T: wp.array(dtype=float), i: int, a: float, b: float, d: float):
        return T[4 * i] * a + T[4 * i + 1] * b + T[4 * i + 2] * d

    @wp.func
    def _to_camera(T: wp.array(dtype=float), center: wp.vec3, M: wp.mat33):
        # pairs._planes_in_camera, operation by operation: c = R centre + t and the columns of R M
        c = wp.vec3(_row_dot(T, 0, center[0], center[1], center[2]) + T[3],
                    _row_dot(T, 1, center[0], center[1], center[2]) + T[7],
                    _row_dot(T, 2, center[0], center[1], center[2]) + T[11])
        ax = wp.vec3(_row_dot(T, 0, M[0, 0], M[1, 0], M[2, 0]), _row_dot(T, 1, M[0, 0], M[1, 0], M[2, 0]),
                     _row_dot(T, 2, M[0, 0], M[1, 0], M[2, 0]))
        ay = wp.vec3(_row_dot(T, 0, M[0, 1], M[1, 1], M[2, 1]), _row_dot(T, 1, M[0, 1], M[1, 1], M[2, 1]),
                     _row_dot(T, 2, M[0, 1], M[1, 1], M[2, 1]))
        n = wp.vec3(_row_dot(T, 0, M[0, 2], M[1, 2], M[2, 2]), _row_dot(T, 1, M[0, 2], M[1, 2], M[2, 2]),
                    _row_dot(T, 2, M[0, 2], M[1, 2], M[2, 2]))
        return c, ax, ay, n

    @wp.func
    def _dot3(a: wp.vec3, b: wp.vec3):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    @wp.kernel(enable_backward=False)
    def _setup_fwd(
        center: wp.array(dtype=wp.vec3), quat: wp.array(dtype=wp.vec4), radii: wp.array(dtype=wp.vec4),
        T: wp.array(dtype=float), r_min: float, r_max: float,
        c: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), ay: wp.array(dtype=wp.vec3),
        n: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec4), nc: wp.array(dtype=float),
    ):
        k = wp.tid()
        qn, qh, M = _rotation(quat[k])
        ck, xk, yk, nk = _to_camera(T, center[k], M)
        d = _dot3(nk, ck)
        if d > 0.0:  # the normal faces the camera
            nk = -nk
            d = -d
        rk = radii[k]
        for i in range(4):
            if wp.isfinite(rk[i]):  # torch's clamp keeps a NaN, and a NaN radius hides the plane
                rk[i] = wp.clamp(rk[i], r_min, r_max)
        c[k] = ck
        ax[k] = xk
        ay[k] = yk
        n[k] = nk
        r[k] = rk
        nc[k] = d

    @wp.kernel(enable_backward=False)
    def _setup_bwd(
        center: wp.array(dtype=wp.vec3), quat: wp.array(dtype=wp.vec4), radii: wp.array(dtype=wp.vec4),
        T: wp.array(dtype=float), r_min: float, r_max: float, n_chunks: int,
        g_c: wp.array2d(dtype=wp.vec3), g_ax: wp.array2d(dtype=wp.vec3), g_ay: wp.array2d(dtype=wp.vec3),
        g_n: wp.array2d(dtype=wp.vec3), g_r: wp.array2d(dtype=wp.vec4),
        g_center: wp.array(dtype=wp.vec3), g_quat: wp.array(dtype=wp.vec4), g_radii: wp.array(dtype=wp.vec4),
    ):
        # the reverse of _setup_fwd (autograd of pairs._planes_in_camera); the raster reverse pass's per-chunk
        # gradient buffers are summed here, chunk 0 first
        k = wp.tid()
        gc, gx, gy, gn = wp.vec3(), wp.vec3(), wp.vec3(), wp.vec3()
        gr = wp.vec4()
        for h in range(n_chunks):
            gc += g_c[h, k]
            gx += g_ax[h, k]
            gy += g_ay[h, k]
            gn += g_n[h, k]
            gr += g_r[h, k]
        qn, qh, M = _rotation(quat[k])
        ck, xk, yk, nk = _to_camera(T, center[k], M)
        if _dot3(nk, ck) > 0.0:
            gn = -gn
        R = wp.mat33(T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10])
        Rt = wp.transpose(R)
        g_center[k] = Rt * gc
        # dL/dM = R^T [gX gY gn]: columns of R M are the axes
        G = Rt * wp.matrix_from_cols(gx, gy, gn)
        w, x, y, z = qh[0], qh[1], qh[2], qh[3]
        gw = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
        gqx = 2.0 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2.0 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                     + w * G[2, 1] - 2.0 * x * G[2, 2])
        gqy = 2.0 * (-2.0 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                     + z * G[2, 1] - 2.0 * y * G[2, 2])
        gqz = 2.0 * (-2.0 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2.0 * z * G[1, 1]
                     + y * G[1, 2] + x * G[2, 0] + y * G[2, 1])
        gh = wp.vec4(gw, gqx, gqy, gqz)
        q = quat[k]
        if q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] >= 1.0e-24:
            gh = gh - qh * wp.dot(qh, gh)  # through the normalization; below the clamp the norm is a constant
        g_quat[k] = gh / qn
        rk = radii[k]
        for i in range(4):
            if not (rk[i] >= r_min and rk[i] <= r_max):  # torch's clamp passes the gradient inside [min, max]
                gr[i] = 0.0
        g_radii[k] = gr

    @wp.kernel(enable_backward=False)
    def _recenter(center: wp.array(dtype=wp.vec3), quat: wp.array(dtype=wp.vec4), radii: wp.array(dtype=wp.vec4),
                  r_min: float, r_max: float):
        # Planes.recentered and the quaternion's normalisation, in place: the centre moves to the middle of the
        # clamped rectangle, x+ = x- and y+ = y-
        k = wp.tid()
        qn, qh, M = _rotation(quat[k])
        rk = radii[k]
        for i in range(4):
            if wp.isfinite(rk[i]):
                rk[i] = wp.clamp(rk[i], r_min, r_max)
        center[k] = center[k] + (0.5 * (rk[0] - rk[1])) * wp.vec3(M[0, 0], M[1, 0], M[2, 0]) + (
            0.5 * (rk[2] - rk[3])) * wp.vec3(M[0, 1], M[1, 1], M[2, 1])
        rx = 0.5 * (rk[0] + rk[1])
        ry = 0.5 * (rk[2] + rk[3])
        radii[k] = wp.vec4(rx, rx, ry, ry)
        quat[k] = qh

    @wp.kernel(enable_backward=False)
    def _bin_planes(
        c: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), ay: wp.array(dtype=wp.vec3),
        n: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec4), nc: wp.array(dtype=float),
        dilate: float, fx: float, fy: float, cx: float, cy: float, width: int, height: int, tile: int,
        u_tab: wp.array(dtype=float), v_tab: wp.array(dtype=float), near: float,
        rect: wp.array(dtype=wp.vec4i), count: wp.array(dtype=wp.int32), zmin: wp.array(dtype=float),
    ):
        k = wp.tid()
        count[k] = 0
        zmin[k] = inf
        ck, xk, yk, nk, rk = c[k], ax[k], ay[k], n[k], r[k]
        if not (wp.isfinite(ck) and wp.isfinite(xk) and wp.isfinite(yk) and wp.isfinite(nk) and wp.isfinite(rk)):
            return
        if not (wp.abs(nc[k]) > 1.0e-9):  # a plane through the camera centre is seen edge-on
            return
        # the dilated rectangle's corners v1..v4 and, for each edge crossing z = near, the crossing point
        u0, u1, v0, v1, zm = inf, -inf, inf, -inf, inf
        any_pt = int(0)
        for i in range(4):
            j = (i + 1) % 4
            sx_i = rk[0] + dilate
            if i >= 2:
                sx_i = -(rk[1] + dilate)
            sy_i = rk[2] + dilate
            if i == 1 or i == 2:
                sy_i = -(rk[3] + dilate)
            sx_j = rk[0] + dilate
            if j >= 2:
                sx_j = -(rk[1] + dilate)
            sy_j = rk[2] + dilate
            if j == 1 or j == 2:
                sy_j = -(rk[3] + dilate)
            a = ck + sx_i * xk + sy_i * yk
            b = ck + sx_j * xk + sy_j * yk
            for e in range(2):
                p = a
                ok = a[2] >= near
                if e == 1:
                    ok = (a[2] - near) * (b[2] - near) < 0.0
                    p = a + wp.clamp((near - a[2]) / (b[2] - a[2]), 0.0, 1.0) * (b - a)
                if ok:
                    zz = wp.max(p[2], near)
                    pu = fx * p[0] / zz + cx
                    pv = fy * p[1] / zz + cy
                    u0, u1 = wp.min(u0, pu), wp.max(u1, pu)
                    v0, v1 = wp.min(v0, pv), wp.max(v1, pv)
                    zm = wp.min(zm, zz)
                    any_pt = 1
        if any_pt == 0 or u1 < 0.0 or u0 > float(width) or v1 < 0.0 or v0 > float(height):
            return
        wf, hf = float(width) - 1.0e-3, float(height) - 1.0e-3
        tx0 = int(wp.clamp(u0, 0.0, wf) / float(tile))
        tx1 = int(wp.clamp(u1, 0.0, wf) / float(tile))
        ty0 = int(wp.clamp(v0, 0.0, hf) / float(tile))
        ty1 = int(wp.clamp(v1, 0.0, hf) / float(tile))
        rect[k] = wp.vec4i(tx0, ty0, tx1, ty1)
        zmin[k] = zm
        cnt = int(0)
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                if _tile_touches(tx, ty, tile, width, height, u_tab, v_tab, ck, xk, yk, nk, rk, nc[k], dilate, near):
                    cnt += 1
        count[k] = cnt

    @wp.kernel(enable_backward=False)
    def _emit_pairs(
        c: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), ay: wp.array(dtype=wp.vec3),
        n: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec4), nc: wp.array(dtype=float), dilate: float,
        width: int, height: int, tile: int, u_tab: wp.array(dtype=float), v_tab: wp.array(dtype=float), near: float,
        rect: wp.array(dtype=wp.vec4i), count: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int64),
        zmin: wp.array(dtype=float), ntx: int, keys: wp.array(dtype=wp.int64), planes: wp.array(dtype=wp.int32),
    ):
        k = wp.tid()
        if count[k] == 0:
            return
        rc = rect[k]
        # key: tile in the high bits, the quantized nearest depth in the low 32
        dq = wp.int64(wp.min(zmin[k] * steps, 4.0e9))
        o = offset[k] - wp.int64(count[k])
        for ty in range(rc[1], rc[3] + 1):
            for tx in range(rc[0], rc[2] + 1):
                if _tile_touches(tx, ty, tile, width, height, u_tab, v_tab, c[k], ax[k], ay[k], n[k], r[k], nc[k],
                                 dilate, near):
                    keys[o] = wp.int64(ty * ntx + tx) * wp.int64(4294967296) + dq
                    planes[o] = k
                    o += wp.int64(1)

    @wp.kernel(enable_backward=False)
    def _raster_fwd(
        start: wp.array(dtype=wp.int32), cand: wp.array(dtype=wp.int32), zmin: wp.array(dtype=float),
        c: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), ay: wp.array(dtype=wp.vec3),
        n: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec4), nc: wp.array(dtype=float),
        u_tab: wp.array(dtype=float), v_tab: wp.array(dtype=float), width: int, height: int, ntx: int, tile: int,
        lam: float, max_hits: int, near: float, rule: int, chunk: int, n_chunks: int,
        hits: wp.array2d(dtype=wp.int64), depth: wp.array(dtype=float), alpha: wp.array(dtype=float),
        normal: wp.array(dtype=wp.vec3), seen: wp.array(dtype=wp.int32),
    ):
        tid = wp.tid()
        tt = tile * tile
        ti = (tid // tt) * n_chunks + chunk  # tiles interleaved over the CPU threads' launches
        loc = tid - (tid // tt) * tt
        if ti >= start.shape[0] - 1:
            return
        col = (ti % ntx) * tile + loc % tile
        row = (ti // ntx) * tile + loc // tile
        if col >= width or row >= height:
            return
        p = row * width + col
        u, v = u_tab[col], v_tab[row]
        lt, lw = vecM(), vecM()
        lk = vecMi()
        m = int(0)
        cut = inf
        last, tr = float(0.0), float(1.0)
        for idx in range(start[ti], start[ti + 1]):
            k = cand[idx]
            if rule == 1:  # the reference's walk (planes by centre depth): a hit nearer than the last one is skipped
                if m >= max_hits or tr < teps:
                    break
            elif zmin[k] > cut:
                # the tile's planes are sorted by quantized nearest depth: none after this one can be nearer
                if wp.floor(zmin[k] * steps) / steps > cut:
                    break
                continue
            t, den, q, px, py, zx, zy, z = _pair_geo(c[k], ax[k], ay[k], n[k], r[k], nc[k], u, v, lam)
            if not (t > near and t < inf) or z < z_reject:
                continue
            w = float(1.0)
            if not (z >= 0.0):  # _weight without the exponential inside the rectangle (NaN stays NaN)
                w = 2.0 * _sigmoid(z)
            if not (w > weps):
                continue
            if rule == 1:
                if t >= last:
                    lt[m] = t
                    lw[m] = w
                    lk[m] = k
                    m += 1
                    last = t
                    tr = tr * (1.0 - w)
                continue
            pos = m
            while pos > 0 and (lt[pos - 1] > t or (lt[pos - 1] == t and lk[pos - 1] > k)):
                pos -= 1
            if pos >= max_hits:
                continue
            j = wp.min(m, max_hits - 1)
            while j > pos:
                lt[j] = lt[j - 1]
                lw[j] = lw[j - 1]
                lk[j] = lk[j - 1]
                j -= 1
            lt[pos] = t
            lw[pos] = w
            lk[pos] = k
            m = wp.min(m + 1, max_hits)
            # the depth beyond which no plane can change this pixel: the last hit in front of the point where
            # the transmittance falls below TRANSMITTANCE_EPS, or the M-th hit
            cut = inf
            T = float(1.0)
            for jj in range(m):
                if T < teps:
                    cut = lt[jj - 1]
                    break
                T = T * (1.0 - lw[jj])
            if cut == inf and (m == max_hits or T < teps):
                cut = lt[m - 1]
            if cut < inf:
                cut = cut * (1.0 + slack) + 1.0e-6
        T = float(1.0)
        dsum, asum = float(0.0), float(0.0)
        nsum = wp.vec3(0.0, 0.0, 0.0)
        used = int(0)
        for jj in range(m):
            if T < teps:
                break
            tw = T * lw[jj]
            dsum += tw * lt[jj]
            asum += tw
            nsum += tw * n[lk[jj]]
            T = T * (1.0 - lw[jj])
            used = jj + 1
        for jj in range(max_hits):
            if jj < used:
                hits[p, jj] = wp.int64(lk[jj])
                seen[lk[jj]] = 1  # every writer stores the same 1: the order of the stores does not matter
            else:
                hits[p, jj] = wp.int64(-1)
        depth[p] = dsum
        alpha[p] = asum
        normal[p] = nsum

    @wp.kernel(enable_backward=False)
    def _raster_bwd(
        hits: wp.array2d(dtype=wp.int64),
        c: wp.array(dtype=wp.vec3), ax: wp.array(dtype=wp.vec3), ay: wp.array(dtype=wp.vec3),
        n: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec4), nc: wp.array(dtype=float),
        u_tab: wp.array(dtype=float), v_tab: wp.array(dtype=float), width: int, lam: float, chunk: int,
        n_chunks: int, v_depth: wp.array(dtype=float), v_normal: wp.array(dtype=wp.vec3),
        v_alpha: wp.array(dtype=float), g_c: wp.array(dtype=wp.vec3), g_ax: wp.array(dtype=wp.vec3),
        g_ay: wp.array(dtype=wp.vec3), g_n: wp.array(dtype=wp.vec3), g_r: wp.array(dtype=wp.vec4),
    ):
        p = wp.tid() * n_chunks + chunk
        if p >= hits.shape[0]:
            return
        if hits[p, 0] < wp.int64(0):
            return
        col = p % width
        row = p // width
        u, v = u_tab[col], v_tab[row]
        d = wp.vec3(u, v, 1.0)
        vd, va, vn = v_depth[p], v_alpha[p], v_normal[p]
        lT, lG, lS = vecM(), vecM(), vecM()
        m = int(0)
        T = float(1.0)
        for j in range(hits.shape[1]):
            kk = hits[p, j]
            if kk < wp.int64(0):
                break
            k = int(kk)
            t, den, q, px, py, zx, zy, z = _pair_geo(c[k], ax[k], ay[k], n[k], r[k], nc[k], u, v, lam)
            s = _sigmoid(z)
            lT[j] = T
            lG[j] = vd * t + va + wp.dot(vn, n[k])
            lS[j] = s
            T = T * (1.0 - _weight(z, s))
            m = j + 1
        # back to front: Q = sum over the hits behind of G_l w_l prod (1 - w_i) between (see render._Composite)
        Q = float(0.0)
        for jj in range(m):
            j = m - 1 - jj
            k = int(hits[p, j])
            t, den, q, px, py, zx, zy, z = _pair_geo(c[k], ax[k], ay[k], n[k], r[k], nc[k], u, v, lam)
            Tj, Gj, s = lT[j], lG[j], lS[j]
            w = _weight(z, s)
            dw = Tj * (Gj - Q)
            Q = Gj * w + (1.0 - w) * Q
            tw = Tj * w
            dz = float(0.0)
            if not (z >= 0.0):
                dz = dw * 2.0 * s * (1.0 - s)
            fx_, fy_ = float(0.0), float(0.0)
            if zx < zy:
                fx_ = 1.0
            elif zy < zx:
                fy_ = 1.0
            elif zx == zy:
                fx_, fy_ = 0.5, 0.5
            dzx, dzy = dz * fx_, dz * fy_
            dpx = -lam * wp.sign(px) * dzx
            dpy = -lam * wp.sign(py) * dzy
            if px == 0.0:
                dpx = 0.0
            if py == 0.0:
                dpy = 0.0
            dq = dpx * ax[k] + dpy * ay[k]
            dt = tw * vd + wp.dot(dq, d)
            dt_den = dt / den
            wp.atomic_add(g_c, k, n[k] * dt_den - dq)
            wp.atomic_add(g_ax, k, dpx * q)
            wp.atomic_add(g_ay, k, dpy * q)
            wp.atomic_add(g_n, k, tw * vn - q * dt_den)
            # the radius on the side of the hit gets the gradient: x+ where px > 0, x- otherwise (same along Y)
            sx = float(0.0)
            if px > 0.0:
                sx = 1.0
            sy = float(0.0)
            if py > 0.0:
                sy = 1.0
            wp.atomic_add(g_r, k, lam * wp.vec4(sx * dzx, (1.0 - sx) * dzx, sy * dzy, (1.0 - sy) * dzy))

    return dict(wp=wp, setup=_setup_fwd, setup_bwd=_setup_bwd, recenter=_recenter, bin=_bin_planes, emit=_emit_pairs,
                fwd=_raster_fwd, bwd=_raster_bwd)


# the CPU reverse pass accumulates into this many gradient buffers (pixels interleaved), summed in order: a fixed
# split, so the gradients do not depend on how many threads run it
_CPU_GRAD_SPLIT = 4


def setup(center, quat, radii, T):
    """Step 1's first half: world-frame planes (K,3), (K,4), (K,4) and cam_from_world as 16 floats -> the camera-frame
    centre, X, Y, normal (K,3 each, the normal facing the camera), clamped radii (K,4) and n . c (K,), bit for bit
    :func:`lipmap.planes.pairs._planes_in_camera`'s."""
    kn = _kernels()
    wp = kn["wp"]
    center, quat, radii, T = (x.contiguous() for x in (center, quat, radii, T))
    K, dev = len(center), center.device
    c, ax, ay, n = (torch.empty(K, 3, dtype=torch.float32, device=dev) for _ in range(4))
    r = torch.empty(K, 4, dtype=torch.float32, device=dev)
    nc = torch.empty(K, dtype=torch.float32, device=dev)
    v3, v4 = wp.vec3, wp.vec4
    wp.launch(kn["setup"], dim=K, device=_device(center), stream=_stream(center), inputs=[
        _view(wp, center, v3), _view(wp, quat, v4), _view(wp, radii, v4), _view(wp, T), R_MIN, R_MAX,
        _view(wp, c, v3), _view(wp, ax, v3), _view(wp, ay, v3), _view(wp, n, v3), _view(wp, r, v4), _view(wp, nc)])
    return c, ax, ay, n, r, nc


def setup_backward(center, quat, radii, T, grads):
    """The reverse of :func:`setup`: gradients w.r.t. centre, quaternion and radii from those w.r.t. the camera-frame
    centre, X, Y, normal and radii, each given as (chunks, K, 3 or 4) partial sums (summed here, chunk 0 first)."""
    kn = _kernels()
    wp = kn["wp"]
    v3, v4 = wp.vec3, wp.vec4
    center, quat, radii, T = (x.contiguous() for x in (center, quat, radii, T))
    grads = [g.contiguous() for g in grads]
    g_center, g_quat, g_radii = (torch.empty_like(x) for x in (center, quat, radii))  # contiguous, as their inputs
    wp.launch(kn["setup_bwd"], dim=len(center), device=_device(center), stream=_stream(center), inputs=[
        _view(wp, center, v3), _view(wp, quat, v4), _view(wp, radii, v4), _view(wp, T), R_MIN, R_MAX, len(grads[0]),
        *[_view(wp, g, ty) for g, ty in zip(grads, (v3, v3, v3, v3, v4))], _view(wp, g_center, v3),
        _view(wp, g_quat, v4), _view(wp, g_radii, v4)])
    return g_center, g_quat, g_radii


def recenter_(center, quat, radii) -> bool:
    """Re-centre the planes in place as :meth:`lipmap.planes.primitives.Planes.recentered` does, and normalise the
    quaternions, in one launch. Returns False (nothing done) where a tensor is not contiguous: the kernel could only
    write a copy."""
    if not (center.is_contiguous() and quat.is_contiguous() and radii.is_contiguous()):
        return False
    kn = _kernels()
    wp = kn["wp"]
    wp.launch(kn["recenter"], dim=len(center), device=_device(center), stream=_stream(center), inputs=[
        _view(wp, center.detach(), wp.vec3), _view(wp, quat.detach(), wp.vec4), _view(wp, radii.detach(), wp.vec4), R_MIN,
        R_MAX])
    return True


class _Raster(torch.autograd.Function):
    """Fused forward (per-plane setup, binning, selection, compositing) and reverse pass.

    Inputs centre (K, 3), quaternion (K, 4), radii (K, 4) in the world frame and cam_from_world as 16 floats;
    outputs depth (P,), normal (P, 3), alpha (P,), and hits (P, M) int64 and seen (K,) int32 (1: a pixel
    composites the plane), not differentiable. The pose gets no gradient.
    """

    @staticmethod
    def forward(ctx, center, quat, radii, T, u, v, dims):
        kn = _kernels()
        wp = kn["wp"]
        width, height, tile, lam, max_hits, near, dilate, intrinsics, rule = dims
        dev, K, P = center.device, len(center), width * height
        wdev, stream = _device(center), _stream(center)
        ntx, nty = -(-width // tile), -(-height // tile)
        v3, v4 = wp.vec3, wp.vec4
        c, ax, ay, n, r, nc = setup(center, quat, radii, T)
        planes = [_view(wp, c, v3), _view(wp, ax, v3), _view(wp, ay, v3), _view(wp, n, v3), _view(wp, r, v4), _view(wp, nc)]
        fx, fy, cx, cy = intrinsics
        rect = torch.empty(K, 4, dtype=torch.int32, device=dev)
        count = torch.empty(K, dtype=torch.int32, device=dev)
        zmin = torch.empty(K, dtype=torch.float32, device=dev)
        wp.launch(kn["bin"], dim=K, device=wdev, stream=stream, inputs=planes + [
            dilate, fx, fy, cx, cy, width, height, tile, _view(wp, u), _view(wp, v), near, _view(wp, rect, wp.vec4i),
            _view(wp, count), _view(wp, zmin)])
        offset = torch.cumsum(count, 0, dtype=torch.int64)
        total = int(offset[-1])  # the step's one host sync: the size of the pair list
        keys = torch.empty(total, dtype=torch.int64, device=dev)
        pair_plane = torch.empty(total, dtype=torch.int32, device=dev)
        if total:
            wp.launch(kn["emit"], dim=K, device=wdev, stream=stream, inputs=planes + [
                dilate, width, height, tile, _view(wp, u), _view(wp, v), near, _view(wp, rect, wp.vec4i), _view(wp, count),
                _view(wp, offset), _view(wp, zmin), ntx, _view(wp, keys), _view(wp, pair_plane)])
        if rule == "reference":  # by tile, then the centres' depth, then plane index (pairs come in plane order)
            order = torch.sort(c[:, 2][pair_plane.long()], stable=True).indices
            order = order[torch.sort(keys[order] >> 32, stable=True).indices]
            keys = keys[order]
        else:
            keys, order = torch.sort(keys)
        cand = pair_plane[order]
        tiles = torch.arange(ntx * nty + 1, device=dev, dtype=torch.int64) << 32
        start = torch.searchsorted(keys, tiles).to(torch.int32)

        hits = torch.empty(P, max_hits, dtype=torch.int64, device=dev)
        depth = torch.empty(P, dtype=torch.float32, device=dev)
        alpha = torch.empty(P, dtype=torch.float32, device=dev)
        normal = torch.empty(P, 3, dtype=torch.float32, device=dev)
        seen = torch.zeros(K, dtype=torch.int32, device=dev)
        n_chunks = _n_chunks(center)
        common = [_view(wp, start), _view(wp, cand), _view(wp, zmin)] + planes + [
            _view(wp, u), _view(wp, v), width, height, ntx, tile, lam, max_hits, near, int(rule == "reference")]
        outs = [_view(wp, hits), _view(wp, depth), _view(wp, alpha), _view(wp, normal, v3), _view(wp, seen)]
        tiles_per_chunk = -(-(len(start) - 1) // n_chunks)
        _launch_chunks(wp, kn["fwd"], tiles_per_chunk * tile * tile, wdev, n_chunks,
                       lambda h: common + [h, n_chunks] + outs, stream=stream)
        ctx.save_for_backward(center, quat, radii, T, c, ax, ay, n, r, nc, u, v, hits)
        ctx.dims = dims
        ctx.mark_non_differentiable(hits, seen)
        return depth, normal, alpha, hits, seen

    @staticmethod
    def backward(ctx, v_depth, v_normal, v_alpha, _v_hits, _v_seen):
        center, quat, radii, T, c, ax, ay, n, r, nc, u, v, hits = ctx.saved_tensors
        width, height, tile, lam, max_hits = ctx.dims[:5]
        kn = _kernels()
        wp = kn["wp"]
        P, dev, wdev = width * height, c.device, _device(c)
        v_depth = torch.zeros(P, device=dev) if v_depth is None else v_depth.contiguous()
        v_alpha = torch.zeros(P, device=dev) if v_alpha is None else v_alpha.contiguous()
        v_normal = torch.zeros(P, 3, device=dev) if v_normal is None else v_normal.contiguous()
        threads = _n_chunks(c)
        n_chunks = 1 if dev.type == "cuda" else _CPU_GRAD_SPLIT
        # one set of gradient buffers per chunk: Warp's CPU atomics are plain adds, not thread-safe ones
        grads = [torch.zeros((n_chunks, *x.shape), dtype=x.dtype, device=dev) for x in (c, ax, ay, n, r)]
        v3, v4 = wp.vec3, wp.vec4
        common = [_view(wp, hits), _view(wp, c, v3), _view(wp, ax, v3), _view(wp, ay, v3), _view(wp, n, v3),
                  _view(wp, r, v4), _view(wp, nc), _view(wp, u), _view(wp, v), width, lam]
        vs = [_view(wp, v_depth), _view(wp, v_normal, v3), _view(wp, v_alpha)]
        types = (v3, v3, v3, v3, v4)
        _launch_chunks(wp, kn["bwd"], -(-P // n_chunks), wdev, n_chunks,
                       lambda h: common + [h, n_chunks] + vs + [_view(wp, g[h], ty) for g, ty in zip(grads, types)],
                       threads, stream=_stream(c))  # autograd runs this on the forward's stream
        return (*setup_backward(center, quat, radii, T, grads), None, None, None, None)


def rasterize(center, quat, radii, cam_from_world, u, v, intrinsics, width: int, height: int, lam: float,
              max_hits: int, tile_size: int, dilate: float, near: float = NEAR, hit_rule: str = "nearest"):
    """Render world-frame planes (centre (K,3), quaternion (K,4), radii (K,4)) into the camera ``cam_from_world``
    (4, 4) with the Warp kernels.

    ``u`` (W,), ``v`` (H,): the pixel rays (:func:`lipmap.planes.pairs._pixel_axes`); ``dilate``: how far beyond
    its rectangle a plane is binned (its weight-1e-4 footprint and a margin); ``near``: the near plane's z (m);
    ``hit_rule``: ``"nearest"`` or ``"reference"`` (:func:`lipmap.planes.select.select_hits`).
    Returns depth (H, W), normal (H, W, 3), alpha (H, W), hits (H W, M) int64 in compositing order (nearest first
    under "nearest", depth ties: lower index first), -1 padded, and the planes some pixel composites (K,) bool; the first three are differentiable
    w.r.t. centre, quaternion and radii.
    """
    T = cam_from_world.detach().reshape(16).contiguous()
    dims = (width, height, tile_size, float(lam), max_hits, float(near), float(dilate), tuple(intrinsics), hit_rule)
    depth, normal, alpha, hits, seen = _Raster.apply(center.contiguous(), quat.contiguous(), radii.contiguous(), T,
                                                     u, v, dims)
    return (depth.reshape(height, width), normal.reshape(height, width, 3), alpha.reshape(height, width), hits,
            seen.bool())
