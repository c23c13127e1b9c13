"""Fast differentiable plane renderer (depth, normal, alpha) for CPU and CUDA, in plain torch.

The paper's renderer (appendix A) intersects every pixel ray with every plane, keeps the M = 5
nearest intersections whose splat weight exceeds 1e-4 and composites them front to back. Done
literally in torch that is O(pixels x planes) (320x240 x 2000 planes: 5.5 s, 23 GB per iteration).
Here the work is split in two:

1. :func:`select_hits` (no gradient): which planes each pixel sees. Each plane's rectangle, dilated
   by the width of its sigmoid fall-off (``SPLAT_MARGIN / lam``), is clipped to the near plane and
   projected; its screen bounding box is binned into tiles; every (tile, plane) pair is expanded
   and sorted by tile; tiles are grouped by candidate count (padded to a power of two) and each
   group intersects its pixels with its candidates in one batched matmul, keeping the M nearest
   hits by ``topk``. Hits behind a transmittance below 1e-4 are dropped. Output: a (P, M) index
   tensor, -1 padded.
2. :func:`composite_hits` (differentiable): gathers only those (pixel, plane) pairs, recomputes
   intersection, splat weight and front-to-back compositing with autograd.

The all-pairs twin lives in :mod:`lipmap.planes._torch_impl` (``_render_all_pairs``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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
_EVAL_BUDGET_CPU = 1 << 22  # (pixel, candidate) evaluations per batched step of the selection
_EVAL_BUDGET_CUDA = 1 << 26


def lambda_schedule(iteration: int, max_iters: int, lam_min: float = 0.0, lam_max: float = 1500.0) -> float:
    """Sharpness of the splat fall-off: ``5 * min(20 * exp(iter / (max_iters // 10) - 1), 300)``.

    Starts at 5 * 20 / e = 36.8 (weight 1e-4 reached ~27 cm outside a rectangle) and saturates at
    1500 (6.6 mm) from 37 % of the iterations on (reference-code schedule, see DESIGN.md).
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
        hits: :math:`(H, W, M)` int64 indices of the composited planes, nearest first, -1 padded
            (no gradient); ``hits[..., 0]`` is the first plane each pixel's ray meets.
    """

    depth: torch.Tensor
    normal: torch.Tensor
    alpha: torch.Tensor
    hits: torch.Tensor

    @property
    def n_pairs(self) -> int:
        return int((self.hits >= 0).sum())

    def visible_planes(self, n_planes: int) -> torch.Tensor:
        """:math:`(K,)` bool: planes that contribute to at least one pixel."""
        seen = torch.zeros(n_planes, dtype=torch.bool, device=self.hits.device)
        h = self.hits[self.hits >= 0]
        seen[h] = True
        return seen


# ------------------------------------------------------------------------------------------------
# shared pieces
# ------------------------------------------------------------------------------------------------
def _planes_in_camera(center, quat, radii, cam_from_world):
    """Camera-frame centres (K,3), axes X, Y, normal (K,3 each; normal flipped to face the camera), radii (K,4)."""
    T = cam_from_world.to(device=center.device, dtype=center.dtype)
    c = center @ T[:3, :3].T + T[:3, 3]
    Rc = T[:3, :3] @ quat_to_rotmat(quat)
    # contiguous copies: index_select on the strided column views is several times slower
    ax, ay, n = Rc[..., 0].contiguous(), Rc[..., 1].contiguous(), Rc[..., 2]
    n = torch.where(((n * c).sum(-1) > 0)[:, None], -n, n)
    return c, ax, ay, n, radii.clamp(R_MIN, R_MAX)


def _pixel_rays(pix: torch.Tensor, width: int, intrinsics, dtype) -> torch.Tensor:
    """Rays (N, 3) with z = 1 through the centres of flat pixel indices ``pix`` (row-major)."""
    fx, fy, cx, cy = intrinsics
    col = (pix % width).to(dtype)
    row = torch.div(pix, width, rounding_mode="floor").to(dtype)
    return torch.stack([(col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy, torch.ones_like(col)], -1)


def _pair_weights(c, n, ax, ay, r, k, d, lam: float):
    """Depth t (N,) and splat weight w (N,) of rays d (N, 3) on planes c, n, ax, ay (N, 3).

    ``r`` (K, 4) are all planes' radii and ``k`` (N,) the plane of each pair: the radius on the
    side of the hit is gathered straight from ``r`` (a gather of whole rows followed by column
    slices would allocate an (N, 4) zero gradient per slice in the backward pass).
    """
    t = (n * c).sum(-1) / (n * d).sum(-1)
    p = t[:, None] * d - c
    px, py = (p * ax).sum(-1), (p * ay).sum(-1)
    rf = r.reshape(-1)
    rx = rf.index_select(0, 4 * k + (px <= 0).long())
    ry = rf.index_select(0, 4 * k + 2 + (py <= 0).long())
    zx, zy = lam * (rx - px.abs()), lam * (ry - py.abs())
    one = torch.ones_like(zx)
    wx = torch.where(zx >= 0, one, 2 * torch.sigmoid(zx))
    wy = torch.where(zy >= 0, one, 2 * torch.sigmoid(zy))
    return t, torch.minimum(wx, wy)


def _compact(hits: torch.Tensor) -> torch.Tensor:
    """Move each row's valid entries (>= 0) to the front, keeping their order: (P, M) -> (P, M)."""
    order = torch.sort((hits < 0).to(torch.uint8), dim=1, stable=True).indices
    return torch.gather(hits, 1, order)


@dataclass
class _FlatPairs:
    """The valid entries of a compacted (P, M) hit tensor, slot-major: all first hits, then all second..."""

    pix: torch.Tensor  # (N,) pixel index, ascending within each slot block
    slot: torch.Tensor  # (N,) position in the pixel's list
    plane: torch.Tensor  # (N,) plane index
    offsets: list  # slot s occupies [offsets[s], offsets[s + 1])
    prev: list  # prev[s] (n_s,): position, within slot s - 1's block, of the same pixel (s >= 1)

    @staticmethod
    def from_hits(hits: torch.Tensor) -> "_FlatPairs":
        """From a (P, M) hit tensor whose rows are prefixes (valid entries first)."""
        valid = hits >= 0
        pix, plane, slot, prev, offsets = [], [], [], [None], [0]
        for s in range(hits.shape[1]):
            p_s = valid[:, s].nonzero().squeeze(1)
            if len(p_s) == 0:
                break
            if s > 0:  # p_s is a subset of the previous slot's pixels (rows are prefixes)
                prev.append((torch.cumsum(valid[:, s - 1], 0) - 1).index_select(0, p_s))
            pix.append(p_s)
            plane.append(hits[:, s].index_select(0, p_s))
            slot.append(torch.full_like(p_s, s))
            offsets.append(offsets[-1] + len(p_s))
        if not pix:
            e = torch.zeros(0, dtype=torch.long, device=hits.device)
            return _FlatPairs(e, e, e, [0, 0], [None])
        return _FlatPairs(torch.cat(pix), torch.cat(slot), torch.cat(plane), offsets, prev)

    def transmittance(self, w: torch.Tensor) -> torch.Tensor:
        """(N,) T_j = prod_{i<j} (1 - w_i) along each pixel's list (differentiable in w)."""
        o = self.offsets
        T = [torch.ones(o[1] - o[0], dtype=w.dtype, device=w.device)]
        for s in range(1, len(o) - 1):
            if o[s + 1] == o[s]:
                break
            T.append((T[-1] * (1 - w[o[s - 1] : o[s]]))[self.prev[s]])
        return torch.cat(T)


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
def _screen_boxes(c, ax, ay, n, r, lam, intrinsics, width, height):
    """Screen boxes (u0, u1, v0, v1) (K,) each of the dilated, near-clipped rectangles, their
    minimum z-depth (K,) and a visibility mask (K,)."""
    fx, fy, cx, cy = intrinsics
    rd = r + SPLAT_MARGIN / lam
    sx = torch.stack([rd[:, 0], rd[:, 0], -rd[:, 1], -rd[:, 1]], 1)[..., None]
    sy = torch.stack([rd[:, 2], -rd[:, 3], -rd[:, 3], rd[:, 2]], 1)[..., None]
    V = c[:, None] + sx * ax[:, None] + sy * ay[:, None]  # (K, 4, 3)
    V2 = V.roll(-1, dims=1)
    z, z2 = V[..., 2], V2[..., 2]
    # the polygon clipped to z >= NEAR: its front corners plus the edges' crossings of z = NEAR
    cross = (z - NEAR) * (z2 - NEAR) < 0
    s = ((NEAR - z) / torch.where(cross, z2 - z, torch.ones_like(z))).clamp(0, 1)
    Vc = V + s[..., None] * (V2 - V)
    pts = torch.cat([V, Vc], 1)  # (K, 8, 3)
    ok = torch.cat([z >= NEAR, cross], 1)
    zz = torch.where(ok, pts[..., 2], torch.ones_like(pts[..., 2])).clamp(min=NEAR)
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
    """(tile, plane) pairs sorted by tile, expanded from each visible plane's tile range."""
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
    tile, order = torch.sort(tile, stable=True)
    return tile, pid[rep[order]], ntx, nty


def _cull_occluded(tile, plane, ntx, tile_size, width, height, intrinsics, n, ax, ay, scal, zmin, margin, max_hits):
    """Keep-mask over (tile, plane) pairs: drop candidates no pixel of the tile can composite.

    Both tests look at the rays of the tile's 4 corner pixels: a rectangle seen from the camera is
    convex, so one containing those 4 rays contains every pixel ray of the tile, and 1 / depth is
    affine in the pixel, so depths over the tile lie between the corner depths. A candidate's
    depth over the tile is bounded below by its corner depths (when all are in front) and by its
    nearest vertex (``zmin``); it is dropped when that bound exceeds
    - the far corner depth of a plane whose rectangle proper (weight 1) covers the tile: the
      transmittance behind it is 0 in every pixel; or
    - the ``max_hits``-th smallest far corner depth of the planes whose dilated rectangle (weight
      > WEIGHT_EPS) covers the tile: every pixel has max_hits nearer hits already. This one does
      the work when lambda is small and splats are wide.
    Exact for the rendered output (ties are kept); it only saves work.
    """
    fx, fy, cx, cy = intrinsics
    ts = tile_size
    x0 = (tile % ntx) * ts
    y0 = torch.div(tile, ntx, rounding_mode="floor") * ts
    x1 = torch.clamp(x0 + ts - 1, max=width - 1)
    y1 = torch.clamp(y0 + ts - 1, max=height - 1)
    u = (torch.stack([x0, x1, x1, x0], 1).to(n.dtype) + 0.5 - cx) / fx  # (N, 4) corner rays
    v = (torch.stack([y0, y0, y1, y1], 1).to(n.dtype) + 0.5 - cy) / fy
    nk, xk, yk, sk = n[plane], ax[plane], ay[plane], scal[plane]

    def dot(a):
        return a[:, None, 0] * u + a[:, None, 1] * v + a[:, None, 2]

    t = sk[:, None, 0] / dot(nk)  # (N, 4)
    front = (t > NEAR).all(1)
    e = torch.maximum((t * dot(xk) - sk[:, None, 1]).abs() - sk[:, None, 3], (t * dot(yk) - sk[:, None, 2]).abs() - sk[:, None, 4])
    e = e.amax(1)  # how far the worst corner is outside the rectangle
    full = front & (e <= 0)
    covered = front & (e < margin)
    inf = float("inf")
    z_far = torch.where(front, t.amax(1), inf)
    n_tiles = int(tile.max()) + 1
    empty = torch.full((n_tiles,), inf, dtype=t.dtype, device=t.device)
    cut = empty.scatter_reduce(0, tile, torch.where(full, z_far, inf), reduce="amin")
    # max_hits-th smallest far depth among the covering planes, by repeated minimum (ties
    # removed together only make it larger, i.e. more conservative)
    zc = torch.where(covered, z_far, inf)
    kth = empty
    for _ in range(max_hits):
        kth = empty.scatter_reduce(0, tile, zc, reduce="amin")
        zc = torch.where(zc <= kth[tile], inf, zc)
    cut = torch.minimum(cut, kth)
    z_near = torch.where(front, torch.maximum(t.amin(1), zmin[plane]), zmin[plane])
    # keep near-ties: corner depths and the per-pixel depths round differently, and a tie between
    # two coplanar planes can decide which one is composited
    return z_near <= cut[tile] * (1 + 1e-4) + 1e-6


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
) -> torch.Tensor:
    """Which planes each pixel composites: :math:`(H W, M)` int64, nearest first, -1 padded.

    A pixel keeps the M nearest intersections (t > NEAR) with splat weight > WEIGHT_EPS (tested
    as "inside the rectangle dilated by SPLAT_MARGIN / lam"). The transmittance cut-off is applied
    by :func:`composite_hits`, which computes the weights anyway.
    """
    _check_inputs(center, quat, radii, cam_from_world, width, height)
    intrinsics = tuple(float(v) for v in intrinsics)
    dev = center.device
    P = width * height
    hits = torch.full((P, max_hits), -1, dtype=torch.long, device=dev)
    K = len(center)
    if K == 0:
        return hits
    c, ax, ay, n, r = _planes_in_camera(center, quat, radii, cam_from_world)
    boxes, zmin, vis = _screen_boxes(c, ax, ay, n, r, lam, intrinsics, width, height)
    if not bool(vis.any()):
        return hits
    tile, plane, ntx, nty = _tile_pairs(boxes, vis, width, height, tile_size)
    if len(tile) == 0:
        return hits
    # the selection test "splat weight > WEIGHT_EPS" is "|X . x - xc| < hx + margin" (same along Y)
    margin = SPLAT_MARGIN / lam
    dirs, scal = _intersection_tables(c, ax, ay, n, r)
    keep = _cull_occluded(tile, plane, ntx, tile_size, width, height, intrinsics, n, ax, ay, scal, zmin, margin, max_hits)
    tile, plane = tile[keep], plane[keep]
    rank, size = _group_sizes(tile, ntx * nty, max_hits)
    _select_in_groups(hits, tile, plane, rank, size, K, ntx, nty, tile_size, width, height, intrinsics, dirs, scal,
                      margin, lam, max_hits)
    return hits


def _intersection_tables(c, ax, ay, n, r):
    """Per-plane directions (K+1, 3, 3) and scalars (K+1, 5) for the batched intersection; row K never hits."""
    dev, dt = c.device, c.dtype
    # plane (n . x = nc) and rectangle in coordinates centred on it, so that the splat weight along
    # X is 1 for |X . x - xc| <= hx and 2 sigmoid(lam (hx - |X . x - xc|)) beyond (same for Y)
    nc = (n * c).sum(-1)
    xc = (ax * c).sum(-1) + 0.5 * (r[:, 0] - r[:, 1])
    yc = (ay * c).sum(-1) + 0.5 * (r[:, 2] - r[:, 3])
    hx = 0.5 * (r[:, 0] + r[:, 1])
    hy = 0.5 * (r[:, 2] + r[:, 3])
    # row K is a dummy that never intersects (t = -1 < NEAR), used for padding
    dirs = torch.cat([torch.stack([n, ax, ay], 2), torch.eye(3, device=dev, dtype=dt)[[2, 0, 1]].T[None]])  # (K+1, 3, 3)
    scal = torch.cat([torch.stack([nc, xc, yc, hx, hy], 1), torch.tensor([[-1.0, 0, 0, 0, 0]], device=dev, dtype=dt)])
    return dirs, scal


def _group_sizes(tile, n_tiles: int, max_hits: int):
    """Rank of each (tile, plane) pair within its tile and each tile's padded candidate count (0: none)."""
    counts = torch.bincount(tile, minlength=n_tiles)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(tile), device=tile.device) - start[tile]
    # tiles grouped by candidate count rounded up to 2^k or 1.5 * 2^k (>= max_hits): padding < 1.5x
    lmin = max(max_hits, 4)
    p2 = torch.clamp(counts, min=1).double().log2().ceil().exp2()
    size = torch.where(counts <= 0.75 * p2, 0.75 * p2, p2).long().clamp(min=lmin)
    size[counts == 0] = 0
    return rank, size


def _select_in_groups(hits, tile, plane, rank, size, K, ntx, nty, tile_size, width, height, intrinsics, dirs, scal,
                      margin, lam, max_hits):
    """Fill ``hits`` group by group: the tiles of one padded size L share one batched intersection."""
    dev = hits.device
    ts = tile_size
    ly, lx = torch.meshgrid(torch.arange(ts, device=dev), torch.arange(ts, device=dev), indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    row_of_tile = torch.empty(ntx * nty, dtype=torch.long, device=dev)
    # evaluations per chunk (pixels x candidates): bounds the memory when splats are wide
    budget = _EVAL_BUDGET_CUDA if dev.type == "cuda" else _EVAL_BUDGET_CPU
    for L in torch.unique(size[size > 0]).tolist():
        tiles_all = (size == L).nonzero().squeeze(1)
        row_of_tile[tiles_all] = torch.arange(len(tiles_all), device=dev)
        in_b = size[tile] == L
        cand_all = torch.full((len(tiles_all), L), K, dtype=torch.long, device=dev)
        cand_all[row_of_tile[tile[in_b]], rank[in_b]] = plane[in_b]
        chunk = max(1, budget // (ts * ts * L))
        for c0 in range(0, len(tiles_all), chunk):
            tiles_b, cand = tiles_all[c0 : c0 + chunk], cand_all[c0 : c0 + chunk]
            row, col, inside, A = _tile_pixel_rays(tiles_b, lx, ly, ntx, ts, width, height, intrinsics, dirs.dtype)
            sel = _nearest_hits(A, cand, inside, dirs, scal, margin, lam, max_hits)
            pix = (row * width + col)[inside]
            hits[pix, : sel.shape[-1]] = sel[inside]


def _tile_pixel_rays(tiles_b, lx, ly, ntx, ts, width, height, intrinsics, dt):
    """Rows, columns, in-image mask (nb, ts*ts) and z = 1 rays (nb, ts*ts, 3) of the pixels of tiles ``tiles_b``."""
    fx, fy, cx, cy = intrinsics
    col = (tiles_b % ntx * ts)[:, None] + lx  # (nb, ts*ts)
    row = (torch.div(tiles_b, ntx, rounding_mode="floor") * ts)[:, None] + ly
    inside = (col < width) & (row < height)
    A = torch.stack([(col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy, torch.ones(col.shape, dtype=dt, device=col.device)], -1)
    return row, col, inside, A


def _nearest_hits(A, cand, inside, dirs, scal, margin, lam, max_hits):
    """Per pixel, the min(max_hits, L) nearest of its tile's L candidates it hits (nb, ts*ts, k), -1 padded."""
    nb, L = cand.shape
    inf = float("inf")
    # (nb, 3, 3L): for each candidate the columns n, X, Y; one bmm gives every n.d, X.d, Y.d
    B = dirs.index_select(0, cand.reshape(-1)).reshape(nb, L, 3, 3).permute(0, 2, 3, 1).reshape(nb, 3, 3 * L)
    dots = torch.bmm(A, B)  # (nb, ts*ts, 3L)
    sc = scal.index_select(0, cand.reshape(-1)).reshape(nb, 1, L, 5)
    t = sc[..., 0] / dots[..., :L]
    ex = (t * dots[..., L : 2 * L] - sc[..., 1]).abs_().sub_(sc[..., 3])  # distance outside, along X
    ey = (t * dots[..., 2 * L :] - sc[..., 2]).abs_().sub_(sc[..., 4])
    ok = (t > NEAR) & (ex < margin) & (ey < margin) & inside[..., None]
    k = min(max_hits, L)
    kv, ki = torch.topk(torch.where(ok, t, inf), k, dim=-1, largest=False, sorted=True)
    # transmittance along the k nearest; entries behind T < TRANSMITTANCE_EPS / 2 are dropped
    # (the exact cut at TRANSMITTANCE_EPS is made by composite_hits with its own arithmetic)
    e = torch.maximum(ex.gather(2, ki), ey.gather(2, ki))
    w = torch.where(e <= 0, 1.0, 2 * torch.sigmoid(-lam * e))
    w = torch.where(torch.isfinite(kv), w, 0.0)
    trans = torch.cumprod(torch.cat([torch.ones_like(w[..., :1]), 1 - w[..., :-1]], -1), -1)
    sel = torch.gather(cand[:, None, :].expand(-1, A.shape[1], -1), 2, ki)
    return torch.where(torch.isfinite(kv) & (trans >= 0.5 * TRANSMITTANCE_EPS), sel, -1)


# ------------------------------------------------------------------------------------------------
# 2. compositing (differentiable)
# ------------------------------------------------------------------------------------------------
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
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable depth (H,W), normal (H,W,3), alpha (H,W) from the selected (pixel, plane) pairs.

    Also returns the (P, M) hits, nearest first, without the pairs that contribute nothing
    (weight <= WEIGHT_EPS after round-off, or behind a transmittance below TRANSMITTANCE_EPS), -1 padded.
    """
    intrinsics = tuple(float(v) for v in intrinsics)
    dev, dt = center.device, center.dtype
    P = hits.shape[0]
    if bool(((hits[:, 1:] >= 0) & (hits[:, :-1] < 0)).any()):
        hits = _compact(hits)
    fp = _FlatPairs.from_hits(hits)
    c, ax, ay, n, r = _planes_in_camera(center, quat, radii, cam_from_world)
    k = fp.plane
    # separate index_selects: their backward is a small index_add each (slicing one packed
    # gather would allocate a zero (N, 16) gradient per slice)
    nk = n.index_select(0, k)
    d = _pixel_rays(fp.pix, width, intrinsics, dt)
    t, w = _pair_weights(c.index_select(0, k), nk, ax.index_select(0, k), ay.index_select(0, k), r, k, d, lam)
    zero = torch.zeros_like(w)
    w = torch.where(w.detach() > WEIGHT_EPS, w, zero)  # float round-off vs. the selection's dilated test
    trans = fp.transmittance(w)
    # front-to-back compositing stops once the transmittance is below TRANSMITTANCE_EPS
    tw = torch.where(trans.detach() >= TRANSMITTANCE_EPS, trans * w, zero)
    depth = torch.zeros(P, dtype=dt, device=dev).index_add(0, fp.pix, tw * t)
    alpha = torch.zeros(P, dtype=dt, device=dev).index_add(0, fp.pix, tw)
    normal = torch.zeros(P, 3, dtype=dt, device=dev).index_add(0, fp.pix, tw[:, None] * nk)
    with torch.no_grad():
        unused = tw == 0
        if bool(unused.any()):
            hits = hits.clone()
            hits[fp.pix[unused], fp.slot[unused]] = -1
            if bool(((hits[:, 1:] >= 0) & (hits[:, :-1] < 0)).any()):
                hits = _compact(hits)  # keep "hits[..., 0] = the first composited plane"
    return depth.reshape(height, width), normal.reshape(height, width, 3), alpha.reshape(height, width), hits


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
) -> RenderOutput:
    """Render planes into one pinhole camera; differentiable w.r.t. center, quat and radii.

    Args:
        center, quat, radii: plane parameters (see :class:`~lipmap.planes.primitives.Planes`).
        cam_from_world: :math:`(4, 4)` pose (x_cam = R x_world + t).
        intrinsics: (fx, fy, cx, cy), COLMAP convention (pixel (i, j) centred at (i+.5, j+.5)).
        width, height: image size in pixels.
        lam: splat sharpness, see :func:`lambda_schedule`.
        max_hits: M, intersections composited per pixel.
        tile_size: tile edge in pixels for the selection (speed only; results do not depend on it).

    Returns:
        :class:`RenderOutput` (depth, normal, alpha, hits).
    """
    if not isinstance(cam_from_world, torch.Tensor):
        cam_from_world = torch.as_tensor(np.asarray(cam_from_world), dtype=center.dtype, device=center.device)
    cam_from_world = cam_from_world.to(device=center.device, dtype=center.dtype)
    hits = select_hits(center.detach(), quat.detach(), radii.detach(), cam_from_world, intrinsics, width, height, lam, max_hits, tile_size)
    depth, normal, alpha, hits = composite_hits(hits, center, quat, radii, cam_from_world, intrinsics, width, height, lam)
    return RenderOutput(depth, normal, alpha, hits.reshape(height, width, max_hits))


def render_planes(
    planes: Planes,
    camera,
    cam_from_world,
    lam: float,
    downscale: float = 1.0,
    max_hits: int = MAX_HITS,
    tile_size: int = TILE_SIZE,
) -> RenderOutput:
    """Render ``planes`` (:class:`Planes`) from a :class:`~lipmap.scene.Camera` at ``1 / downscale`` resolution."""
    cam = camera if downscale == 1 else camera.scaled(1.0 / downscale)
    return rasterize_planes(
        planes.center, planes.quat, planes.radii, cam_from_world, cam.params, cam.width, cam.height, lam, max_hits, tile_size
    )


def render_view(planes: Planes, view, lam: float, downscale: float = 1.0, **kw) -> RenderOutput:
    """Render ``planes`` into a :class:`~lipmap.scene.View` (its camera and ``cam_from_world``)."""
    if view.cam_from_world is None:
        raise InputError(f"view {view.name} has no pose")
    return render_planes(planes, view.camera, view.cam_from_world, lam, downscale, **kw)
