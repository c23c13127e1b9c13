"""2D line -> 3D plane-edge assignment (paper Sec. 3.2): 1-pixel regions, first plane hit, best edge.

The selection here is non-differentiable (which plane a pixel's ray hits first, which of its four
edges explains the detected line); the line losses then differentiate through the chosen edges.
Plane geometry enters only as corners :math:`(K, 4, 3)` in the paper's vertex order v1..v4, with
edges e_k = (v_k, v_{k+1 mod 4}).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from .. import geometry as geo

EDGE_VERTS = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])


def corner_edges(corners):
    """(K, 4, 3) corners -> (K, 4, 2, 3) edges e1=(v1,v2), e2=(v2,v3), e3=(v3,v4), e4=(v4,v1) (numpy or torch)."""
    if geo._is_torch(corners):
        import torch

        return corners[:, torch.as_tensor(EDGE_VERTS, device=corners.device)]
    return corners[:, EDGE_VERTS]


def line_regions(lines: np.ndarray, width: int, height: int, radius: float = 1.0, step: float = 0.5,
                 exclusive: bool = False):
    """Pixels of each segment's 1-pixel region (paper Sec. 3.2).

    A pixel belongs to the region of a segment when its centre is within ``radius`` px of the segment
    and its foot point falls inside the segment. With ``exclusive`` a pixel in several regions belongs to the
    nearest segment alone (ties: the first), as the reference's attraction field labels each pixel with one line;
    else to each of them.

    Args:
        lines: :math:`(N, 4)` segments (x1, y1, x2, y2), COLMAP pixel convention.

    Returns:
        **pixels** :math:`(P, 2)` int (col, row), **line_idx** :math:`(P,)` int.
    """
    lines = np.asarray(lines, dtype=float).reshape(-1, 4)
    if len(lines) == 0:
        return np.zeros((0, 2), int), np.zeros(0, int)
    p0, p1 = lines[:, :2], lines[:, 2:]
    length = np.linalg.norm(p1 - p0, axis=1)
    n_s = np.maximum(2, np.ceil(length / step).astype(int) + 1)
    idx = np.repeat(np.arange(len(lines)), n_s)
    t = np.concatenate([np.linspace(0, 1, n) for n in n_s])
    pts = p0[idx] + t[:, None] * (p1 - p0)[idx]
    r = int(np.ceil(radius))
    offs = np.stack(np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1)), -1).reshape(-1, 2)
    cand = np.floor(pts)[:, None, :].astype(int) + offs[None]
    cand = cand.reshape(-1, 2)
    cidx = np.repeat(idx, len(offs))
    inside = (cand[:, 0] >= 0) & (cand[:, 0] < width) & (cand[:, 1] >= 0) & (cand[:, 1] < height)
    cand, cidx = cand[inside], cidx[inside]
    key = np.unique(cidx * (width * height) + cand[:, 1] * width + cand[:, 0])
    cidx = key // (width * height)
    rem = key % (width * height)
    pix = np.stack([rem % width, rem // width], -1)
    centre = pix + 0.5
    seg = lines[cidx]
    d = seg[:, 2:] - seg[:, :2]
    l2 = np.maximum((d * d).sum(1), 1e-12)
    tt = ((centre - seg[:, :2]) * d).sum(1) / l2
    dist = np.abs(d[:, 0] * (centre[:, 1] - seg[:, 1]) - d[:, 1] * (centre[:, 0] - seg[:, 0])) / np.sqrt(l2)
    keep = (tt >= 0) & (tt <= 1) & (dist <= radius)
    pix, cidx = pix[keep], cidx[keep]
    if exclusive and len(pix):
        flat = pix[:, 1] * width + pix[:, 0]
        order = np.lexsort((cidx, dist[keep], flat))  # per pixel: nearest first, then the lowest line index
        first = np.ones(len(order), bool)
        first[1:] = flat[order][1:] != flat[order][:-1]
        sel = np.sort(order[first])  # the (line, pixel) order of the shared case
        pix, cidx = pix[sel], cidx[sel]
    return pix, cidx


def pixel_rays_camera(pixels: np.ndarray, camera) -> np.ndarray:
    """Camera-frame rays (P, 3) through pixel centres (col, row), scaled to z = 1 (a hit's parameter is its depth)."""
    x = (pixels[:, 0] + 0.5 - camera.cx) / camera.fx
    y = (pixels[:, 1] + 0.5 - camera.cy) / camera.fy
    return np.stack([x, y, np.ones_like(x)], -1)


def pixel_rays_world(pixels: np.ndarray, cam_from_world: np.ndarray, camera):
    """World-frame ray origins (P, 3) and unit directions (P, 3) through pixel centres (col, row)."""
    d_cam = pixel_rays_camera(pixels, camera)
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    d = d_cam @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.repeat((-R.T @ t)[None], len(d), 0), d


class PlaneRaycaster:
    """First-hit ray casting against rectangles with hard borders (embree through trimesh).

    The rectangles are triangulated (two triangles per plane); ``first_hit`` returns the plane index
    (-1 for a miss) and the hit distance along the ray. Build once per set of corners.
    """

    def __init__(self, corners: np.ndarray):
        import trimesh

        corners = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 3)
        self.n_planes = len(corners)
        verts = corners.reshape(-1, 3)
        base = np.arange(len(corners)) * 4
        faces = np.concatenate([np.stack([base, base + 1, base + 2], 1), np.stack([base, base + 2, base + 3], 1)])
        self._face_plane = np.concatenate([np.arange(len(corners)), np.arange(len(corners))])
        self.mesh = trimesh.Trimesh(verts, faces, process=False) if len(corners) else None
        self._isect = None
        if self.mesh is not None:
            try:
                from trimesh.ray.ray_pyembree import RayMeshIntersector
            except ImportError:  # pragma: no cover - embreex missing: slow pure-python fallback
                from trimesh.ray.ray_triangle import RayMeshIntersector
            self._isect = RayMeshIntersector(self.mesh)

    def first_hit(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, 3), (P, 3) -> plane index (P,) (-1: miss), distance along the unit ray (P,) (inf: miss)."""
        plane = np.full(len(origins), -1, dtype=np.int64)
        dist = np.full(len(origins), np.inf)
        if self._isect is None or len(origins) == 0:
            return plane, dist
        locs, ray_idx, tri = self._isect.intersects_location(origins, dirs, multiple_hits=False)
        if len(ray_idx):
            plane[ray_idx] = self._face_plane[tri]
            dist[ray_idx] = np.linalg.norm(locs - origins[ray_idx], axis=1)
        return plane, dist


    def hit_distance(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(P, 3), (P, 3) -> the distance (P,) along each unit ray to its first hit (inf: miss): :meth:`first_hit`'s,
        to float32 precision (embree's own hit parameter), without trimesh computing the hit points, which took
        longer than casting the rays."""
        scene = getattr(self._isect, "_scene", None)  # trimesh's embree wrapper; absent in the pure-python fallback
        if scene is None or len(origins) == 0:
            return self.first_hit(origins, dirs)[1]
        res = scene.run(np.asarray(origins, dtype=np.float64), np.asarray(dirs, dtype=np.float64), output=1)
        t = np.asarray(res["tfar"], dtype=np.float64) / scene.scale  # the scene is stored scaled by ``scale``
        return np.where(np.asarray(res["geomID"]) >= 0, t, np.inf)


