"""Procedural synthetic indoor scenes written in the 7-Scenes layout.

``generate_scene(out_root, seed, preset)`` builds a random furnished room (walls, floor, ceiling, a
door and windows with protruding frames, cabinets, shelves with books, desks with legs, sometimes a
short staircase), textures most surfaces procedurally (value noise, wood, tiles, terrazzo, posters)
and leaves some deliberately plain (one wall, cabinet fronts, frames, window glass) where only edges
help. It ray casts a mapping pass (seq-01) and a query pass (seq-02) along two different smooth loops
through the room and writes, like 7-Scenes::

    <out_root>/room-s<seed>/TrainSplit.txt        "sequence1"
    <out_root>/room-s<seed>/TestSplit.txt         "sequence2"
    <out_root>/room-s<seed>/seq-0{1,2}/frame-NNNNNN.color.png   RGB, lossless
                                      frame-NNNNNN.depth.png   uint16 mm z-depth, registered to colour
                                      frame-NNNNNN.normal.png  camera-frame normals (lipmap.imageio)
                                      frame-NNNNNN.pose.txt    4x4 camera-to-world (like 7-Scenes)
    <out_root>/room-s<seed>/mesh.ply              ground-truth mesh (face attribute surface_id)
    <out_root>/room-s<seed>/surfaces.json         the planar rectangles the mesh is made of
    <out_root>/room-s<seed>/scene.json            metadata; written last, it marks the scene complete

Cameras follow OpenCV/COLMAP: they look along +z, x right, y down; the world is z up, floor at z = 0.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import logger
from ..errors import InputError
from ..imageio import atomic_path, write_color, write_depth, write_normals, write_text_atomic
from ..poses import invert_T, make_T
from ..presets import resolve
from ..scene import Camera
from .synth_render import RenderScene, render_view
from .synth_room import Room, build_room

GENERATOR_VERSION = 1


@dataclass(frozen=True)
class SynthConfig:
    """Image size, intrinsics, frame counts and rendering knobs of a synthetic scene."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    n_mapping: int
    n_query: int
    supersample: int = 2  # colour rays per pixel = supersample**2
    texels_per_m: float = 256.0
    noise_sigma: float = 1.0  # per-pixel Gaussian noise, 8-bit units
    clearance: float = 0.6  # camera loop keeps this far (m) from furniture and walls
    min_view_depth: float = 0.5  # no surface closer than this (z-depth, m) in any frame
    # > 0: the depth files are corrupted like a predicted / low-quality depth map (corrupt_depth); the
    # mesh, normals and poses stay exact, so mapping metrics against the mesh show what the error costs
    depth_warp_sigma: float = 0.0

    @property
    def camera(self) -> Camera:
        return Camera(self.width, self.height, (self.fx, self.fy, self.cx, self.cy))


SYNTH_PRESETS = {
    "small": SynthConfig("small", 320, 240, 262.5, 262.5, 160.0, 120.0, n_mapping=30, n_query=20,
                         texels_per_m=256.0),
    "default": SynthConfig("default", 640, 480, 525.0, 525.0, 320.0, 240.0, n_mapping=100, n_query=50,
                           texels_per_m=400.0),
}
# "small" with corrupted depth (2 % smooth per-frame warp + Kinect-like per-pixel noise): the setting of
# the paper's claim that planes average depth error where lifting lines with the depth cannot
SYNTH_PRESETS["small-noisy-depth"] = replace(SYNTH_PRESETS["small"], name="small-noisy-depth", depth_warp_sigma=0.02)


def corrupt_depth(depth: np.ndarray, rng: np.random.Generator, warp_sigma: float, grid=(3, 4)) -> np.ndarray:
    """Exact z-depth -> depth with the errors of a predicted or consumer-sensor depth map.

    Two parts: a smooth multiplicative warp per frame (a ``grid`` of N(0, warp_sigma) relative errors,
    bilinearly upsampled: the low-frequency scale error of monocular depth, different in every view) and
    independent per-pixel axial noise with the Kinect v1 model sigma(z) = 1.2 mm + 1.9 mm * (z - 0.4)^2
    (Nguyen, Izadi & Lovell, 3DIMPVT 2012).

    Args:
        depth: :math:`(H, W)` metres, 0 = no surface (kept 0).
    """
    import cv2

    H, W = depth.shape
    warp = cv2.resize(rng.normal(0.0, warp_sigma, grid), (W, H), interpolation=cv2.INTER_LINEAR)
    axial = 0.0012 + 0.0019 * (depth - 0.4) ** 2
    noisy = depth * (1.0 + warp) + rng.normal(0.0, 1.0, depth.shape) * axial
    return np.where(depth > 0, np.maximum(noisy, 1e-3), 0.0)


