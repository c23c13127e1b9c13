"""Plane initialization: fuse the mapping views' depth into a mesh, decimate, one plane per face.

Reference-code facts (docs/design.md): TSDF fusion (~1 cm voxels), decimation to N faces (2000 by
default), one plane per face with centre = face centroid, normal = mean vertex normal and all
four radii = 0.3 x the mean centroid-to-vertex distance.

The TSDF is a dense grid fused in torch (no open3d); the surface is extracted with
``skimage.measure.marching_cubes`` on observed voxels only, and decimated with
``fast_simplification`` (quadric edge collapse).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple, Optional

import numpy as np
import torch

from .. import logger
from ..errors import InputError
from .primitives import R_MAX, R_MIN, Planes


@dataclass
class PlaneInitConfig:
    n_planes: int = 2000  # faces after decimation = planes
    voxel_size: float = 0.02  # metres; the reference uses ~1 cm (use 0.01 for the paper preset)
    trunc_voxels: float = 4.0  # TSDF truncation distance in voxels
    depth_downscale: int = 1  # fuse depth at 1 / this resolution; 0 = auto (the cost is per voxel, not per pixel)
    target_width: int = 160  # with depth_downscale = 0: the integer factor bringing the width closest to this
    max_depth: float = 6.0  # metres; farther depth is ignored (sensor noise grows with depth^2)
    bounds_percentile: float = 0.5  # scene box = [p, 100 - p] percentiles of the fused points, plus a margin
    max_voxels: int = 40_000_000  # coarsen the voxels if the scene box would need more
    max_frames: int = 200  # fuse at most this many views, evenly spread (0 = all): the init needs coverage, not every frame
    radius_scale: float = 0.3  # plane radius = this x mean centroid-to-vertex distance
    min_component_faces: int = 20  # drop isolated mesh fragments smaller than this before decimating
    manhattan: bool = False  # in-plane axes from the scene's dominant directions (else the world axes)

    def to_dict(self) -> dict:
        return asdict(self)


def resize_nearest(a: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize sampling each output pixel centre (COLMAP convention; never mixes depths)."""
    H, W = a.shape[:2]
    if (W, H) == (width, height):
        return a
    cols = np.minimum(((np.arange(width) + 0.5) * W / width).astype(np.int64), W - 1)
    rows = np.minimum(((np.arange(height) + 0.5) * H / height).astype(np.int64), H - 1)
    return a[rows[:, None], cols[None, :]]


class DepthFrame(NamedTuple):
    view: object  # lipmap.scene.View
    camera: object  # lipmap.scene.Camera of ``depth`` (the view's camera, possibly scaled)
    cam_from_world: np.ndarray  # (4, 4)
    depth: np.ndarray  # (h, w) float32 metres, 0 = invalid


def auto_downscale(width: int, target_width: int) -> int:
    """The integer factor that brings ``width`` closest to ``target_width`` (>= 1)."""
    return max(1, int(round(width / max(target_width, 1))))


def working_downscale(downscale: int, width: int, target_width: int) -> int:
    """``downscale``, or for 0 the :func:`auto_downscale` of ``width`` towards ``target_width``."""
    return downscale or auto_downscale(width, target_width)


def downscale_frames(frames: list, downscale: int, target_width: int = 160) -> list:
    """The same frames with depth resized to 1 / downscale (nearest sampling; 0 = auto, see :func:`auto_downscale`)."""
    out = []
    for f in frames:
        ds = working_downscale(downscale, f.camera.width, target_width)
        if ds <= 1:
            out.append(f)
            continue
        cam = f.camera.scaled(1.0 / ds)
        out.append(f._replace(camera=cam, depth=resize_nearest(f.depth, cam.width, cam.height)))
    return out


def _load_frame(v, downscale: int = 1, target_width: int = 160) -> Optional[DepthFrame]:
    """The :class:`DepthFrame` of one view at 1 / downscale (0 = auto), or None without depth or pose."""
    if v.depth_path is None or v.cam_from_world is None:
        return None
    depth = v.load_depth()
    cam = v.camera
    ds = working_downscale(downscale, cam.width, target_width)
    if ds > 1:
        cam = cam.scaled(1.0 / ds)
        depth = resize_nearest(depth, cam.width, cam.height)
    return DepthFrame(v, cam, np.asarray(v.cam_from_world, dtype=np.float64), depth.astype(np.float32))