def plane_depth(caster: PlaneRaycaster, view) -> np.ndarray:
    """Z-depth :math:`(H, W)` float32 (metres, 0 where no plane is hit) of every pixel of ``view`` at its
    camera resolution, by ray casting the rectangles (hard borders, first hit)."""
    cam = view.camera
    jj, ii = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    pix = np.stack([jj.ravel(), ii.ravel()], 1)
    o, d = pixel_rays_world(pix, view.cam_from_world, cam)
    k, t = caster.first_hit(o, d)
    z = t * (d @ view.cam_from_world[:3, :3].T)[:, 2]
    return np.where((k >= 0) & np.isfinite(z), z, 0).reshape(cam.height, cam.width).astype(np.float32)


def plane_or_input_depth(plane_z: np.ndarray, input_z: Optional[np.ndarray], tol: float) -> np.ndarray:
    """The depth the on-plane lines are lifted with: the planes' where they model the surface, the input's
    elsewhere.

    Planes average the input depth's noise over a region (the paper's argument for lifting onto them), but
    on clutter no plane models (chair backs, mugs) they can sit centimetres off it; there the input depth
    is the better evidence.

    Args:
        plane_z: :math:`(H, W)` ray-cast plane depth (0 = no plane hit).
        input_z: :math:`(H, W)` input (sensor / predicted) depth (0 = invalid; resized by nearest sampling if
            its size differs), or None.
        tol: metres; a pixel whose plane depth is more than ``tol`` from a valid input depth (or that hits no
            plane) takes the input depth. ``tol <= 0`` or no input: the plane depth alone.

    Returns:
        :math:`(H, W)` float32 depth, 0 where neither is valid.
    """
    plane_z = np.asarray(plane_z, dtype=np.float32)
    if input_z is None or tol <= 0:
        return plane_z
    input_z = np.asarray(input_z, dtype=np.float32)
    if input_z.shape != plane_z.shape:  # depth stored at another resolution than the colour image
        from ..planes.init import resize_nearest

        input_z = resize_nearest(input_z, plane_z.shape[1], plane_z.shape[0])
    use_input = (input_z > 0) & ((plane_z <= 0) | (np.abs(plane_z - input_z) > tol))
    return np.where(use_input, input_z, plane_z)