def get_config(preset="small") -> SynthConfig:
    """A :class:`SynthConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(preset, SYNTH_PRESETS, "synthetic", default="small")


# ---- trajectories -----------------------------------------------------------------------------------------
def look_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """world_from_cam rotation (3, 3) of a camera looking at heading ``yaw`` (from +x towards +y, rad),
    tilted up by ``pitch`` and rolled by ``roll`` about its optical axis; columns are the camera's
    x (right), y (down), z (forward) axes in the z-up world."""
    fwd = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, fwd], axis=1)


@dataclass(frozen=True)
class _LoopParams:
    center: tuple
    semi_axes: tuple
    theta0: float
    direction: float
    wobble: tuple  # (amplitude, phase) of the radial wobble
    height: tuple  # (mid, amplitude, frequency, phase)
    yaw: tuple  # (amplitude, frequency, phase)
    pitch: tuple  # (mid, amplitude, frequency, phase)
    roll: tuple  # (amplitude, phase)
    query: tuple  # (inward offset mid, amplitude, phase, height amp, phase, yaw amp, phase, pitch amp, phase)


def _free_rect(room: Room, clearance: float) -> tuple[np.ndarray, np.ndarray]:
    Lx, Ly, _ = room.size
    band = [max(b, 0.15) + clearance for b in room.band]
    lo = np.array([band[3], band[0]])
    hi = np.array([Lx - band[1], Ly - band[2]])
    return lo, hi


def _draw_loop(room: Room, cfg: SynthConfig, rng: np.random.Generator, attempt: int) -> _LoopParams:
    lo, hi = _free_rect(room, cfg.clearance)
    center = (lo + hi) / 2
    semi = np.maximum((hi - lo) / 2, 0.05)
    calm = 1.0 / (1.0 + 0.15 * attempt)  # later attempts turn less, so they fail less
    u = rng.uniform
    return _LoopParams(
        center=tuple(center), semi_axes=tuple(semi), theta0=u(0, 2 * np.pi), direction=float(rng.choice([-1.0, 1.0])),
        wobble=(u(0.0, 0.12), u(0, 2 * np.pi)),
        # heights stay in [1.2, 1.7] m, the query offset included
        height=(u(1.42, 1.48), u(0.08, 0.14), float(rng.integers(1, 4)), u(0, 2 * np.pi)),
        yaw=(u(0.3, 0.6) * calm, float(rng.integers(1, 3)), u(0, 2 * np.pi)),
        pitch=(u(-0.3, -0.15), u(0.05, 0.12), float(rng.integers(1, 4)), u(0, 2 * np.pi)),
        roll=(u(0.0, 0.05), u(0, 2 * np.pi)),
        query=(u(0.12, 0.18), u(0.04, 0.08), u(0, 2 * np.pi), u(0.04, 0.08), u(0, 2 * np.pi),
               u(0.04, 0.09), u(0, 2 * np.pi), u(0.03, 0.06), u(0, 2 * np.pi)),
    )


def loop_poses(p: _LoopParams, n: int, query: bool) -> np.ndarray:
    """cam_from_world (n, 4, 4) along the loop; the query loop runs inside the mapping loop, between its
    frames, turned by a few degrees, so each query sees what nearby mapping frames saw."""
    phase = (np.arange(n) + (0.5 if query else 0.0)) / n
    theta = p.theta0 + p.direction * 2 * np.pi * phase
    a, b = p.semi_axes
    r = 1.0 - p.wobble[0] * (0.5 + 0.5 * np.sin(2 * theta + p.wobble[1]))
    xy = np.stack([a * r * np.cos(theta), b * r * np.sin(theta)], -1)
    h = p.height[0] + p.height[1] * np.sin(p.height[2] * theta + p.height[3])
    # look across the room (heading = polar angle + pi) so views hold several objects 2-4 m away, as a
    # hand-held sweep does; the polar angle, not the ellipse normal, because the normal whips round
    # the ends of a long thin loop and would turn tens of degrees between frames
    yaw = theta + np.pi + p.yaw[0] * np.sin(p.yaw[1] * theta + p.yaw[2])
    pitch = p.pitch[0] + p.pitch[1] * np.sin(p.pitch[2] * theta + p.pitch[3])
    roll = p.roll[0] * np.sin(3 * theta + p.roll[1])
    if query:
        q = p.query
        inward = q[0] + q[1] * np.sin(3 * theta + q[2])
        rho = np.linalg.norm(xy, axis=1)
        xy = xy * np.clip(1.0 - inward / np.maximum(rho, 1e-6), -1.0, 1.0)[:, None]
        h = h + q[3] * np.sin(2 * theta + q[4])
        yaw = yaw + q[5] * np.sin(2 * theta + q[6])
        pitch = pitch + q[7] * np.sin(3 * theta + q[8])
    centers = np.concatenate([xy + np.asarray(p.center), h[:, None]], axis=1)
    poses = np.empty((n, 4, 4))
    for i in range(n):
        R_wc = look_rotation(yaw[i], pitch[i], roll[i])
        poses[i] = invert_T(make_T(R_wc, centers[i]))
    return poses


def _check_poses(scene: RenderScene, cfg: SynthConfig, poses: np.ndarray) -> str | None:
    """None if every pose is valid, else why not: inside the room, outside furniture, nothing too close."""
    Lx, Ly, H = scene.room.size
    probe = Camera(32, 24, (cfg.fx / cfg.width * 32, cfg.fy / cfg.height * 24, cfg.cx / cfg.width * 32,
                            cfg.cy / cfg.height * 24))
    rays = probe.pixel_rays().reshape(-1, 3)
    for i, T in enumerate(poses):
        c = -T[:3, :3].T @ T[:3, 3]
        if not (0.3 < c[0] < Lx - 0.3 and 0.3 < c[1] < Ly - 0.3 and 0.3 < c[2] < H - 0.3):
            return f"pose {i} leaves the room"
        for lo, hi, label in scene.room.obstacles:
            if np.all(c > lo - 0.3) and np.all(c < hi + 0.3):
                return f"pose {i} is inside {label}"
        sid, z = scene.cast(c, rays @ T[:3, :3])
        if (sid < 0).any():
            return f"pose {i} sees outside the room"
        if z.min() < cfg.min_view_depth:
            return f"pose {i} is {z.min():.2f} m from a surface"
    return None


def make_trajectories(scene: RenderScene, cfg: SynthConfig, rng: np.random.Generator,
                      max_attempts: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """(mapping cam_from_world (n_mapping, 4, 4), query cam_from_world (n_query, 4, 4))."""
    why = None
    for attempt in range(max_attempts):
        params = _draw_loop(scene.room, cfg, rng, attempt)
        mapping = loop_poses(params, cfg.n_mapping, query=False)
        query = loop_poses(params, cfg.n_query, query=True)
        why = _check_poses(scene, cfg, mapping) or _check_poses(scene, cfg, query)
        if why is None:
            return mapping, query
        logger.debug(f"trajectory attempt {attempt} rejected: {why}")
    raise RuntimeError(f"no valid camera loop in this room after {max_attempts} attempts (last: {why})")


# ---- writing ----------------------------------------------------------------------------------------------
def _pose_text(cam_from_world: np.ndarray) -> str:
    world_from_cam = invert_T(cam_from_world)
    return "".join(" ".join(f"{v: .10e}" for v in row) + "\n" for row in world_from_cam)


def _frame_files(seq_dir: Path, i: int) -> dict:
    stem = seq_dir / f"frame-{i:06d}"
    return {k: Path(f"{stem}.{k}.{ext}") for k, ext in
            (("color", "png"), ("depth", "png"), ("normal", "png"), ("pose", "txt"))}


def _clean(scene_dir: Path):
    """Remove what a previous run of the generator wrote (and only that), completion marker first."""
    for name in ("scene.json", "mesh.ply", "surfaces.json", "TrainSplit.txt", "TestSplit.txt"):
        (scene_dir / name).unlink(missing_ok=True)
    for seq in ("seq-01", "seq-02"):
        for pattern in ("frame-*.color.png", "frame-*.depth.png", "frame-*.normal.png", "frame-*.pose.txt"):
            for f in (scene_dir / seq).glob(pattern):
                f.unlink()


def _surfaces_json(room: Room) -> str:
    """The planar rectangles of the mesh (mesh face f belongs to surface f // 2), one per line."""
    rows = []
    for i, s in enumerate(room.surfaces):
        row = {"id": i, "label": s.label, "object_id": s.object_id, "plain": s.material.plain,
               "material": s.material.kind, "origin": np.round(s.origin, 6).tolist(),
               "u_axis": np.round(s.u_axis, 6).tolist(), "v_axis": np.round(s.v_axis, 6).tolist(),
               "size": [round(s.size[0], 6), round(s.size[1], 6)], "normal": np.round(s.normal, 6).tolist()}
        rows.append(json.dumps(row, separators=(",", ":")))
    return '{"room_size": %s, "surfaces": [\n%s\n]}\n' % (json.dumps(list(room.size)), ",\n".join(rows))


def generate_scene(out_root, seed: int = 0, preset="small", overwrite: bool = False) -> Path:
    """Generate (or find) the synthetic scene ``out_root/room-s<seed>`` and return its folder.

    A scene whose ``scene.json`` exists is complete and is kept unless ``overwrite``; it must have
    been made with the same preset (the name does not record it), else InputError.
    """
    cfg = get_config(preset)
    seed = int(seed)
    if seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed}")
    scene_dir = Path(out_root) / f"room-s{seed}"
    marker = scene_dir / "scene.json"
    if marker.exists() and not overwrite:
        _check_existing_scene(marker, cfg)
        logger.info(f"Skipping synthetic scene {scene_dir}: it exists (overwrite=False).")
        return scene_dir

    t0 = time.perf_counter()
    logger.info(f"Generating synthetic scene {scene_dir} (seed {seed}, preset {cfg.name}).")
    scene_dir.mkdir(parents=True, exist_ok=True)
    _clean(scene_dir)
    room, scene, mapping, query = _build_world(seed, cfg)
    t_build = time.perf_counter() - t0
    plain_pixels, total_pixels = _render_sequences(scene_dir, scene, cfg, seed, mapping, query)
    _write_scene_files(scene_dir, room, scene)
    meta = _scene_meta(cfg, seed, room, scene, plain_pixels, total_pixels)
    write_text_atomic(marker, json.dumps(meta, indent=1) + "\n")
    logger.info(f"Synthetic scene {scene_dir.name}: room {room.size[0]:.2f} x {room.size[1]:.2f} x "
                f"{room.size[2]:.2f} m, {len(room.surfaces)} surfaces, {cfg.n_mapping}+{cfg.n_query} frames "
                f"in {time.perf_counter() - t0:.1f} s (scene {t_build:.1f} s).")
    return scene_dir