def depth_frames(views, downscale: int = 1) -> list:
    """One :class:`DepthFrame` per view that has a pose and a depth map, all loaded now.

    Depth is the registered depth (colour camera), resized by nearest sampling to 1 / downscale.
    Views without depth or pose are skipped with a warning. :class:`LazyDepthFrames` is the same
    sequence loaded on access, for scenes whose depth does not fit in memory.
    """
    frames = []
    for v in views:
        f = _load_frame(v, max(downscale, 1))
        if f is None:
            logger.warning("view %s has no depth or no pose; skipped", v.name)
            continue
        frames.append(f)
    return frames


class LazyDepthFrames:
    """The :class:`DepthFrame` sequence of ``views`` (those with depth and a pose), each loaded when accessed
    and not kept: memory stays that of one frame whatever the number of views."""

    def __init__(self, views, downscale: int = 1, target_width: int = 160):
        self.views = [v for v in views if v.depth_path is not None and v.cam_from_world is not None]
        self.downscale, self.target_width = downscale, target_width

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> DepthFrame:
        return _load_frame(self.views[i], self.downscale, self.target_width)

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def fuse_tsdf(frames, conf: PlaneInitConfig, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Fuse depth frames (a sequence of :class:`DepthFrame`, e.g. :func:`depth_frames` or :class:`LazyDepthFrames`)
    into a TSDF and extract its zero surface.

    Memory is bounded by ``conf.max_voxels`` (the grid) and one frame; each frame updates only the voxels of
    its view frustum's bounding box, so time grows with the frames' frusta, not frames x grid.

    Returns:
        **vertices** :math:`(V, 3)` world metres and **faces** :math:`(F, 3)` int64.
    """
    device = torch.device(device or "cpu")
    used, pts = _bounds_sample(frames, conf)
    if not used:
        raise InputError("no view has valid depth and a pose: cannot fuse depth")
    lo, voxel, trunc, dims = _tsdf_volume(np.concatenate(pts), conf)
    logger.info("plane init: TSDF %s voxels of %.3f m over %d views", "x".join(map(str, dims)), voxel, len(used))
    tsdf, weight = _integrate_tsdf((frames[i] for i in used), conf, lo, voxel, trunc, dims, device)
    return _tsdf_surface(tsdf, weight, dims, voxel, lo)


def _clean_depth(depth: np.ndarray, conf: PlaneInitConfig) -> np.ndarray:
    return np.where(np.isfinite(depth) & (depth > 0) & (depth <= conf.max_depth), depth, 0).astype(np.float32)


def _bounds_sample(frames, conf: PlaneInitConfig) -> tuple[list, list]:
    """Indices of the frames with usable depth and a subsample of their world points (for the grid's box)."""
    # 20,000 points per frame up to 100 frames, then a total of 2 million: the box of a 7,000-frame scene
    # fits in ~50 MB
    per_frame = max(1000, min(20000, 2_000_000 // max(len(frames), 1)))
    used, pts = [], []
    for i in range(len(frames)):
        _, cam, T, depth = frames[i]
        depth = _clean_depth(depth, conf)
        if not (depth > 0).any():
            continue
        used.append(i)
        X = cam.pixel_rays()[depth > 0] * depth[depth > 0, None]
        sub = X[:: max(1, len(X) // per_frame)]
        pts.append((sub - T[:3, 3]) @ T[:3, :3])  # world = R^T (x - t)
    return used, pts


def _tsdf_volume(pts: np.ndarray, conf: PlaneInitConfig):
    """Grid origin, voxel size (coarsened to stay under max_voxels), truncation and dims over the points' bounds."""
    p = conf.bounds_percentile
    lo, hi = np.percentile(pts, p, axis=0), np.percentile(pts, 100 - p, axis=0)
    voxel = float(conf.voxel_size)
    trunc = conf.trunc_voxels * voxel
    lo, hi = lo - 2 * trunc, hi + 2 * trunc
    while np.prod(np.ceil((hi - lo) / voxel) + 1) > conf.max_voxels:
        voxel *= 1.25
        trunc = conf.trunc_voxels * voxel
    if voxel != conf.voxel_size:
        logger.info("plane init: voxels coarsened to %.3f m to stay under %d voxels", voxel, conf.max_voxels)
    dims = (np.ceil((hi - lo) / voxel) + 1).astype(int)
    return lo, voxel, trunc, dims


SLAB_VOXELS = 2_000_000  # voxels projected at once: bounds the temporaries of one frame's update


def _integrate_tsdf(frames, conf: PlaneInitConfig, lo, voxel: float, trunc: float, dims, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Fuse every frame into a dense grid; returns the flat TSDF and observation weight per voxel."""
    f32 = dict(dtype=torch.float32, device=device)
    axes = [torch.arange(d, **f32) * voxel + float(lo[i]) for i, d in enumerate(dims)]
    tsdf = torch.ones(int(np.prod(dims)), **f32)
    weight = torch.zeros(int(np.prod(dims)), **f32)
    for _, cam, T, depth in frames:
        depth = _clean_depth(depth, conf)
        box = _frustum_box(cam, T, float(depth.max()) + trunc, lo, voxel, dims)
        if box is None:
            continue
        (x0, x1), (y0, y1), (z0, z1) = box
        step = max(1, SLAB_VOXELS // ((y1 - y0) * (z1 - z0)))
        d = torch.as_tensor(depth, **f32)
        for xa in range(x0, x1, step):
            xb = min(xa + step, x1)
            sub = torch.stack(torch.meshgrid(axes[0][xa:xb], axes[1][y0:y1], axes[2][z0:z1], indexing="ij"), -1).reshape(-1, 3)
            ii = torch.arange(xa, xb, device=device)[:, None, None] * (dims[1] * dims[2])
            jj = torch.arange(y0, y1, device=device)[None, :, None] * dims[2]
            kk = torch.arange(z0, z1, device=device)[None, None, :]
            _integrate_frame(sub, (ii + jj + kk).reshape(-1), tsdf, weight, cam, T, d, trunc)
    return tsdf, weight


def _frustum_box(cam, T, far: float, lo, voxel: float, dims):
    """Index ranges ((x0, x1), (y0, y1), (z0, z1)) of the grid voxels inside the bounding box of the view's
    frustum up to depth ``far`` (the apex and the four image corners there), or None when it misses the grid."""
    if not far > 0:
        return None
    R, t = T[:3, :3], T[:3, 3]
    corners = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], dtype=float)
    rays = np.stack([(corners[:, 0] - cam.cx) / cam.fx, (corners[:, 1] - cam.cy) / cam.fy, np.ones(4)], 1) * far
    pts = np.concatenate([np.zeros((1, 3)), rays]) - t
    world = pts @ R  # R^T (x - t), row-wise
    a = np.floor((world.min(0) - lo) / voxel).astype(int) - 1
    b = np.ceil((world.max(0) - lo) / voxel).astype(int) + 2
    a, b = np.maximum(a, 0), np.minimum(b, dims)
    if np.any(b <= a):
        return None
    return tuple((int(a[i]), int(b[i])) for i in range(3))


def _integrate_frame(grid: torch.Tensor, flat: torch.Tensor, tsdf: torch.Tensor, weight: torch.Tensor, cam, T,
                     depth: torch.Tensor, trunc: float):
    """Average one frame's truncated signed distances into ``tsdf`` / ``weight`` (in place) at the voxels
    ``flat`` whose centres are ``grid`` (n, 3)."""
    f32 = dict(dtype=torch.float32, device=grid.device)
    Tt = torch.as_tensor(T, **f32)
    Xc = grid @ Tt[:3, :3].T + Tt[:3, 3]
    z = Xc[:, 2]
    zs = z.clamp(min=1e-6)
    # continuous pixel coordinates with pixel centres at integers (COLMAP centre = +0.5)
    u = cam.fx * Xc[:, 0] / zs + cam.cx - 0.5
    v = cam.fy * Xc[:, 1] / zs + cam.cy - 0.5
    inside = (z > 1e-3) & (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
    idx = inside.nonzero().squeeze(1)
    d = _sample_depth(depth, u[idx], v[idx])
    sdf = d - z[idx]
    # voxels far behind the surface stay unobserved, so no false surface appears there
    upd = (d > 0) & (sdf >= -trunc)
    idx, sdf = flat[idx[upd]], sdf[upd]
    val = (sdf / trunc).clamp(max=1.0)
    w_old = weight[idx]
    tsdf[idx] = (tsdf[idx] * w_old + val) / (w_old + 1)
    weight[idx] = w_old + 1


def _tsdf_surface(tsdf: torch.Tensor, weight: torch.Tensor, dims, voxel: float, lo) -> tuple[np.ndarray, np.ndarray]:
    """Zero surface of the TSDF over fully observed cubes: world vertices (V, 3) and faces (F, 3)."""
    from skimage.measure import marching_cubes

    vol = tsdf.reshape(*dims).cpu().numpy()
    obs = (weight > 0).reshape(*dims).cpu().numpy()
    mask = _observed_cubes_mask(obs, dims)
    if not ((vol < 0) & mask).any() or not ((vol > 0) & mask).any():
        raise InputError("the fused depth holds no surface (TSDF has no zero crossing)")
    verts, faces, _, _ = marching_cubes(vol, level=0.0, mask=mask)
    verts = verts * voxel + lo
    return verts.astype(np.float64), faces.astype(np.int64)


def _observed_cubes_mask(obs: np.ndarray, dims) -> np.ndarray:
    """marching_cubes mask admitting only cubes whose 8 corners are all observed."""
    # require all 8 corners of a cube observed, or the step from the band behind a surface (-1)
    # to never-observed voxels (+1) makes false walls; skimage (0.26, checked by the tests) reads
    # the mask of cube [i, i+1] at its far corner i+1
    mask = np.zeros_like(obs)
    c = obs[:-1, :-1, :-1].copy()
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                c &= obs[dx : dims[0] - 1 + dx, dy : dims[1] - 1 + dy, dz : dims[2] - 1 + dz]
    mask[1:, 1:, 1:] = c
    return mask


def _sample_depth(depth: torch.Tensor, u: torch.Tensor, v: torch.Tensor, max_rel_spread: float = 0.05) -> torch.Tensor:
    """Bilinear depth at (u, v) (pixel centres at integers), nearest where the 4 neighbours are not
    all valid or straddle a depth discontinuity (spread > max_rel_spread x depth); 0 = invalid."""
    H, W = depth.shape
    u0 = u.floor().long().clamp(0, W - 1)
    v0 = v.floor().long().clamp(0, H - 1)
    u1, v1 = (u0 + 1).clamp(max=W - 1), (v0 + 1).clamp(max=H - 1)
    a, b = u - u0, v - v0
    flat = depth.reshape(-1)
    d00, d01 = flat[v0 * W + u0], flat[v0 * W + u1]
    d10, d11 = flat[v1 * W + u0], flat[v1 * W + u1]
    q = torch.stack([d00, d01, d10, d11], 1)
    lo, hi = q.amin(1), q.amax(1)
    bil = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    near = flat[v.round().long().clamp(0, H - 1) * W + u.round().long().clamp(0, W - 1)]
    smooth = (lo > 0) & (hi - lo <= max_rel_spread * lo)
    return torch.where(smooth, bil, near)


def decimate(vertices: np.ndarray, faces: np.ndarray, n_faces: int, min_component_faces: int = 0):
    """Quadric decimation to about ``n_faces`` faces; small fragments removed first. Returns (V, F)."""
    import fast_simplification
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if min_component_faces > 0 and len(mesh.faces) > n_faces:
        comps = trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)))
        keep = np.concatenate([c for c in comps if len(c) >= min_component_faces] or [np.arange(len(mesh.faces))])
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[np.sort(keep)], process=True)
    V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    area = float(mesh.area)

    def fqms(V, F):
        # one pass often stalls above the target on TSDF meshes; a few more passes get further
        for _ in range(6):
            if len(F) <= 1.05 * n_faces:
                break
            n0 = len(F)
            V, F = fast_simplification.simplify(V, F.astype(np.int32), target_count=int(n_faces))
            if len(F) >= 0.99 * n0:
                break
        return V, np.asarray(F, np.int64)

    V, F = fqms(V, F)
    # still stalled (collapses at sharp creases would flip the chamfer faces marching cubes puts
    # there): cluster vertices on a grid about the target face size, then collapse again
    cell = 0.25 * np.sqrt(area / max(n_faces, 1))
    for _ in range(4):
        if len(F) <= 1.2 * n_faces:
            break
        V, F = _cluster_vertices(V, F, cell)
        V, F = fqms(V, F)
        cell *= 1.5
    mesh = trimesh.Trimesh(V, F, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _cluster_vertices(V: np.ndarray, F: np.ndarray, cell: float):
    """Vertex clustering: merge the vertices of each grid cell into their mean; drop collapsed faces."""
    key = np.floor(V / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = inv.max() + 1
    Vn = np.zeros((n, 3))
    np.add.at(Vn, inv, V)
    Vn /= np.bincount(inv, minlength=n)[:, None]
    Fn = inv[F]
    ok = (Fn[:, 0] != Fn[:, 1]) & (Fn[:, 1] != Fn[:, 2]) & (Fn[:, 0] != Fn[:, 2])
    Fn = np.unique(np.sort(Fn[ok], axis=1), axis=0, return_index=True)[1]
    return Vn, inv[F][ok][np.sort(Fn)]


def manhattan_frame(normals: np.ndarray, weights: np.ndarray | None = None, tol_deg: float = 10.0) -> np.ndarray:
    """The scene's dominant orthogonal directions (3, 3) (rows) from surface normals (N, 3).

    The first axis is the normal direction (sign-free) with the largest weight within ``tol_deg``;
    the second the same among the normals within ``tol_deg`` of perpendicular to it, made exactly
    orthogonal; the third their cross product. Falls back to the world axes without enough support.
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(n)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    ok = np.isfinite(n).all(1) & (np.linalg.norm(n, axis=1) > 1e-9) & np.isfinite(w)
    n, w = n[ok] / np.linalg.norm(n[ok], axis=1, keepdims=True), w[ok]
    if len(n) < 10:
        return np.eye(3)
    rng = np.random.default_rng(0)
    cand = n[rng.choice(len(n), size=min(len(n), 500), replace=False)]
    cos_tol = np.cos(np.radians(tol_deg))

    def best(c, mask):
        score = ((np.abs(c @ n[mask].T) >= cos_tol) * w[mask]).sum(1)
        i = int(np.argmax(score))
        members = n[mask][np.abs(n[mask] @ c[i]) >= cos_tol]
        members = members * np.sign(members @ c[i])[:, None]
        m = members.mean(0)
        return m / np.linalg.norm(m)

    a1 = best(cand, np.ones(len(n), bool))
    perp = np.abs(n @ a1) <= np.sin(np.radians(tol_deg))
    c2 = cand[np.abs(cand @ a1) <= np.sin(np.radians(tol_deg))]
    if perp.sum() < 10 or len(c2) == 0:
        return np.eye(3)
    a2 = best(c2, perp)
    a2 = a2 - (a2 @ a1) * a1
    a2 /= np.linalg.norm(a2)
    return np.stack([a1, a2, np.cross(a1, a2)])


def planes_from_mesh(vertices: np.ndarray, faces: np.ndarray, radius_scale: float = 0.3, device=None,
                     manhattan: bool = False) -> Planes:
    """One plane per triangle: centroid, mean vertex normal, radii = radius_scale x mean centroid-vertex
    distance; in-plane axes from the mesh's Manhattan frame when ``manhattan``, else the world axes."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    centroid = tri.mean(1)
    vn = np.asarray(mesh.vertex_normals)[mesh.faces].mean(1)
    fn = np.asarray(mesh.face_normals)
    ok = np.linalg.norm(vn, axis=1) > 1e-6
    normal = np.where(ok[:, None], vn, fn)
    radius = radius_scale * np.linalg.norm(tri - centroid[:, None], axis=2).mean(1)
    good = np.isfinite(normal).all(1) & (np.linalg.norm(normal, axis=1) > 1e-6) & np.isfinite(centroid).all(1)
    radius = np.clip(radius, R_MIN * 2, R_MAX)
    frame = manhattan_frame(fn, mesh.area_faces) if manhattan and len(fn) else None
    return Planes.from_normals(centroid[good], normal[good], radius[good], device=device, frame=frame)


def init_planes(views, conf: Optional[PlaneInitConfig] = None, device=None, frames=None) -> Planes:
    """Planes initialized from the views' depth (TSDF -> mesh -> decimation -> one plane per face).

    ``frames`` (a :class:`DepthFrame` sequence at the fusion resolution) may be given instead of ``views``;
    from ``views`` the depth is read one frame at a time (:class:`LazyDepthFrames`), of at most
    ``conf.max_frames`` views evenly spread.
    """
    conf = conf or PlaneInitConfig()
    if frames is None:
        frames = LazyDepthFrames(views, conf.depth_downscale, conf.target_width)  # the views with depth and pose
        n = len(frames.views)
        if conf.max_frames and n > conf.max_frames:
            logger.info("plane init: fusing %d of %d views, evenly spread", conf.max_frames, n)
            frames.views = [frames.views[i] for i in np.unique(np.linspace(0, n - 1, conf.max_frames).round().astype(int))]
    V, F = fuse_tsdf(frames, conf, device=device)
    logger.info("plane init: fused mesh %d vertices, %d faces", len(V), len(F))
    V, F = decimate(V, F, conf.n_planes, conf.min_component_faces)
    planes = planes_from_mesh(V, F, conf.radius_scale, device=device, manhattan=conf.manhattan)
    logger.info("plane init: %d planes (median radius %.3f m)", len(planes), float(planes.radii[:, 0].median()) if len(planes) else 0.0)
    return planes