def best_edges(corners, plane_idx, lines2d, cam_from_world, camera, dist_reduce: str = "max"):
    """For each (hit plane, detected line) pair, the plane edge that explains the line.

    Of the four projected edges keep the two closest in angle to the detected line, then pick the one
    whose endpoints are nearer (mean distance) to the detected line's infinite line (paper Sec. 3.2).

    One definition for NumPy arrays and for torch tensors on the training device (the same steps in either
    namespace, for every row at once with no data-dependent shape): float64 in, float64 out, so both pick the same
    edge.

    Args:
        corners: :math:`(K, 4, 3)`; plane_idx: :math:`(P,)` (>= 0); lines2d: :math:`(P, 4)`; cam_from_world:
            :math:`(4, 4)`; all arrays, or all tensors (``corners`` needs no gradient).

    Returns:
        **edge_idx** :math:`(P,)` in 0..3, **angle** :math:`(P,)` rad and **dist** :math:`(P,)` px
        (the paper's d_ang and d_dist: the ``dist_reduce`` - "max", or "mean" as the reference code - of the
        endpoint-to-line distances; inf where the edge does not project) of the chosen edge's projection, and the
        projected edges :math:`(P, 2, 2)`; arrays or tensors, as given.
    """
    xp = geo._xp(corners)
    P = len(plane_idx)
    if xp is np:
        if P == 0:
            z = np.zeros(0)
            return np.zeros(0, int), z, z, np.zeros((0, 2, 2))
        corners, lines2d = np.asarray(corners, dtype=float), np.asarray(lines2d, dtype=float)
    edges = corner_edges((corners if xp is np else corners.detach())[plane_idx])  # (P, 4, 2, 3)
    proj, valid = geo.project_segments(edges.reshape(-1, 2, 3), cam_from_world, camera)
    proj = proj.reshape(P, 4, 2, 2)
    valid = valid.reshape(P, 4)
    det = lines2d.reshape(P, 1, 2, 2)
    det = det if xp is np else det.to(proj.dtype)
    inf = float("inf")
    with np.errstate(invalid="ignore"):
        ang = geo.angle_distance(proj, det)
        dmean = geo.perpendicular_distance(proj, det, reduce="mean")
        ang = xp.where(valid & xp.isfinite(ang), ang, inf)
        dmean = xp.where(valid & xp.isfinite(dmean), dmean, inf)
        two = _argsort_rows(ang)[:, :2]
        edge = _take_rows(two, xp.argmin(_take_rows(dmean, two), 1)[:, None])[:, 0]
        chosen = _take_rows(proj, edge[:, None, None, None])[:, 0]
        a = geo.angle_distance(chosen, det[:, 0])
        dmax = geo.perpendicular_distance(chosen, det[:, 0], reduce=dist_reduce)
    return edge, xp.where(xp.isfinite(a), a, inf), xp.where(xp.isfinite(dmax), dmax, inf), chosen


def _argsort_rows(x):
    """Row-wise argsort, stable (of equal keys the lower index first: both namespaces pick the same edge)."""
    return np.argsort(x, axis=1, kind="stable") if isinstance(x, np.ndarray) else x.argsort(dim=1, stable=True)


def _take_rows(x, idx):
    """``x``'s entries at ``idx`` along axis 1 (broadcast), in either namespace."""
    return np.take_along_axis(x, idx, 1) if isinstance(x, np.ndarray) else x.take_along_dim(idx, 1)