def _check_existing_scene(marker: Path, cfg: SynthConfig):
    """Raise InputError unless the complete scene at ``marker`` was made with this preset and generator."""
    try:
        meta = json.loads(marker.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"scene.json is not valid JSON ({e})", marker, hint="pass overwrite=True") from e
    if meta.get("preset") != cfg.name or meta.get("generator_version") != GENERATOR_VERSION:
        raise InputError(f"existing scene was made with preset {meta.get('preset')!r} (generator version "
                         f"{meta.get('generator_version')}), asked for {cfg.name!r} (version {GENERATOR_VERSION})",
                         marker, hint="pass overwrite=True (--overwrite) or another --out")


def _build_world(seed: int, cfg: SynthConfig) -> tuple:
    """The room, its textured render scene and the (mapping, query) camera loops of ``seed``."""
    # independent streams: the room and the camera loops do not depend on the preset's texture size
    ss_room, ss_tex, ss_traj = np.random.SeedSequence(seed).spawn(3)
    room = build_room(np.random.default_rng(ss_room))
    scene = RenderScene.build(room, cfg.texels_per_m, np.random.default_rng(ss_tex))
    mapping, query = make_trajectories(scene, cfg, np.random.default_rng(ss_traj))
    return room, scene, mapping, query


def _render_sequences(scene_dir: Path, scene: RenderScene, cfg: SynthConfig, seed: int, mapping, query) -> tuple:
    """Render and write seq-01 (mapping) and seq-02 (query); returns the mapping frames' (plain, all) pixels."""
    camera = cfg.camera
    plain_pixels = total_pixels = 0
    for seq_idx, (seq, poses) in enumerate((("seq-01", mapping), ("seq-02", query)), start=1):
        seq_dir = scene_dir / seq
        seq_dir.mkdir(exist_ok=True)
        for i, T in enumerate(tqdm(poses, desc=f"render {seq}", leave=False)):
            sid = _render_frame(seq_dir, i, T, scene, camera, cfg, seed, seq_idx)
            if seq_idx == 1:
                plain_pixels += int(scene.plain[sid[sid >= 0]].sum())
                total_pixels += int((sid >= 0).sum())
    return plain_pixels, total_pixels


