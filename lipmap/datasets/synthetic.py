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

Presets with ``n_rooms`` > 1 ("medium", "large") put that many such rooms side by side along x, 1 m
apart, each with its own random streams and camera loops: room k's mapping frames go to seq-(2k+1) and
its queries to seq-(2k+2), TrainSplit.txt lists sequence1, sequence3, ..., TestSplit.txt sequence2,
sequence4, ...; mesh.ply holds every room, and scene.json says where each room is ("rooms").

Cameras follow OpenCV/COLMAP: they look along +z, x right, y down; the world is z up, floor at z = 0.
"""
from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
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
    # > 1: that many rooms side by side along x (ROOM_GAP apart, never seeing each other), each with its
    # own random streams and camera loops; room k's mapping frames go to seq-(2k+1), its queries to seq-(2k+2)
    n_rooms: int = 1

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
# several rooms at "default"'s resolution and texture density: "medium" (4-7 min) for CI-scale checks
# (minutes), "large" for the benchmark (1,500 mapping + 500 query frames; ~1.5 s a frame per worker on a
# shared 2-core machine, about 50 min with one)
SYNTH_PRESETS["medium"] = replace(SYNTH_PRESETS["default"], name="medium", n_rooms=2, n_mapping=200, n_query=60)
SYNTH_PRESETS["large"] = replace(SYNTH_PRESETS["default"], name="large", n_rooms=5, n_mapping=1500, n_query=500)
ROOM_GAP = 1.0  # m of empty space between neighbouring rooms of a multi-room scene


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
    # every seq-NN: a previous run may have had more rooms (sequences) than this one
    for seq in sorted(p for p in scene_dir.glob("seq-[0-9][0-9]") if p.is_dir()):
        for pattern in ("frame-*.color.png", "frame-*.depth.png", "frame-*.normal.png", "frame-*.pose.txt"):
            for f in seq.glob(pattern):
                f.unlink()


def _surfaces_json(room: Room, room_of: list | None = None) -> str:
    """The planar rectangles of the mesh (mesh face f belongs to surface f // 2), one per line; with
    ``room_of`` (multi-room scenes) each row also says which room the surface belongs to."""
    rows = []
    for i, s in enumerate(room.surfaces):
        row = {"id": i, "label": s.label, "object_id": s.object_id, "plain": s.material.plain,
               "material": s.material.kind, "origin": np.round(s.origin, 6).tolist(),
               "u_axis": np.round(s.u_axis, 6).tolist(), "v_axis": np.round(s.v_axis, 6).tolist(),
               "size": [round(s.size[0], 6), round(s.size[1], 6)], "normal": np.round(s.normal, 6).tolist()}
        if room_of is not None:
            row["room"] = int(room_of[i])
        rows.append(json.dumps(row, separators=(",", ":")))
    return '{"room_size": %s, "surfaces": [\n%s\n]}\n' % (json.dumps(list(room.size)), ",\n".join(rows))


def generate_scene(out_root, seed: int = 0, preset="small", overwrite: bool = False, workers: int = 1) -> Path:
    """Generate (or find) the synthetic scene ``out_root/room-s<seed>`` and return its folder.

    A scene whose ``scene.json`` exists is complete and is kept unless ``overwrite``; it must have
    been made with the same preset (the name does not record it), else InputError. ``workers`` > 1
    renders frames in that many processes; the files are the same as with one.
    """
    cfg = get_config(preset)
    seed = int(seed)
    if seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed}")
    if int(workers) < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    if cfg.n_rooms < 1 or min(cfg.n_mapping, cfg.n_query) < cfg.n_rooms:
        raise InputError(f"{cfg.n_rooms} room(s) need n_rooms >= 1 and at least one mapping and one query frame "
                         f"each, got n_mapping={cfg.n_mapping}, n_query={cfg.n_query}")
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
    if cfg.n_rooms > 1:
        world, rooms, plain_pixels, total_pixels = _generate_rooms(scene_dir, cfg, seed, int(workers))
        meta = _scene_meta(cfg, seed, world, plain_pixels, total_pixels)
        meta["n_rooms"] = cfg.n_rooms
        meta["room_gap"] = ROOM_GAP
        meta["rooms"] = rooms
        write_text_atomic(marker, json.dumps(meta, indent=1) + "\n")
        logger.info(f"Synthetic scene {scene_dir.name}: {cfg.n_rooms} rooms in {world.size[0]:.2f} x "
                    f"{world.size[1]:.2f} x {world.size[2]:.2f} m, {len(world.surfaces)} surfaces, "
                    f"{cfg.n_mapping}+{cfg.n_query} frames in {time.perf_counter() - t0:.1f} s.")
        return scene_dir
    room, scene, mapping, query = _build_world(seed, cfg)
    t_build = time.perf_counter() - t0
    with _frame_pool(int(workers), seed, cfg) as pool:
        plain_pixels, total_pixels = _render_sequences(scene_dir, cfg, seed, ((1, mapping), (2, query)), None,
                                                       scene, pool)
    _write_scene_files(scene_dir, room)
    meta = _scene_meta(cfg, seed, room, plain_pixels, total_pixels)
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


def _room_streams(seed: int, room_index: int | None) -> list:
    """The (layout, texture, trajectory) seed sequences of the one room of a 1-room scene (``room_index``
    None) or of room ``room_index`` of a multi-room scene; the latter do not depend on how many rooms
    there are, so a 2-room scene holds the first two rooms of the 5-room scene of the same seed."""
    if room_index is None:
        return np.random.SeedSequence(seed).spawn(3)
    return np.random.SeedSequence([seed, _MULTI_ROOM_TAG, room_index]).spawn(3)


_MULTI_ROOM_TAG = 0x6D756C7469  # "multi": keeps the multi-room streams apart from the 1-room ones


def _room_scene(seed: int, cfg: SynthConfig, room_index: int | None) -> tuple[Room, RenderScene, object]:
    """(room in its own frame, its textured render scene, its trajectory seed sequence)."""
    # independent streams: the room and the camera loops do not depend on the preset's texture size
    ss_room, ss_tex, ss_traj = _room_streams(seed, room_index)
    room = build_room(np.random.default_rng(ss_room))
    scene = RenderScene.build(room, cfg.texels_per_m, np.random.default_rng(ss_tex))
    return room, scene, ss_traj


def _build_world(seed: int, cfg: SynthConfig) -> tuple:
    """The room, its textured render scene and the (mapping, query) camera loops of ``seed``."""
    room, scene, ss_traj = _room_scene(seed, cfg, None)
    mapping, query = make_trajectories(scene, cfg, np.random.default_rng(ss_traj))
    return room, scene, mapping, query


def _split_count(n: int, parts: int) -> list[int]:
    """``n`` frames over ``parts`` rooms, the remainder to the first rooms."""
    return [n // parts + (k < n % parts) for k in range(parts)]


def _shifted(room: Room, offset: np.ndarray, first_object: int) -> Room:
    """A copy of ``room`` moved by ``offset`` (3,), its object ids starting at ``first_object``."""
    moved = Room(room.size, [replace(w, origin=w.origin + offset) for w in room.walls])
    moved.surfaces = [replace(s, origin=s.origin + offset, object_id=s.object_id + first_object)
                      for s in room.surfaces]
    moved.obstacles = [(lo + offset, hi + offset, label) for lo, hi, label in room.obstacles]
    moved.blockers = [(lo + offset, hi + offset) for lo, hi in room.blockers]
    moved.band, moved.n_objects, moved.has_stairs = list(room.band), room.n_objects, room.has_stairs
    return moved


def _generate_rooms(scene_dir: Path, cfg: SynthConfig, seed: int, workers: int) -> tuple:
    """Build, render and write the rooms of a multi-room scene, one room at a time (one room's textures
    in memory). Room k is built and rendered in its own frame (x in [0, Lx], y in [0, Ly]) and placed at
    x offset = the widths of rooms 0..k-1 + k * ROOM_GAP; the pose files and the mesh are in the world
    frame. Each room is closed by its walls, floor and ceiling, so no camera sees another room.

    Returns (world Room holding every room's surfaces, per-room metadata, plain and all mapping pixels).
    """
    n = cfg.n_rooms
    layouts = [build_room(np.random.default_rng(_room_streams(seed, k)[0])) for k in range(n)]
    offsets = np.zeros((n, 3))
    offsets[1:, 0] = np.round(np.cumsum([r.size[0] + ROOM_GAP for r in layouts[:-1]]), 6)
    n_map, n_qry = _split_count(cfg.n_mapping, n), _split_count(cfg.n_query, n)
    placed, room_of, rooms, pixels = [], [], [], []
    with _frame_pool(workers, seed, cfg) as pool:
        for k in range(n):
            t0 = time.perf_counter()
            pixels.append(_generate_room(scene_dir, cfg, seed, k, offsets[k], n_map[k], n_qry[k], pool,
                                         placed, room_of, rooms))
            logger.info(f"room {k + 1}/{n}: {placed[k].size[0]:.2f} x {placed[k].size[1]:.2f} m at x = "
                        f"{offsets[k, 0]:.2f}, {n_map[k]}+{n_qry[k]} frames in {time.perf_counter() - t0:.1f} s")
    plain_pixels, total_pixels = (sum(c) for c in zip(*pixels))
    size = (round(float(offsets[-1, 0] + placed[-1].size[0]), 6), max(r.size[1] for r in placed),
            max(r.size[2] for r in placed))
    world = Room(size, [], surfaces=[s for r in placed for s in r.surfaces],
                 obstacles=[o for r in placed for o in r.obstacles], blockers=[b for r in placed for b in r.blockers],
                 n_objects=sum(r.n_objects for r in placed), has_stairs=any(r.has_stairs for r in placed))
    _write_scene_files(scene_dir, world, train=[2 * k + 1 for k in range(n)], test=[2 * k + 2 for k in range(n)],
                       room_of=room_of)
    return world, rooms, plain_pixels, total_pixels


def _generate_room(scene_dir: Path, cfg: SynthConfig, seed: int, k: int, offset: np.ndarray, n_map: int,
                   n_qry: int, pool, placed: list, room_of: list, rooms: list) -> tuple[int, int]:
    """Build, render and write room ``k`` of a multi-room scene; appends it (moved to ``offset``), its
    surfaces' room index and its metadata to ``placed``, ``room_of`` and ``rooms``; returns its mapping
    frames' (plain, all) pixels."""
    room, scene, ss_traj = _room_scene(seed, cfg, k)
    mapping, query = make_trajectories(scene, replace(cfg, n_mapping=n_map, n_query=n_qry),
                                       np.random.default_rng(ss_traj))
    seqs = ((2 * k + 1, mapping), (2 * k + 2, query))
    pixels = _render_sequences(scene_dir, cfg, seed, seqs, offset, scene, pool, room_index=k)
    del scene
    first = len(room_of)
    placed.append(_shifted(room, offset, sum(r.n_objects for r in placed)))
    room_of += [k] * len(room.surfaces)
    rooms.append({"index": k, "offset": offset.tolist(), "size": list(room.size),
                  "has_stairs": bool(room.has_stairs), "mapping_sequence": 2 * k + 1, "query_sequence": 2 * k + 2,
                  "n_mapping": n_map, "n_query": n_qry, "surfaces": [first, len(room_of)]})
    return pixels


def _render_sequences(scene_dir: Path, cfg: SynthConfig, seed: int, seqs, offset, scene: RenderScene,
                      pool=None, room_index: int | None = None) -> tuple:
    """Render and write the sequences ``seqs`` ((sequence number, cam_from_world (n, 4, 4)), ...) of one room,
    mapping sequences odd, query even; returns the mapping frames' (plain, all) pixels.

    Poses are in the room's frame; ``offset`` (3,) (None: 0) is where the room sits in the world, which
    only the pose files see. With a ``pool`` (:func:`_frame_pool`) the frames are rendered there, each
    worker rebuilding the room's render scene from its seeds (``room_index`` as for :func:`_room_streams`)
    instead of receiving it.
    """
    jobs = []
    for seq_idx, poses in seqs:
        seq_dir = scene_dir / f"seq-{seq_idx:02d}"
        seq_dir.mkdir(exist_ok=True)
        jobs += [(seq_dir, i, T, seq_idx) for i, T in enumerate(poses)]
    desc = f"render room {room_index + 1}" if room_index is not None else "render"
    if pool is None:
        counts = (_render_frame(seq_dir, i, T, scene, cfg.camera, cfg, seed, seq_idx, offset)
                  for seq_dir, i, T, seq_idx in jobs)
    else:
        counts = pool.map(_worker_render, [(room_index, *j, offset) for j in jobs], chunksize=2)
    counts = list(tqdm(counts, total=len(jobs), desc=desc, leave=False))
    mapping = [c for (_, _, _, seq_idx), c in zip(jobs, counts) if seq_idx % 2 == 1]
    return sum(p for p, _ in mapping), sum(t for _, t in mapping)


@contextmanager
def _frame_pool(workers: int, seed: int, cfg: SynthConfig):
    """None for one worker, else a pool of ``workers`` processes for :func:`_worker_render`."""
    if workers <= 1:
        yield None
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # spawn, not fork: the parent's embree threads do not survive a fork
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
                             initargs=(seed, cfg)) as pool:
        yield pool


_WORKER: dict = {}  # in a pool worker: the seed, the config and the render scene of the room it last rendered


def _init_worker(seed: int, cfg: SynthConfig):
    _WORKER.update(seed=seed, cfg=cfg)


def _worker_render(job) -> tuple[int, int]:
    room_index, seq_dir, i, T, seq_idx, offset = job
    w = _WORKER
    if "scene" not in w or w["room"] != room_index:  # rooms come in order: one rebuild per room and worker
        w["scene"], w["room"] = None, room_index  # drop the last room's textures first
        w["scene"] = _room_scene(w["seed"], w["cfg"], room_index)[1]
    return _render_frame(seq_dir, i, T, w["scene"], w["cfg"].camera, w["cfg"], w["seed"], seq_idx, offset)


def _render_frame(seq_dir: Path, i: int, T: np.ndarray, scene: RenderScene, camera: Camera, cfg: SynthConfig,
                  seed: int, seq_idx: int, offset=None) -> tuple[int, int]:
    """Render and write frame ``i``'s colour, depth, normals and pose (moved by the room's ``offset``);
    returns its (plain, all) pixels that see a surface."""
    # noise seeded per frame, so a frame does not depend on how many were rendered before it
    noise_rng = np.random.default_rng([seed, seq_idx, i])
    rgb, depth, normals, sid = render_view(scene, camera, T, cfg.supersample, cfg.noise_sigma, noise_rng)
    if cfg.depth_warp_sigma > 0:
        depth = corrupt_depth(depth, np.random.default_rng([seed, seq_idx, i, 1]), cfg.depth_warp_sigma)
    files = _frame_files(seq_dir, i)
    write_color(files["color"], rgb)
    write_depth(files["depth"], depth)
    write_normals(files["normal"], normals)
    if offset is not None:  # x_cam = R (x_world - offset) + t
        T = T.copy()
        T[:3, 3] -= T[:3, :3] @ offset
    write_text_atomic(files["pose"], _pose_text(T))
    hit = sid[sid >= 0]
    return int(scene.plain[hit].sum()), int(hit.size)


def _write_scene_files(scene_dir: Path, room: Room, train=(1,), test=(2,), room_of: list | None = None):
    """Write the split files, the ground-truth mesh (with surface ids) and surfaces.json."""
    write_text_atomic(scene_dir / "TrainSplit.txt", "".join(f"sequence{s}\n" for s in train))
    write_text_atomic(scene_dir / "TestSplit.txt", "".join(f"sequence{s}\n" for s in test))
    mesh, face_surface = room.to_mesh()
    mesh.face_attributes["surface_id"] = face_surface.astype(np.int32)
    with atomic_path(scene_dir / "mesh.ply") as tmp:
        mesh.export(tmp, file_type="ply")
    write_text_atomic(scene_dir / "surfaces.json", _surfaces_json(room, room_of))


def _scene_meta(cfg: SynthConfig, seed: int, room: Room, plain_pixels: int, total_pixels: int) -> dict:
    """The contents of scene.json."""
    areas = np.array([s.area for s in room.surfaces])
    plain = np.array([s.material.plain for s in room.surfaces])
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
        "plain_surface_fraction": round(float(areas[plain].sum() / areas.sum()), 4),
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
    from lipmap.cliargs import int_at_least

    p = subparsers.add_parser("synth", help="generate a procedural synthetic room in the 7-Scenes layout",
                              description=generate_scene.__doc__)
    p.add_argument("--out", type=Path, required=True, help="root folder; the scene goes to OUT/room-s<seed>")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="random seed: the same seed gives identical files")
    p.add_argument("--preset", choices=sorted(SYNTH_PRESETS), default="small",
                   help="small: 320x240, 30+20 frames (seconds); default: 640x480, 100+50 frames; "
                        "small-noisy-depth: small with predicted-depth-like errors in the depth files; "
                        "medium: 2 rooms, 640x480, 200+60 frames (minutes); large: 5 rooms, 640x480, "
                        "1500+500 frames (about 1.5 s a frame per worker)")
    p.add_argument("--overwrite", action="store_true", help="regenerate even if the scene exists")
    p.add_argument("--workers", type=int_at_least(1), default=1,
                   help="render frames in this many processes (same files as with 1)")
    p.set_defaults(func=cli_synth)
    return p


def cli_synth(args) -> Path:
    path = generate_scene(args.out, seed=args.seed, preset=args.preset, overwrite=args.overwrite,
                          workers=getattr(args, "workers", 1))
    print(path)
    return path


__all__ = ["SynthConfig", "SYNTH_PRESETS", "generate_scene", "get_config", "loop_poses", "look_rotation",
           "make_trajectories", "add_synth_parser", "cli_synth"]