def assign_lines(raycaster: PlaneRaycaster, corners, lines2d, cam_from_world, camera, pixels=None, line_idx=None,
                 dist_reduce: str = "max", exclusive: bool = False):
    """Assign detected lines to plane edges through the pixels of their 1-pixel regions.

    Args:
        raycaster: built on ``corners``.
        corners: :math:`(K, 4, 3)`.
        lines2d: :math:`(N, 4)` detected segments of this view.
        pixels, line_idx: region pixels (P, 2) and their line (P,); all region pixels when None.

    Returns:
        dict of arrays over the P' pixels whose ray hit a plane: ``pixel`` (P', 2), ``line`` (P',),
        ``plane`` (P',), ``edge`` (P',), ``angle`` (P',), ``dist`` (P',), ``depth`` (P',) ray distance.
    """
    if pixels is None:
        pixels, line_idx = line_regions(lines2d, camera.width, camera.height, exclusive=exclusive)
    o, d = pixel_rays_world(pixels, cam_from_world, camera)
    plane, dist_ray = raycaster.first_hit(o, d)
    hit = plane >= 0
    pixels, line_idx, plane, dist_ray = pixels[hit], line_idx[hit], plane[hit], dist_ray[hit]
    edge, ang, dmax, _ = best_edges(corners, plane, np.asarray(lines2d).reshape(-1, 4)[line_idx], cam_from_world, camera,
                                    dist_reduce)
    return {"pixel": pixels, "line": line_idx, "plane": plane, "edge": edge, "angle": ang, "dist": dmax, "depth": dist_ray}


def _rect_frames(corners):
    """Per rectangle (torch, no grad): corner v3, unit axes X (v4 -> v1) and Y (v2 -> v1), their lengths, the normal."""
    import torch

    v1, v2, v3, v4 = corners.detach().unbind(1)
    ex, ey = v1 - v4, v1 - v2  # full-length x and y edge vectors
    lx, ly = ex.norm(dim=-1).clamp_min(1e-12), ey.norm(dim=-1).clamp_min(1e-12)
    X, Y = ex / lx[:, None], ey / ly[:, None]
    return v3, X, Y, lx, ly, torch.linalg.cross(X, Y)


def _ray_rect_t(v3, X, Y, lx, ly, n, o, d):
    """Ray parameters t (any matching leading shape) of rays o + t d on the rectangles (hard borders): inf where the
    ray misses the rectangle or meets its plane behind the origin."""
    import torch

    denom = (d * n).sum(-1)
    safe = torch.where(denom.abs() > 1e-12, denom, torch.full_like(denom, 1e-12))
    t = ((v3 - o) * n).sum(-1) / safe
    rel = o + t[..., None] * d - v3
    u, w = (rel * X).sum(-1), (rel * Y).sum(-1)
    ok = (t > 1e-6) & (denom.abs() > 1e-12) & (u >= 0) & (u <= lx) & (w >= 0) & (w <= ly)
    return torch.where(ok, t, torch.full_like(t, float("inf")))


def first_hit_torch(corners, origins, dirs, chunk: int = 2048):
    """First-hit ray casting against rectangles, brute force in torch (no grad; CPU or CUDA).

    The twin of :class:`PlaneRaycaster` for the few hundred rays sampled per training iteration,
    where building a BVH each iteration would cost more than testing every plane.

    Args:
        corners: :math:`(K, 4, 3)` tensor; origins, dirs: :math:`(P, 3)` tensors (dirs unit).

    Returns:
        plane index :math:`(P,)` long (-1 miss) and hit distance :math:`(P,)` (inf miss).
    """
    import torch

    with torch.no_grad():
        frames = [f[None] for f in _rect_frames(corners)]  # (1, K, ...)
        P = len(origins)
        best_t = torch.full((P,), float("inf"), dtype=corners.dtype, device=corners.device)
        best_k = torch.full((P,), -1, dtype=torch.long, device=corners.device)
        for s in range(0, P if len(corners) else 0, chunk):
            t = _ray_rect_t(*frames, origins[s : s + chunk, None], dirs[s : s + chunk, None])  # (p, K)
            best_k[s : s + chunk], best_t[s : s + chunk] = _nearest(t)
        return best_k, best_t


def _nearest(t, planes=None):
    """Per row of ray parameters ``t`` (P, M), the plane of the least finite one (the earliest column at a tie, as
    the Warp kernel keeps it) and that parameter: (P,) long (-1 where none), (P,). ``planes`` (P, M): the plane of
    each column (None: the column is the plane)."""
    import torch

    tmin, j = t.min(dim=1)
    k = j if planes is None else planes.gather(1, j[:, None])[:, 0]
    return torch.where(torch.isfinite(tmin), k, torch.full_like(k, -1)), tmin


def _hit_backend(backend, corners) -> str:
    """``"warp"`` (:mod:`lipmap.planes.raycast_warp`) or ``"torch"`` for casting rays on ``corners``: the renderer's
    choice (:func:`lipmap.planes.render.resolve_backend`, ``LIPMAP_RENDER_BACKEND``)."""
    from ..planes.render import resolve_backend

    return resolve_backend(backend, corners.device, corners.dtype, 1)