def _render_frame(seq_dir: Path, i: int, T: np.ndarray, scene: RenderScene, camera: Camera, cfg: SynthConfig,
                  seed: int, seq_idx: int) -> np.ndarray:
    """Render and write frame ``i``'s colour, depth, normals and pose; returns its per-pixel surface ids."""
    # noise seeded per frame, so a frame does not depend on how many were rendered before it
    noise_rng = np.random.default_rng([seed, seq_idx, i])
    rgb, depth, normals, sid = render_view(scene, camera, T, cfg.supersample, cfg.noise_sigma, noise_rng)
    if cfg.depth_warp_sigma > 0:
        depth = corrupt_depth(depth, np.random.default_rng([seed, seq_idx, i, 1]), cfg.depth_warp_sigma)
    files = _frame_files(seq_dir, i)
    write_color(files["color"], rgb)
    write_depth(files["depth"], depth)
    write_normals(files["normal"], normals)
    write_text_atomic(files["pose"], _pose_text(T))
    return sid


def _write_scene_files(scene_dir: Path, room: Room, scene: RenderScene):
    """Write the split files, the ground-truth mesh (with surface ids) and surfaces.json."""
    write_text_atomic(scene_dir / "TrainSplit.txt", "sequence1\n")
    write_text_atomic(scene_dir / "TestSplit.txt", "sequence2\n")
    mesh = scene.mesh.copy()
    mesh.face_attributes["surface_id"] = scene.face_surface.astype(np.int32)
    with atomic_path(scene_dir / "mesh.ply") as tmp:
        mesh.export(tmp, file_type="ply")
    write_text_atomic(scene_dir / "surfaces.json", _surfaces_json(room))


