"""Fast differentiable plane renderer (depth, normal, alpha) for CPU and CUDA: a fused Warp kernel, or plain torch.

The paper's renderer (appendix A) intersects every pixel ray with every plane, keeps the M nearest
intersections whose splat weight exceeds 1e-4 and composites them front to back. Done literally in
torch that is O(pixels x planes) (320x240 x 2000 planes: 5.5 s, 23 GB per iteration). Both backends
here bin the planes into screen tiles first and only test a pixel against its tile's planes:

- ``backend="warp"`` (:mod:`lipmap.planes.raster_warp`, the ``fast`` extra): per-plane setup, tile
  binning by a sort on (tile, depth) keys, one fused program per pixel that keeps its M nearest hits
  and composites them, and one reverse program that accumulates the per-plane gradients. One kernel
  source for CPU and CUDA, float32 only.
- ``backend="torch"``, this module: :func:`select_hits` (no gradient) groups the tiles by candidate
  count, evaluates every pixel of a group against its tile's candidates in one batch and sorts them;
  :func:`composite_hits` composites the selected pairs with a hand-derived backward
  (:class:`_Composite`, the reference the Warp kernel's reverse pass follows).
- ``"auto"`` (the default; ``LIPMAP_RENDER_BACKEND`` overrides it): Warp where it is installed and the
  tensors are float32 on CPU or CUDA, torch otherwise.

This module is the one torch reference of the renderer: the Warp kernels transcribe it, and the tests hold them
to it. Each step has one definition here: the plane-to-camera setup (:func:`_planes_in_camera`; Warp's
``_setup_fwd``), the (pixel, plane) pair (:func:`_pair_terms`; Warp's ``_pair_geo``), the selection of the
first hits (:func:`select_hits`: nearest first, depth ties by plane index) and the compositing and its backward
(:class:`_Composite`; Warp's ``_raster_fwd`` / ``_raster_bwd``), so both backends select the same hits. The tests
check this reference in turn against a brute-force all-pairs render differentiated by autograd.
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from .primitives import (
    MAX_HITS,
    NEAR,
    R_MAX,
    R_MIN,
    SPLAT_MARGIN,
    TRANSMITTANCE_EPS,
    WEIGHT_EPS,
    Planes,
    quat_to_rotmat,
)

TILE_SIZE = 8
BACKENDS = ("auto", "torch", "warp")
# the backend rasterize_planes uses when none is named (e.g. LIPMAP_RENDER_BACKEND=torch to compare maps)
DEFAULT_BACKEND = os.environ.get("LIPMAP_RENDER_BACKEND", "auto")
_EVAL_BUDGET_CPU = 1 << 21  # (pixel, candidate) evaluations per batched step of the torch selection
_EVAL_BUDGET_CUDA = 1 << 25
# screen boxes are dilated 1 % beyond the weight-1e-4 footprint, so that round-off in the per-pixel
# weight cannot put a selected pair outside its plane's box
BIN_SLACK = 1.01
# packed per-plane table: centre, X axis, Y axis, normal (camera frame, facing the camera), radii, n . c
_C, _AX, _AY, _N, _R, _NC = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 16), 16


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
# shared pieces (both backends)
# ------------------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------------------
# 1. selection (no gradient)
# ------------------------------------------------------------------------------------------------
def _screen_boxes(c, ax, ay, n, r, lam, intrinsics, width, height, near=NEAR):
    """Screen boxes (u0, u1, v0, v1) (K,) each of the dilated, near-clipped rectangles, their
    minimum z-depth (K,) and a visibility mask (K,)."""
    fx, fy, cx, cy = intrinsics
    rd = r + BIN_SLACK * SPLAT_MARGIN / lam
    sx = torch.stack([rd[:, 0], rd[:, 0], -rd[:, 1], -rd[:, 1]], 1)[..., None]
    sy = torch.stack([rd[:, 2], -rd[:, 3], -rd[:, 3], rd[:, 2]], 1)[..., None]
    V = c[:, None] + sx * ax[:, None] + sy * ay[:, None]  # (K, 4, 3)
    V2 = V.roll(-1, dims=1)
    z, z2 = V[..., 2], V2[..., 2]
    # the polygon clipped to z >= near: its front corners plus the edges' crossings of z = near
    cross = (z - near) * (z2 - near) < 0
    s = ((near - z) / torch.where(cross, z2 - z, torch.ones_like(z))).clamp(0, 1)
    Vc = V + s[..., None] * (V2 - V)
    pts = torch.cat([V, Vc], 1)  # (K, 8, 3)
    ok = torch.cat([z >= near, cross], 1)
    zz = torch.where(ok, pts[..., 2], torch.ones_like(pts[..., 2])).clamp(min=near)
    u = fx * pts[..., 0] / zz + cx
    v = fy * pts[..., 1] / zz + cy
    inf = torch.full_like(u, float("inf"))
    u0, u1 = torch.where(ok, u, inf).amin(1), torch.where(ok, u, -inf).amax(1)
    v0, v1 = torch.where(ok, v, inf).amin(1), torch.where(ok, v, -inf).amax(1)
    finite = torch.isfinite(c).all(1) & torch.isfinite(n).all(1) & torch.isfinite(r).all(1)
    vis = finite & ok.any(1) & (u1 >= 0) & (u0 <= width) & (v1 >= 0) & (v0 <= height)
    vis &= (n * c).sum(-1).abs() > 1e-9  # a plane through the camera centre is seen edge-on
    zmin = torch.where(ok, zz, torch.full_like(zz, float("inf"))).amin(1)
    return (u0, u1, v0, v1), zmin, vis


def _tile_pairs(boxes, vis, width, height, tile_size):
    """(tile, plane) pairs sorted by tile, planes ascending within a tile, from each visible plane's tile range."""
    u0, u1, v0, v1 = boxes
    dev = u0.device
    ntx, nty = -(-width // tile_size), -(-height // tile_size)
    pid = vis.nonzero().squeeze(1)
    # pixel i is in tile i // tile_size; the box covers pixel centres i + 0.5 in [u0, u1]
    tx0 = (u0[pid].clamp(0, width - 1e-3) / tile_size).long()
    tx1 = (u1[pid].clamp(0, width - 1e-3) / tile_size).long()
    ty0 = (v0[pid].clamp(0, height - 1e-3) / tile_size).long()
    ty1 = (v1[pid].clamp(0, height - 1e-3) / tile_size).long()
    wx = tx1 - tx0 + 1
    cnt = wx * (ty1 - ty0 + 1)
    total = int(cnt.sum())
    rep = torch.repeat_interleave(torch.arange(len(pid), device=dev), cnt, output_size=total)
    local = torch.arange(total, device=dev) - (torch.cumsum(cnt, 0) - cnt)[rep]
    wr = wx[rep]
    tile = (ty0[rep] + torch.div(local, wr, rounding_mode="floor")) * ntx + tx0[rep] + local % wr
    tile, order = torch.sort(tile, stable=True)  # stable: planes stay ascending within a tile (depth ties)
    return tile, pid[rep[order]], ntx, nty


def _cull_occluded(tile, plane, ntx, tile_size, width, height, intrinsics, tab, zmin, margin, max_hits,
                   near=NEAR):
    """Keep-mask over (tile, plane) pairs: drop candidates no pixel of the tile can composite.

    Both tests look at the rays of the tile's 4 corner pixels: a rectangle seen from the camera is
    convex, so one containing those 4 rays contains every pixel ray of the tile, and 1 / depth is
    affine in the pixel, so depths over the tile lie between the corner depths. A candidate's
    depth over the tile is bounded below by its corner depths (when all are in front) and by its
    nearest vertex (``zmin``); it is dropped when that bound exceeds
    - the far corner depth of a plane whose rectangle proper (weight 1) covers the tile: the
      transmittance behind it is 0 in every pixel; or
    - the ``max_hits``-th smallest far corner depth of the planes whose dilated rectangle (weight
      > WEIGHT_EPS, with a 0.1 % margin for round-off) covers the tile: every pixel has max_hits
      nearer hits already. This one does the work when lambda is small and splats are wide.
    A candidate is also dropped when its 4 corner hits lie beyond one edge of its dilated rectangle
    (the screen box of a slanted plane covers many tiles the plane misses).
    Exact for the rendered output (near-ties are kept); it only saves work.
    """
    fx, fy, cx, cy = intrinsics
    ts = tile_size
    x0 = (tile % ntx) * ts
    y0 = torch.div(tile, ntx, rounding_mode="floor") * ts
    x1 = torch.clamp(x0 + ts - 1, max=width - 1)
    y1 = torch.clamp(y0 + ts - 1, max=height - 1)
    dt = tab.dtype
    u = (torch.stack([x0, x1, x1, x0], 1).to(dt) + 0.5 - cx) / fx  # (N, 4) corner rays
    v = (torch.stack([y0, y0, y1, y1], 1).to(dt) + 0.5 - cy) / fy
    g = _gather(tab, plane)
    t, _, a = _pair_terms(g[..., None], u, v, 1.0, full=True)
    # distance outside the rectangle along X and Y at each corner (lam = 1 gives it in metres)
    e = torch.maximum(-a["zx"], -a["zy"]).amax(1)
    front = (t > near).all(1) & torch.isfinite(t).all(1)
    full = front & (e <= 0)
    covered = front & (e < margin * (1 - 1e-3))
    # the 4 corners' hits all beyond one edge of the dilated rectangle: so are all the tile's pixels' (their
    # hits are convex combinations of the corners'), and the plane misses the tile
    px, py, r, mg = a["px"], a["py"], g[_R, :, None], BIN_SLACK * margin
    apart = (px > r[0] + mg).all(1) | (px < -(r[1] + mg)).all(1)
    apart |= (py > r[2] + mg).all(1) | (py < -(r[3] + mg)).all(1)
    inf = float("inf")
    z_far = torch.where(front, t.amax(1), inf)
    n_tiles = int(tile.max()) + 1
    empty = torch.full((n_tiles,), inf, dtype=t.dtype, device=t.device)
    cut = empty.scatter_reduce(0, tile, torch.where(full, z_far, inf), reduce="amin")
    # max_hits-th smallest far depth among the covering planes
    zc = torch.where(covered, z_far, inf)
    if max_hits <= 8:  # by repeated minimum (ties removed together only make it larger: conservative)
        kth = empty
        for _ in range(max_hits):
            kth = empty.scatter_reduce(0, tile, zc, reduce="amin")
            zc = torch.where(zc <= kth[tile], inf, zc)
    else:  # sorted by (tile, depth), the entry of rank max_hits - 1 in each tile
        o1 = torch.sort(zc, stable=True).indices
        o2 = o1[torch.sort(tile[o1], stable=True).indices]
        ts_sorted = tile[o2]
        counts = torch.bincount(ts_sorted, minlength=n_tiles)
        rank = torch.arange(len(o2), device=tile.device) - (torch.cumsum(counts, 0) - counts)[ts_sorted]
        kth = empty.scatter_reduce(0, ts_sorted, torch.where(rank == max_hits - 1, zc[o2], inf), reduce="amin")
    cut = torch.minimum(cut, kth)
    z_near = torch.where(front, torch.maximum(t.amin(1), zmin[plane]), zmin[plane])
    # keep near-ties: corner depths and the per-pixel depths round differently, and a tie between
    # two coplanar planes can decide which one is composited
    return (z_near <= cut[tile] * (1 + 1e-4) + 1e-6) & ~(front & apart)


@torch.no_grad()
def select_hits(
    center: torch.Tensor,  # (K, 3)
    quat: torch.Tensor,  # (K, 4)
    radii: torch.Tensor,  # (K, 4)
    cam_from_world: torch.Tensor,  # (4, 4)
    intrinsics: tuple,
    width: int,
    height: int,
    lam: float,
    max_hits: int = MAX_HITS,
    tile_size: int = TILE_SIZE,
    near: float = NEAR,
    hit_rule: str = "nearest",
) -> torch.Tensor:
    """Which planes each pixel composites (torch backend): :math:`(H W, M)` int64, in compositing order, -1 padded.

    A pixel's candidates are the intersections with t > ``near`` and splat weight > WEIGHT_EPS. With
    ``hit_rule="nearest"`` (this toolkit's, both backends) it keeps the M nearest (depth ties: lower plane index
    first) and of those the ones in front of the point where the transmittance falls below TRANSMITTANCE_EPS.
    ``"reference"`` is the reference rasterizer's rule (``renderCUDA``): the tile's planes are walked
    in order of their centres' depth (ties by plane index), and a hit is taken only when it lies no nearer than the
    last one taken, until M are taken or the transmittance falls below TRANSMITTANCE_EPS.
    """
    _check_inputs(center, quat, radii, cam_from_world, width, height)
    check_near(near)
    check_hit_rule(hit_rule)
    intrinsics = tuple(float(v) for v in intrinsics)
    cam = _planes_in_camera(center, quat, radii, cam_from_world.to(device=center.device, dtype=center.dtype))
    return _select(cam, _plane_table(*cam), intrinsics, width, height, lam, max_hits, tile_size, near=near,
                   hit_rule=hit_rule)


HIT_RULES = ("nearest", "reference")


def check_hit_rule(hit_rule: str) -> None:
    if hit_rule not in HIT_RULES:
        raise InputError(f"unknown hit rule {hit_rule!r}; choose one of {', '.join(HIT_RULES)}")


def _select(cam, tab, intrinsics, width, height, lam, max_hits, tile_size, tw=None, near=NEAR,
            hit_rule="nearest") -> torch.Tensor:
    """:func:`select_hits` on camera-frame planes; fills ``tw`` = (depth, weight) (P, M) of the hits when given."""
    c, ax, ay, n, r = (x.detach() for x in cam)
    dev = c.device
    hits = torch.full((width * height, max_hits), -1, dtype=torch.long, device=dev)
    if len(c) == 0:
        return hits
    boxes, zmin, vis = _screen_boxes(c, ax, ay, n, r, lam, intrinsics, width, height, near)
    if not bool(vis.any()):
        return hits
    tile, plane, ntx, nty = _tile_pairs(boxes, vis, width, height, tile_size)
    if len(tile) == 0:
        return hits
    if hit_rule == "nearest":  # the occlusion cull is exact for the nearest hits only
        margin = SPLAT_MARGIN / lam
        keep = _cull_occluded(tile, plane, ntx, tile_size, width, height, intrinsics, tab, zmin, margin, max_hits,
                              near)
        tile, plane = tile[keep], plane[keep]
    rank, size = _group_sizes(tile, ntx * nty, max_hits)
    u, v = _pixel_axes(width, height, intrinsics, c.dtype, dev)
    _select_in_groups(hits, tile, plane, rank, size, len(c), ntx, nty, tile_size, width, height, u, v, tab, lam, tw,
                      near, hit_rule)
    return hits


def _group_sizes(tile, n_tiles: int, max_hits: int):
    """Rank of each (tile, plane) pair within its tile and each tile's padded candidate count (0: none)."""
    counts = torch.bincount(tile, minlength=n_tiles)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(tile), device=tile.device) - start[tile]
    # tiles grouped by candidate count rounded up to a power of 2 (>= max_hits): few groups, padding < 2x
    lmin = max(max_hits, 4)
    size = torch.clamp(counts, min=1).double().log2().ceil().exp2().long().clamp(min=lmin)
    size[counts == 0] = 0
    return rank, size