def first_hit(corners, origins, dirs, backend=None):
    """The first rectangle (hard borders) each ray meets: :math:`(P,)` long, -1 where none. The Warp kernel where it
    runs (one thread per ray), else :func:`first_hit_torch`; ``backend`` as the renderer's."""
    return first_hit_in_render(corners, None, origins, dirs, None, backend)


def first_hit_in_render(corners, candidates, origins, dirs, complete, backend=None):
    """The first rectangle (hard borders) each ray meets, among the planes a render composited along it.

    A render lists, nearest first, the planes whose splat weight along a pixel's ray exceeds its threshold; inside
    its rectangle the weight is 1, so the nearest rectangle the ray meets is in the list whenever the list was not
    cut (by its length, or by the transmittance). Rays whose list may have been cut and holds no rectangle the ray
    meets are cast against every plane (:func:`first_hit_torch`).

    Args:
        corners: :math:`(K, 4, 3)` tensor; candidates: :math:`(P, M)` long, the render's hits (-1 padded), or None
            (every ray against every plane, :func:`first_hit`); origins, dirs: :math:`(P, 3)` world rays (dirs unit);
            complete: :math:`(P,)` bool, the lists not cut (None with ``candidates`` None).

    Returns:
        plane index :math:`(P,)` long (-1 miss).

    ``backend`` as the renderer's: ``"warp"`` runs :func:`lipmap.planes.raycast_warp.first_hit`, the fused twin of
    the torch code below.
    """
    import torch

    with torch.no_grad():
        if _hit_backend(backend, corners) == "warp":
            from ..planes import raycast_warp

            return raycast_warp.first_hit(_rect_frames(corners), origins, dirs, candidates, complete)
        if candidates is None:
            return first_hit_torch(corners, origins, dirs)[0]
        k = candidates.clamp(min=0)
        t = _ray_rect_t(*(f[k] for f in _rect_frames(corners)), origins[:, None], dirs[:, None])  # (P, M)
        first, tmin = _nearest(torch.where(candidates >= 0, t, torch.full_like(t, float("inf"))), candidates)
        redo = ~torch.isfinite(tmin) & ~complete
        if bool(redo.any()):
            first[redo] = first_hit_torch(corners, origins[redo], dirs[redo])[0]
        return first


def visible_lines(lines3d: np.ndarray, cam_from_world: np.ndarray, camera, caster: "PlaneRaycaster | None" = None,
                  tol: float = 0.05) -> np.ndarray:
    """Indices of 3D lines in front of the camera, inside the image and not hidden by the planes.

    A line counts as visible when at least two of its endpoints and midpoint are not occluded: the
    first plane hit on the ray towards the point lies no nearer than the point (minus ``tol`` metres
    and 2 % of the distance). Without ``caster`` only the frustum test is made.

    Args:
        lines3d: :math:`(N, 2, 3)` world segments; caster: the planes' :class:`PlaneRaycaster`.

    Returns:
        int array of indices into ``lines3d``.
    """
    lines3d = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    proj, valid = geo.project_segments(lines3d, cam_from_world, camera)
    idx = np.flatnonzero(valid & geo.segments_in_image(proj, camera.width, camera.height))
    if caster is None or len(idx) == 0:
        return idx
    T = np.asarray(cam_from_world, dtype=float)
    C = -T[:3, :3].T @ T[:3, 3]

    def unoccluded(pts):
        vec = pts - C
        dist = np.linalg.norm(vec, axis=-1)
        d = vec / np.maximum(dist[..., None], 1e-9)
        hit = caster.hit_distance(np.broadcast_to(C, d.shape).copy(), d)
        return hit >= dist - tol - 0.02 * dist

    # the midpoint decides only where the endpoints disagree: a third fewer rays, the same answer
    seg = lines3d[idx]
    n_unocc = unoccluded(seg[:, 0]).astype(np.int64) + unoccluded(seg[:, 1])
    split = np.flatnonzero(n_unocc == 1)
    n_unocc[split] += unoccluded(seg[split, 0] + 0.5 * (seg[split, 1] - seg[split, 0]))
    return idx[n_unocc >= 2]


class LineVisibility:
    """3D lines and their planes' raycaster, for repeated visibility tests from many cameras."""

    def __init__(self, lines3d: np.ndarray, corners: np.ndarray | None = None):
        self.lines = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
        self.caster = PlaneRaycaster(corners) if corners is not None and len(corners) else None

    def visible_lines(self, cam_from_world, camera, tol: float = 0.05) -> np.ndarray:
        return visible_lines(self.lines, cam_from_world, camera, self.caster, tol)