def _scene_meta(cfg: SynthConfig, seed: int, room: Room, scene: RenderScene, plain_pixels: int,
                total_pixels: int) -> dict:
    """The contents of scene.json."""
    areas = np.array([s.area for s in room.surfaces])
    return {
        "dataset": "synthetic",
        "width": cfg.width,
        "height": cfg.height,
        "intrinsics": [cfg.fx, cfg.fy, cfg.cx, cfg.cy],
        "depth_registered": True,
        "seed": seed,
        "preset": cfg.name,
        "n_mapping": cfg.n_mapping,
        "n_query": cfg.n_query,
        # share of the mesh's surface area that is one uniform colour (no texture to match)
        "plain_surface_fraction": round(float(areas[scene.plain].sum() / areas.sum()), 4),
        # share of the mapping frames' pixels that land on such surfaces
        "plain_pixel_fraction": round(plain_pixels / max(total_pixels, 1), 4),
        "room_size": list(room.size),
        "has_stairs": bool(room.has_stairs),
        "n_surfaces": len(room.surfaces),
        "depth_scale": 1000.0,
        "depth_warp_sigma": cfg.depth_warp_sigma,
        "generator_version": GENERATOR_VERSION,
    }


# ---- CLI --------------------------------------------------------------------------------------------------
def add_synth_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("synth", help="generate a procedural synthetic room in the 7-Scenes layout",
                              description=generate_scene.__doc__)
    p.add_argument("--out", type=Path, required=True, help="root folder; the scene goes to OUT/room-s<seed>")
    p.add_argument("--seed", type=int, default=0, help="random seed: the same seed gives identical files")
    p.add_argument("--preset", choices=sorted(SYNTH_PRESETS), default="small",
                   help="small: 320x240, 30+20 frames (seconds); default: 640x480, 100+50 frames; "
                        "small-noisy-depth: small with predicted-depth-like errors in the depth files")
    p.add_argument("--overwrite", action="store_true", help="regenerate even if the scene exists")
    p.set_defaults(func=cli_synth)
    return p


def cli_synth(args) -> Path:
    path = generate_scene(args.out, seed=args.seed, preset=args.preset, overwrite=args.overwrite)
    print(path)
    return path


__all__ = ["SynthConfig", "SYNTH_PRESETS", "generate_scene", "get_config", "loop_poses", "look_rotation",
           "make_trajectories", "add_synth_parser", "cli_synth"]
