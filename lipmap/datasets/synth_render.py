"""Ray-cast renderer for the synthetic rooms: RGB (supersampled), z-depth and normals per view.

Rays go through pixel centres in COLMAP's convention (pixel (i, j) is centred at (i + 0.5, j + 0.5)).
Embree (through trimesh) only says which triangle a ray hits; the hit distance is then recomputed in
float64 against that triangle's plane, so depth is exact to double precision, not embree's float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..scene import Camera
from .synth_room import Room
from .synth_textures import TextureAtlas, make_texture

# Two directional lights + ambient: each of the six axis-aligned face orientations gets its own
# brightness, so the edge between two plain faces of different orientation stays visible.
_AMBIENT = 0.55
_LIGHTS = (  # (direction towards the light, intensity)
    (np.array([0.45, 0.25, 0.86]), 0.4),
    (np.array([-0.55, 0.7, 0.3]), 0.25),
)


@dataclass
class RenderScene:
    """A room ready to ray cast: mesh, embree intersector, per-surface planes and textures."""

    room: Room
    mesh: trimesh.Trimesh
    face_surface: np.ndarray  # (F,) surface id per triangle
    normals: np.ndarray  # (S, 3) outward unit normal per surface
    origins: np.ndarray  # (S, 3)
    u_axes: np.ndarray  # (S, 3)
    v_axes: np.ndarray  # (S, 3)
    plain: np.ndarray  # (S,) bool
    plain_color: np.ndarray  # (S, 3) albedo of plain surfaces
    atlas: TextureAtlas  # the textures of the non-plain surfaces
    texels_per_m: float
    intersector: object

    @classmethod
    def build(cls, room: Room, texels_per_m: float, rng: np.random.Generator) -> "RenderScene":
        mesh, face_surface = room.to_mesh()
        surfs = room.surfaces
        textures = []
        for s in surfs:
            textures.append(None if s.material.plain else make_texture(s.material, s.size, texels_per_m, rng))
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        except ImportError as e:  # pragma: no cover - embreex is a declared dependency
            raise ImportError("the synthetic renderer needs embreex (pip install embreex)") from e
        return cls(
            room=room,
            mesh=mesh,
            face_surface=face_surface,
            normals=np.array([s.normal for s in surfs]),
            origins=np.array([s.origin for s in surfs]),
            u_axes=np.array([s.u_axis for s in surfs]),
            v_axes=np.array([s.v_axis for s in surfs]),
            plain=np.array([s.material.plain for s in surfs]),
            plain_color=np.array([s.material.color for s in surfs], dtype=np.float32),
            atlas=TextureAtlas(textures, texels_per_m),
            texels_per_m=float(texels_per_m),
            intersector=RayMeshIntersector(mesh, scale_to_box=False),
        )

    def cast(self, center: np.ndarray, dirs_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays ``center + t * dirs_world`` (N, 3).

        Returns:
            surface id (N,) int, -1 for a miss; ``t`` (N,) float64 along the unnormalised direction
            (with camera-frame directions of z = 1 this is the z-depth), 0 for a miss.
        """
        n = len(dirs_world)
        tri, ray = self.intersector.intersects_id(np.broadcast_to(center, (n, 3)), dirs_world,
                                                  multiple_hits=False, return_locations=False)
        sid = np.full(n, -1, np.int64)
        sid[ray] = self.face_surface[tri]
        t = np.zeros(n)
        hit = sid >= 0
        nrm = self.normals[sid[hit]]
        denom = np.einsum("ij,ij->i", nrm, dirs_world[hit])
        num = np.einsum("ij,ij->i", nrm, self.origins[sid[hit]] - center)
        with np.errstate(divide="ignore", invalid="ignore"):
            t[hit] = num / denom
        bad = ~np.isfinite(t) | (t <= 0)
        sid[bad], t[bad] = -1, 0.0
        return sid, t

    def shade(self, center, dirs_world, sid, t, pixel_angle: float) -> np.ndarray:
        """Lambertian colour (N, 3) in [0, 1] of the hits (``sid``, ``t``) of rays ``dirs_world``."""
        out = np.zeros((len(sid), 3), np.float32)
        hit = np.flatnonzero(sid >= 0)
        if len(hit) == 0:
            return out
        s = sid[hit]
        d = dirs_world[hit]
        # light the side the camera sees: both sides' brightness per surface, picked by the ray
        front = np.full(len(self.normals), _AMBIENT)
        back = front.copy()
        for ldir, k in _LIGHTS:
            cosl = self.normals @ (ldir / np.linalg.norm(ldir))
            front += k * np.clip(cosl, 0, None)
            back += k * np.clip(-cosl, 0, None)
        dn = np.einsum("ij,ij->i", np.take(self.normals, s, axis=0), d)
        light = np.where(dn > 0, np.take(back, s), np.take(front, s)).astype(np.float32)
        albedo = np.take(self.plain_color, s, axis=0)
        textured = np.flatnonzero(~self.plain[s])
        if len(textured):
            st = s[textured]
            dt, tt = d[textured], t[hit[textured]]
            # (u, v) of the hit = (center - origin) . axis + t * (d . axis); the first term per surface.
        # np.take: several times faster than fancy indexing for these row gathers
            rel = center - self.origins
            uv = []
            for axes in (self.u_axes, self.v_axes):
                at = np.take(axes, st, axis=0)
                uv.append(np.take((rel * axes).sum(1), st) + tt * np.einsum("ij,ij->i", dt, at))
            u, v = uv
            dnorm = np.sqrt(np.einsum("ij,ij->i", dt, dt))
            cos = np.abs(dn[textured]) / dnorm
            footprint = tt * dnorm * pixel_angle / np.sqrt(np.maximum(cos, 0.05)) * self.texels_per_m
            lod = np.log2(np.maximum(footprint, 1e-6))
            albedo[textured] = self.atlas.sample(st, u, v, lod)
        out[hit] = albedo * light[:, None]
        return out


