"""Which planes each pixel composites, the torch reference of the renderer's selection (no gradient): the planes'
screen boxes binned into tiles, the candidates no pixel of a tile can composite culled, and each pixel's hits under
the nearest-hit rule or the reference rasterizer's (:func:`select_hits`). The Warp kernel ``_raster_fwd`` selects the
same hits; :mod:`lipmap.planes.render` composites them.
"""
from __future__ import annotations

import math

import torch

from ..errors import InputError
from .pairs import (_C, _R, BIN_SLACK, TILE_SIZE, _check_inputs, _gather, _pair_terms, _pixel_axes, _plane_table,
                    _planes_in_camera, _valid, check_near)
from .primitives import MAX_HITS, NEAR, SPLAT_MARGIN, TRANSMITTANCE_EPS

_EVAL_BUDGET_CPU = 1 << 21  # (pixel, candidate) evaluations per batched step of the torch selection
_EVAL_BUDGET_CUDA = 1 << 25


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