def _select_in_groups(hits, tile, plane, rank, size, K, ntx, nty, tile_size, width, height, u, v, tab, lam, tw=None,
                      near=NEAR, hit_rule="nearest"):
    """Fill ``hits`` (and the depths and weights ``tw``, when given) group by group: the tiles of one padded size
    L share one batched evaluation."""
    dev = hits.device
    ts = tile_size
    ly, lx = torch.meshgrid(torch.arange(ts, device=dev), torch.arange(ts, device=dev), indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    row_of_tile = torch.empty(ntx * nty, dtype=torch.long, device=dev)
    max_hits = hits.shape[1]
    # evaluations per chunk (pixels x candidates): bounds the memory when splats are wide
    budget = _EVAL_BUDGET_CUDA if dev.type == "cuda" else _EVAL_BUDGET_CPU
    for L in torch.unique(size[size > 0]).tolist():
        tiles_all = (size == L).nonzero().squeeze(1)
        row_of_tile[tiles_all] = torch.arange(len(tiles_all), device=dev)
        in_b = size[tile] == L
        # padding: the dummy plane K, which never intersects; columns stay in ascending plane order
        cand_all = torch.full((len(tiles_all), L), K, dtype=torch.long, device=dev)
        cand_all[row_of_tile[tile[in_b]], rank[in_b]] = plane[in_b]
        if hit_rule == "reference":  # each row in order of the centres' depth, ties (and the padding) by index
            cz = tab[_C][2].clone()
            cz[-1] = math.inf  # the dummy column
            order = torch.sort(cz[cand_all], dim=1, stable=True).indices
            cand_all = torch.gather(cand_all, 1, order)
        chunk = max(1, budget // (ts * ts * L))
        for c0 in range(0, len(tiles_all), chunk):
            tiles_b, cand = tiles_all[c0 : c0 + chunk], cand_all[c0 : c0 + chunk]
            col = (tiles_b % ntx * ts)[:, None] + lx  # (nb, ts*ts)
            row = (torch.div(tiles_b, ntx, rounding_mode="floor") * ts)[:, None] + ly
            inside = (col < width) & (row < height)
            uc, vr = u[col.clamp(max=width - 1)], v[row.clamp(max=height - 1)]
            pick = _nearest_hits if hit_rule == "nearest" else _reference_hits
            sel, ts_, ws_ = pick(uc, vr, inside, cand, tab, lam, max_hits, near)
            pix = (row * width + col)[inside]
            hits[pix, : sel.shape[-1]] = sel[inside]
            if tw is not None:
                tw[0][pix, : sel.shape[-1]] = ts_[inside]
                tw[1][pix, : sel.shape[-1]] = ws_[inside]


def _nearest_hits(u, v, inside, cand, tab, lam, max_hits, near=NEAR):
    """Per pixel, the min(max_hits, L) nearest of its tile's L candidates it composites (nb, S, k), -1 padded,
    and their depths and weights (0 where unused).

    ``u``, ``v``, ``inside``: (nb, S) pixel rays and in-image mask; ``cand``: (nb, L) plane indices,
    ascending within a row. Nearest first, depth ties by plane index.
    """
    nb, L = cand.shape
    S, k = u.shape[1], min(max_hits, L)
    t, w = _pair_terms(_gather(tab, cand[:, None, :]), u[..., None], v[..., None], lam)  # (nb, S, L)
    ok = _valid(t, w, near) & inside[..., None]
    if t.dtype == torch.float32 and L < (1 << 16):
        # one key per pair: the depth's bits (t > 0 sorts as its bits do) then the column, i.e. the plane order;
        # distinct keys, so any sort orders them by (depth, plane index). A whole-row sort is faster than topk
        # on rows of up to 16 (CPU, 400k keys: 6 against 8 ms at 8 columns), topk beyond (6 against 15 at 64)
        col = torch.arange(L, device=t.device)
        key = torch.where(ok, t.view(torch.int32).to(torch.int64) << 16 | col, torch.iinfo(torch.int64).max)
        if L <= 16:
            kv, ki = torch.sort(key, dim=-1)
            kv, ki = kv[..., :k], ki[..., :k]
        else:
            kv, ki = torch.topk(key, k, dim=-1, largest=False, sorted=True)
        found = kv < torch.iinfo(torch.int64).max
    else:  # a stable sort of the rows, whose columns are in plane order, breaks depth ties by plane index
        kv, ki = torch.sort(torch.where(ok, t, math.inf), dim=-1, stable=True)
        kv, ki = kv[..., :k], ki[..., :k]
        found = torch.isfinite(kv)
    tk, wk = torch.where(found, t.gather(2, ki), 0.0), torch.where(found, w.gather(2, ki), 0.0)
    sel = torch.gather(cand[:, None, :].expand(-1, S, -1), 2, ki)
    # front-to-back compositing stops once the transmittance is below TRANSMITTANCE_EPS
    trans = torch.cumprod(torch.cat([torch.ones_like(wk[..., :1]), 1 - wk[..., :-1]], -1), -1)
    used = found & (trans >= TRANSMITTANCE_EPS)
    return torch.where(used, sel, -1), torch.where(used, tk, 0.0), torch.where(used, wk, 0.0)


def _reference_hits(u, v, inside, cand, tab, lam, max_hits, near=NEAR):
    """:func:`_nearest_hits` under the reference rasterizer's rule: ``cand`` (nb, L) in walking order (the centres'
    depth); a pixel takes a hit when it lies no nearer than its last one, until it has ``max_hits`` or its
    transmittance is below TRANSMITTANCE_EPS. Returns (nb, S, k) planes, depths and weights, -1 / 0 padded.

    No loop over the walk: a valid hit is taken exactly when it lies no nearer than every valid hit before it (a
    skipped one lies nearer than a taken one before it, so the running maximum over the valid hits is the last
    taken depth); the cap and the transmittance then cut the taken ones to a prefix.
    """
    nb, L = cand.shape
    S, k = u.shape[1], min(max_hits, L)
    t, w = _pair_terms(_gather(tab, cand[:, None, :]), u[..., None], v[..., None], lam)  # (nb, S, L)
    ok = _valid(t, w, near) & inside[..., None]
    tv = torch.where(ok, t, -math.inf)
    before = torch.cat([torch.full_like(tv[..., :1], -math.inf), torch.cummax(tv, -1).values[..., :-1]], -1)
    take = ok & (t >= before)
    wt = torch.where(take, w, 0.0)
    trans = torch.cumprod(torch.cat([torch.ones_like(wt[..., :1]), 1 - wt[..., :-1]], -1), -1)
    rank = torch.cumsum(take.long(), -1)
    take &= (rank <= k) & (trans >= TRANSMITTANCE_EPS)
    slot = torch.where(take, rank - 1, k)  # column k collects what is not taken, and is dropped
    out = []
    for val, pad in ((cand[:, None, :].expand(-1, S, -1), -1), (t, 0.0), (w, 0.0)):
        o = torch.full((nb, S, k + 1), pad, dtype=val.dtype, device=t.device)
        out.append(o.scatter_(2, slot, torch.where(take, val, pad))[..., :k])
    return tuple(out)


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