def render_view(scene: RenderScene, camera: Camera, cam_from_world: np.ndarray, supersample: int = 2,
                noise_sigma: float = 0.0, rng: np.random.Generator | None = None):
    """Render one view.

    Args:
        camera: pinhole intrinsics (COLMAP pixel convention).
        cam_from_world: (4, 4) x_cam = R x_world + t; the camera looks along +z, x right, y down.
        supersample: colour uses ``supersample``**2 rays per pixel (anti-aliased edges); depth and
            normals come from the single ray through the pixel centre.
        noise_sigma: std of Gaussian noise added to the 8-bit colour (drawn from ``rng``).

    Returns:
        rgb (H, W, 3) uint8, depth (H, W) float64 z-depth in metres (0 = no hit), normals (H, W, 3)
        float32 camera-frame unit normals facing the camera (0 = no hit), surface ids (H, W) int64 (-1 = no hit).
    """
    R = cam_from_world[:3, :3]
    center = -R.T @ cam_from_world[:3, 3]
    W, H = camera.width, camera.height

    rays = camera.pixel_rays().reshape(-1, 3)  # z = 1: the hit parameter t is the z-depth
    dirs = rays @ R  # = (R^T rays^T)^T, camera -> world
    sid, depth = scene.cast(center, dirs)
    nrm = scene.normals[np.maximum(sid, 0)]
    nrm = np.where((np.einsum("ij,ij->i", nrm, dirs) > 0)[:, None], -nrm, nrm)
    nrm_cam = (nrm @ R.T).astype(np.float32)
    nrm_cam[sid < 0] = 0

    k = supersample
    offs = (np.arange(k) + 0.5) / k - 0.5  # sub-pixel offsets around the pixel centre
    pixel_angle = 1.0 / (np.sqrt(camera.fx * camera.fy) * k)
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    sub = np.broadcast_to(rays, (k * k, H * W, 3)).copy()
    sub[..., 0] += ox.reshape(-1, 1) / camera.fx
    sub[..., 1] += oy.reshape(-1, 1) / camera.fy
    sdirs = sub.reshape(-1, 3) @ R
    ssid, st = scene.cast(center, sdirs)
    acc = scene.shade(center, sdirs, ssid, st, pixel_angle).reshape(k * k, H * W, 3).sum(0)
    rgb = acc / (k * k) * 255.0
    if noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        rgb = rgb + rng.normal(0.0, noise_sigma, rgb.shape).astype(np.float32)
    rgb = np.clip(np.round(rgb), 0, 255).astype(np.uint8).reshape(H, W, 3)
    return rgb, depth.reshape(H, W), nrm_cam.reshape(H, W, 3), sid.reshape(H, W)
