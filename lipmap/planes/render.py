"""Fast differentiable plane renderer (depth, normal, alpha) for CPU and CUDA: a fused Warp kernel, or plain torch.

The paper's renderer (appendix A) intersects every pixel ray with every plane, keeps the M nearest
intersections whose splat weight exceeds 1e-4 and composites them front to back. Done literally in
torch that is O(pixels x planes) (320x240 x 2000 planes: 5.5 s, 23 GB per iteration). Both backends
here bin the planes into screen tiles first and only test a pixel against its tile's planes:

- ``backend="warp"`` (:mod:`lipmap.planes.raster_warp`, the ``fast`` extra): per-plane setup, tile
  binning by a sort on (tile, depth) keys, one fused program per pixel that keeps its M nearest hits
  and composites them, and one reverse program that accumulates the per-plane gradients. One kernel
  source for CPU and CUDA, float32 only.
- ``backend="torch"``: :func:`~lipmap.planes.select.select_hits` (no gradient) groups the tiles by candidate
  count, evaluates every pixel of a group against its tile's candidates in one batch and picks its hits;
  :func:`composite_hits` (this module) composites the selected pairs with a hand-derived backward
  (:class:`_Composite`, the reference the Warp kernel's reverse pass follows).
- ``"auto"`` (the default; ``LIPMAP_RENDER_BACKEND`` overrides it): Warp where it is installed and the
  tensors are float32 on CPU or CUDA, torch otherwise.

The torch backend is the one reference of the renderer: the Warp kernels transcribe it, and the tests hold them to
it. Each step has one definition: the plane-to-camera setup and the (pixel, plane) pair in :mod:`lipmap.planes.pairs`
(:func:`_planes_in_camera`, :func:`_pair_terms`; Warp's ``_setup_fwd``, ``_pair_geo``), the selection of the hits
in :mod:`lipmap.planes.select` (the nearest first, depth ties by plane index, or the reference rasterizer's rule),
and the compositing and its backward here (:class:`_Composite`; Warp's ``_raster_fwd`` / ``_raster_bwd``), so both
backends select the same hits. The tests check this reference in turn against a brute-force all-pairs render
differentiated by autograd.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
# the pair definitions and the selection have modules of their own; their public names are also this module's
from .pairs import (_AX, _AY, _N, BIN_SLACK, TILE_SIZE, _check_inputs, _dot3, _gather, _pair_terms,  # noqa: F401
                    _pixel_axes, _plane_table, _planes_in_camera, check_near)
from .primitives import MAX_HITS, NEAR, SPLAT_MARGIN, Planes
from .select import HIT_RULES, _select, check_hit_rule, select_hits  # noqa: F401

BACKENDS = ("auto", "torch", "warp")
# the backend rasterize_planes uses when none is named (e.g. LIPMAP_RENDER_BACKEND=torch to compare maps)
DEFAULT_BACKEND = os.environ.get("LIPMAP_RENDER_BACKEND", "auto")



def lambda_schedule(iteration: int, max_iters: int, lam_min: float = 0.0, lam_max: float = 1500.0) -> float:
    """Sharpness of the splat fall-off: ``5 * min(20 * exp(iter / (max_iters // 10) - 1), 300)``.

    Starts at 5 * 20 / e = 36.8 (weight 1e-4 reached ~27 cm outside a rectangle) and saturates at
    1500 (6.6 mm) from 37 % of the iterations on (reference-code schedule, see docs/design.md).
    ``lam_min`` / ``lam_max`` clip it (defaults: the reference schedule unchanged).
    """
    period = max(max_iters // 10, 1)
    lam = 5.0 * min(20.0 * math.exp(min(iteration / period - 1.0, 50.0)), 300.0)
    return float(min(max(lam, lam_min), lam_max))


@dataclass
class RenderOutput:
    """Rendered maps of one view; ``hits`` is the selection the gradients flow through.

    Attributes:
        depth: :math:`(H, W)` z-depth sum_j T_j w_j t_j (not normalised by alpha; 0 where empty).
        normal: :math:`(H, W, 3)` camera-frame normals sum_j T_j w_j n_j (facing the camera).
        alpha: :math:`(H, W)` accumulated weight sum_j T_j w_j in [0, 1].
        hits: :math:`(H, W, M)` int64 indices of the composited planes in compositing order, -1 padded (no
            gradient). Under the ``"nearest"`` hit rule nearest first (depth ties: lower index first), and
            ``hits[..., 0]`` is the first plane each pixel's ray meets; under ``"reference"`` a nearer plane can be
            missing from the list (:func:`select_hits`).
        hit_rule: the rule that selected ``hits``.
    """

    depth: torch.Tensor
    normal: torch.Tensor
    alpha: torch.Tensor
    hits: torch.Tensor
    visible: Optional[torch.Tensor] = None  # (K,) bool, when the renderer marked the planes it composited
    hit_rule: str = "nearest"

    @property
    def n_pairs(self) -> int:
        return int((self.hits >= 0).sum())

    def visible_planes(self, n_planes: int) -> torch.Tensor:
        """:math:`(K,)` bool: planes that contribute to at least one pixel."""
        if self.visible is not None and len(self.visible) == n_planes:
            return self.visible
        # scatter into a spare slot K for the -1 padding: no boolean indexing, no host sync
        seen = torch.zeros(n_planes + 1, dtype=torch.bool, device=self.hits.device)
        h = self.hits.reshape(-1)
        seen[torch.where(h >= 0, h, n_planes)] = True
        return seen[:n_planes]


# ------------------------------------------------------------------------------------------------
# 2. compositing (differentiable, hand-derived backward)
# ------------------------------------------------------------------------------------------------
def _flat_pairs(hits: torch.Tensor):
    """The selected pairs of a prefix (P, m) hit tensor: flat slot f = pixel * m + slot (N,), pixel (N,), plane (N,)."""
    m = hits.shape[1]
    f = (hits.reshape(-1) >= 0).nonzero().squeeze(1)
    return f, torch.div(f, m, rounding_mode="floor"), hits.reshape(-1).index_select(0, f)


def _exclusive_transmittance(wd: torch.Tensor) -> torch.Tensor:
    """(P, m) T_j = prod_{i<j} (1 - w_ij) along each row."""
    return torch.cumprod(torch.cat([torch.ones_like(wd[:, :1]), 1 - wd[:, :-1]], 1), 1)


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of the selected pairs, with the backward written out.

    Inputs: camera-frame planes c, X, Y, n (K, 3 each), radii r (K, 4), the (P, m) prefix hits and
    the pixel rays u (W,), v (H,). Outputs depth (P,), normal (P, 3), alpha (P,). Per pixel with
    hits j = 0..m-1: tw_j = T_j w_j, T_j = prod_{i<j} (1 - w_i); depth = sum tw_j t_j, alpha =
    sum tw_j, normal = sum tw_j n_j. With G_j = dL/dtw_j = v_depth t_j + v_alpha + v_normal . n_j
    and Q_j = sum_{l>j} G_l w_l prod_{j<i<l} (1 - w_i), computed back to front (Q_{j-1} = G_j w_j +
    (1 - w_j) Q_j; dividing suffix sums of G tw by T would lose float32 precision where w is near 1),
    dL/dw_j = T_j (G_j - Q_j). The Warp kernel's reverse pass is this, per pixel.
    """

    @staticmethod
    def forward(ctx, c, ax, ay, n, r, hits, u, v, width: int, lam: float, tab=None, t_w=None):
        P, m = hits.shape
        tab = _plane_table(c, ax, ay, n, r) if tab is None else tab
        if t_w is None:  # the depth and weight of each selected pair, as the selection computes them
            f, pix, k = _flat_pairs(hits)
            up, vp = u.index_select(0, pix % width), v.index_select(0, torch.div(pix, width, rounding_mode="floor"))
            t, w = _pair_terms(_gather(tab, k), up, vp, lam)
            t_w = [torch.zeros(P * m, dtype=c.dtype, device=c.device).index_copy_(0, f, x).reshape(P, m)
                   for x in (t, w)]
        t, w = t_w
        tw = _exclusive_transmittance(w) * w  # (P, m), 0 where there is no hit
        depth = (tw * t).sum(1)
        alpha = tw.sum(1)
        nk = _gather(tab[_N], torch.where(hits >= 0, hits, tab.shape[1] - 1))  # (3, P, m); -1: the dummy column
        normal = (tw * nk).sum(2).T
        ctx.save_for_backward(tab, hits, u, v)
        ctx.width, ctx.lam = width, lam
        return depth, normal, alpha

    @staticmethod
    def backward(ctx, v_depth, v_normal, v_alpha):
        tab, hits, u, v = ctx.saved_tensors
        width, lam = ctx.width, ctx.lam
        K, P, m = tab.shape[1] - 1, hits.shape[0], hits.shape[1]
        f, pix, k = _flat_pairs(hits)
        g = _gather(tab, k)
        up, vp = u.index_select(0, pix % width), v.index_select(0, torch.div(pix, width, rounding_mode="floor"))
        t, w, a = _pair_terms(g, up, vp, lam, full=True)
        wd = torch.zeros(P * m, dtype=w.dtype, device=w.device).index_copy_(0, f, w).reshape(P, m)
        Td = _exclusive_transmittance(wd)
        T = Td.reshape(-1).index_select(0, f)
        tw = T * w
        nk = g[_N].T

        def upstream(v, *shape):  # the pairs' upstream gradients (zero for an output nothing depends on)
            return torch.zeros(len(f), *shape, dtype=t.dtype, device=t.device) if v is None else v.index_select(0, pix)

        vd, vn, va = upstream(v_depth), upstream(v_normal, 3), upstream(v_alpha)
        G = vd * t + va + (vn * nk).sum(-1)
        Gd = torch.zeros(P * m, dtype=w.dtype, device=w.device).index_copy_(0, f, G).reshape(P, m)
        # back to front, on (m, P) rows so that each step is contiguous
        wt, Gt, Tt = wd.T.contiguous(), Gd.T.contiguous(), Td.T.contiguous()
        dwt = torch.empty_like(wt)
        Q = torch.zeros(P, dtype=w.dtype, device=w.device)
        for j in range(m - 1, -1, -1):
            dwt[j] = Tt[j] * (Gt[j] - Q)
            Q = Gt[j] * wt[j] + (1 - wt[j]) * Q
        dw = dwt.T.reshape(-1).index_select(0, f)
        # w = 1 where z >= 0, else 2 sigmoid(z); z = min(zx, zy), a tie splits the gradient (as torch.minimum)
        dz = torch.where(a["z"] >= 0, 0.0, dw * 2 * a["s"] * (1 - a["s"]))
        zx, zy = a["zx"], a["zy"]
        dzx = dz * torch.where(zx < zy, 1.0, torch.where(zx == zy, 0.5, 0.0))
        dzy = dz * torch.where(zy < zx, 1.0, torch.where(zx == zy, 0.5, 0.0))
        dpx, dpy = -lam * torch.sign(a["px"]) * dzx, -lam * torch.sign(a["py"]) * dzy
        qx, qy, qz = a["q"]
        q = torch.stack([qx, qy, qz], -1)
        dq = dpx[:, None] * g[_AX].T + dpy[:, None] * g[_AY].T
        d_ray = torch.stack([up, vp, torch.ones_like(up)], -1)
        dt = tw * vd + (dq * d_ray).sum(-1)
        dt_den = (dt / a["den"])[:, None]
        # dt/dc = n / den and dt/dn = (c - t d) / den = -q / den, for t = (n . c) / (n . d)
        grads = [torch.zeros(K, 3, dtype=t.dtype, device=t.device).index_add_(0, k, value)
                 for value in (nk * dt_den - dq, dpx[:, None] * q, dpy[:, None] * q, tw[:, None] * vn - q * dt_den)]
        # the radius on the side of the hit: x+ where px > 0, x- otherwise (same along Y)
        ridx = torch.cat([4 * k + (a["px"] <= 0).long(), 4 * k + 2 + (a["py"] <= 0).long()])
        d_r = torch.zeros(4 * K, dtype=t.dtype, device=t.device).index_add_(0, ridx, lam * torch.cat([dzx, dzy]))
        return grads[0], grads[1], grads[2], grads[3], d_r.reshape(K, 4), None, None, None, None, None, None, None


def composite_hits(
    hits: torch.Tensor,  # (P, M) int64
    center: torch.Tensor,  # (K, 3)
    quat: torch.Tensor,  # (K, 4)
    radii: torch.Tensor,  # (K, 4)
    cam_from_world: torch.Tensor,  # (4, 4)
    intrinsics: tuple,
    width: int,
    height: int,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable depth (H,W), normal (H,W,3), alpha (H,W) of the selected (pixel, plane) pairs (torch backend).

    ``hits`` as :func:`select_hits` returns them (rows are prefixes: valid entries first). Also
    returns the hits, unchanged.
    """
    intrinsics = tuple(float(v) for v in intrinsics)
    cam = _planes_in_camera(center, quat, radii, cam_from_world.to(device=center.device, dtype=center.dtype))
    return _composite(cam, hits, intrinsics, width, height, lam)


def _composite(cam, hits, intrinsics, width, height, lam, tab=None, t_w=None):
    c = cam[0]
    m = max(int((hits[:, 0] >= 0).sum(0)) and int((hits >= 0).sum(1).max()), 1)  # columns in use (>= 1)
    u, v = _pixel_axes(width, height, intrinsics, c.dtype, c.device)
    t_w = None if t_w is None else [x[:, :m].contiguous() for x in t_w]
    depth, normal, alpha = _Composite.apply(*cam, hits[:, :m].contiguous(), u, v, width, lam, tab, t_w)
    return depth.reshape(height, width), normal.reshape(height, width, 3), alpha.reshape(height, width), hits


# ------------------------------------------------------------------------------------------------
# the public entry points
# ------------------------------------------------------------------------------------------------
def resolve_backend(backend: str | None, device: torch.device, dtype: torch.dtype, max_hits: int) -> str:
    """The backend that renders: ``"torch"`` or ``"warp"``; ``None`` means :data:`DEFAULT_BACKEND`."""
    backend = DEFAULT_BACKEND if backend is None else backend
    if backend not in BACKENDS:
        raise InputError(f"unknown renderer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "torch":
        return "torch"
    from . import raster_warp

    why = raster_warp.unsupported(device, dtype, max_hits)
    if why is None:
        return "warp"
    if backend == "warp":
        raise InputError(f"the Warp renderer cannot run here: {why}", hint=raster_warp.INSTALL_HINT)
    return "torch"


def rasterize_planes(
    center: torch.Tensor,  # (K, 3)
    quat: torch.Tensor,  # (K, 4) wxyz
    radii: torch.Tensor,  # (K, 4) x+, x-, y+, y-
    cam_from_world: torch.Tensor,  # (4, 4)
    intrinsics: tuple,  # (fx, fy, cx, cy)
    width: int,
    height: int,
    lam: float,
    max_hits: int = MAX_HITS,
    tile_size: int = TILE_SIZE,
    backend: str | None = None,
    near: float = NEAR,
    hit_rule: str = "nearest",
) -> RenderOutput:
    """Render planes into one pinhole camera; differentiable w.r.t. center, quat and radii.

    Args:
        center, quat, radii: plane parameters (see :class:`~lipmap.planes.primitives.Planes`).
        cam_from_world: :math:`(4, 4)` pose (x_cam = R x_world + t).
        intrinsics: (fx, fy, cx, cy), COLMAP convention (pixel (i, j) centred at (i+.5, j+.5)).
        width, height: image size in pixels.
        lam: splat sharpness, see :func:`lambda_schedule`.
        max_hits: M, intersections composited per pixel (the Warp kernel takes up to 32).
        tile_size: tile edge in pixels for the binning (speed only; results do not depend on it).
        backend: ``"auto"``, ``"torch"`` or ``"warp"`` (see the module docstring); None: :data:`DEFAULT_BACKEND`.
        near: the near plane's z-depth in metres, > 0: intersections nearer the camera are not rendered (default
            :data:`~lipmap.planes.primitives.NEAR`, 1 cm; the reference code's is 0.1 m).
        hit_rule: ``"nearest"`` or ``"reference"`` (the reference rasterizer's; see :func:`select_hits`).

    Returns:
        :class:`RenderOutput` (depth, normal, alpha, hits).
    """
    if not isinstance(cam_from_world, torch.Tensor):
        cam_from_world = torch.as_tensor(np.asarray(cam_from_world), dtype=center.dtype, device=center.device)
    cam_from_world = cam_from_world.to(device=center.device, dtype=center.dtype)
    _check_inputs(center, quat, radii, cam_from_world, width, height)
    if max_hits < 1:
        raise InputError(f"max_hits must be at least 1, got {max_hits}")
    check_near(near)
    check_hit_rule(hit_rule)
    intrinsics = tuple(float(v) for v in intrinsics)
    which = resolve_backend(backend, center.device, center.dtype, max_hits) if len(center) else "torch"
    if which == "warp" and cam_from_world.requires_grad:
        if backend == "warp":
            raise InputError("the Warp renderer gives no gradient w.r.t. the pose; pass backend='torch'")
        which = "torch"
    if which == "warp":
        from . import raster_warp

        u, v = _pixel_axes(width, height, intrinsics, center.dtype, center.device)
        depth, normal, alpha, hits, seen = raster_warp.rasterize(
            center, quat, radii, cam_from_world, u, v, intrinsics, width, height, lam, max_hits, tile_size,
            BIN_SLACK * SPLAT_MARGIN / lam, near, hit_rule)
        return RenderOutput(depth, normal, alpha, hits.reshape(height, width, max_hits), seen, hit_rule)
    cam = _planes_in_camera(center, quat, radii, cam_from_world)
    tab = _plane_table(*cam)
    P = width * height
    t_w = [torch.zeros(P, max_hits, dtype=center.dtype, device=center.device) for _ in range(2)]
    hits = _select(cam, tab, intrinsics, width, height, lam, max_hits, tile_size, t_w, near, hit_rule)
    depth, normal, alpha, hits = _composite(cam, hits, intrinsics, width, height, lam, tab, t_w)
    return RenderOutput(depth, normal, alpha, hits.reshape(height, width, max_hits), hit_rule=hit_rule)


def render_planes(
    planes: Planes,
    camera,
    cam_from_world,
    lam: float,
    downscale: float = 1.0,
    max_hits: int = MAX_HITS,
    tile_size: int = TILE_SIZE,
    backend: str | None = None,
    near: float = NEAR,
    hit_rule: str = "nearest",
) -> RenderOutput:
    """Render ``planes`` (:class:`Planes`) from a :class:`~lipmap.scene.Camera` at ``1 / downscale`` resolution."""
    cam = camera if downscale == 1 else camera.scaled(1.0 / downscale)
    return rasterize_planes(
        planes.center, planes.quat, planes.radii, cam_from_world, cam.params, cam.width, cam.height, lam, max_hits,
        tile_size, backend, near, hit_rule,
    )


def render_view(planes: Planes, view, lam: float, downscale: float = 1.0, **kw) -> RenderOutput:
    """Render ``planes`` into a :class:`~lipmap.scene.View` (its camera and ``cam_from_world``)."""
    if view.cam_from_world is None:
        raise InputError(f"view {view.name} has no pose")
    return render_planes(planes, view.camera, view.cam_from_world, lam, downscale, **kw)
