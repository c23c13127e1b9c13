"""Procedural room layout for the synthetic scenes: walls, door/window frames, furniture, stairs.

Everything is built from axis-aligned planar rectangles ("surfaces"), each with a material and a
metric (u, v) frame for its texture. A room is x in [0, Lx], y in [0, Ly], z in [0, H], z up, floor
at z = 0. Walls are numbered 0..3 counter-clockwise (y = 0, x = Lx, y = Ly, x = 0); items against a
wall are placed in that wall's frame (s along the wall, h up, d into the room).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from .synth_textures import Material

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass
class Surface:
    """A planar rectangle: corners origin + [0, su] * u_axis + [0, sv] * v_axis; normal = u x v (outward)."""

    origin: np.ndarray  # (3,)
    u_axis: np.ndarray  # (3,) unit
    v_axis: np.ndarray  # (3,) unit
    size: tuple  # (su, sv) metres
    material: Material
    object_id: int
    label: str  # "wall", "floor", "cabinet", ...

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u_axis, self.v_axis)

    @property
    def area(self) -> float:
        return float(self.size[0] * self.size[1])


@dataclass
class Wall:
    index: int
    origin: np.ndarray  # (3,) corner where s = 0
    along: np.ndarray  # (3,) unit, horizontal
    inward: np.ndarray  # (3,) unit normal pointing into the room
    length: float

    def point(self, s, h, d) -> np.ndarray:
        return self.origin + s * self.along + h * Z_UP + d * self.inward

    def aabb(self, s0, s1, h0, h1, d0, d1) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.point(s0, h0, d0), self.point(s1, h1, d1)
        return np.minimum(a, b), np.maximum(a, b)


@dataclass
class Room:
    size: tuple  # (Lx, Ly, H)
    walls: list
    surfaces: list = field(default_factory=list)
    obstacles: list = field(default_factory=list)  # (lo, hi, label) of furniture the camera must avoid
    blockers: list = field(default_factory=list)  # (lo, hi) furniture must not cut: sills, doorways
    band: list = field(default_factory=lambda: [0.0] * 4)  # furniture depth from each wall
    n_objects: int = 0
    has_stairs: bool = False

    def new_object(self) -> int:
        self.n_objects += 1
        return self.n_objects - 1

    # ---- primitives -------------------------------------------------------------------------------------
    def add_quad(self, origin, u_axis, v_axis, su, sv, mat: Material, obj: int, label: str):
        if su <= 1e-4 or sv <= 1e-4:
            return
        self.surfaces.append(Surface(np.asarray(origin, float), np.asarray(u_axis, float), np.asarray(v_axis, float),
                                     (float(su), float(sv)), mat, obj, label))

    def add_box(self, lo, hi, mats: dict, label: str, front: np.ndarray | None = None, skip=(), obstacle=False):
        """Axis-aligned box with outward faces. ``mats`` keys: front, back, side, top, bottom (default side).

        ``front`` is the outward normal of the face called "front" (the one facing into the room).
        """
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        sx, sy, sz = hi - lo
        ex, ey, ez = np.eye(3)
        obj = self.new_object()
        # (outward normal, origin, u, v, su, sv); u x v = outward normal, u horizontal for vertical faces
        faces = [
            (ez, (x0, y0, z1), ex, ey, sx, sy),
            (-ez, (x0, y0, z0), ey, ex, sy, sx),
            (ex, (x1, y0, z0), ey, ez, sy, sz),
            (-ex, (x0, y1, z0), -ey, ez, sy, sz),
            (ey, (x1, y1, z0), -ex, ez, sx, sz),
            (-ey, (x0, y0, z0), ex, ez, sx, sz),
        ]
        for n, o, u, v, su, sv in faces:
            if n[2] > 0.5:
                role = "top"
            elif n[2] < -0.5:
                role = "bottom"
            elif front is not None and np.dot(n, front) > 0.5:
                role = "front"
            elif front is not None and np.dot(n, front) < -0.5:
                role = "back"
            else:
                role = "side"
            if role in skip:
                continue
            self.add_quad(o, u, v, su, sv, mats.get(role, mats["side"]), obj, label)
        if obstacle:
            self.obstacles.append((lo, hi, label))
        return obj

    def add_wall_box(self, wall: Wall, s0, s1, h0, h1, d0, d1, mats, label, skip=(), obstacle=False):
        lo, hi = wall.aabb(s0, s1, h0, h1, d0, d1)
        return self.add_box(lo, hi, mats, label, front=wall.inward, skip=skip, obstacle=obstacle)

    # ---- output -----------------------------------------------------------------------------------------
    def to_mesh(self) -> tuple[trimesh.Trimesh, np.ndarray]:
        """Triangle mesh (2 triangles per surface, in surface order) and the surface id of each face (F,)."""
        n = len(self.surfaces)
        verts = np.empty((n, 4, 3))
        for i, s in enumerate(self.surfaces):
            su, sv = s.size
            verts[i] = [s.origin, s.origin + su * s.u_axis, s.origin + su * s.u_axis + sv * s.v_axis,
                        s.origin + sv * s.v_axis]
        base = 4 * np.arange(n)[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
        mesh = trimesh.Trimesh(verts.reshape(-1, 3), faces, process=False)
        face_surface = np.repeat(np.arange(n), 2)
        return mesh, face_surface


# ---- materials --------------------------------------------------------------------------------------------
def _rgb(rng, lo=0.0, hi=1.0, sat=0.35):
    """A colour of brightness in [lo, hi] and saturation <= ``sat`` (real rooms are mostly muted)."""
    value = rng.uniform(lo, hi)
    s = rng.uniform(0.0, sat)
    hue = rng.uniform(0.0, 1.0)
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0  # HSV -> RGB
    rgb = value - value * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return tuple(float(v) for v in rgb)


def _paint(rng) -> tuple:
    """A muted wall/furniture paint colour."""
    base = rng.uniform(0.55, 0.9)
    tint = rng.uniform(-0.12, 0.12, 3)
    return tuple(float(v) for v in np.clip(base + tint, 0.05, 0.95))


def _wood_mat(rng, dark=None) -> Material:
    dark = rng.random() < 0.4 if dark is None else dark
    light = np.array([0.72, 0.52, 0.32]) * (0.55 if dark else 1.0) * rng.uniform(0.85, 1.1)
    return Material("wood", tuple(np.clip(light, 0, 1)), tuple(np.clip(light * 0.55, 0, 1)),
                    {"grain_per_m": float(rng.uniform(25, 60))})


def _plaster_mat(rng, contrast=None) -> Material:
    c = np.array(_paint(rng))
    return Material("noise", tuple(c), tuple(np.clip(c * rng.uniform(0.3, 0.45), 0, 1)),
                    {"contrast": float(contrast if contrast is not None else rng.uniform(0.2, 0.26))})


def _plain(rng, lo=0.2, hi=0.9) -> Material:
    return Material("plain", _rgb(rng, lo, hi))


def _poster_mat(rng) -> Material:
    return Material("poster", _rgb(rng, 0.3, 0.95), params={"shapes_per_m2": float(rng.uniform(40, 90))})


def _floor_mat(rng) -> Material:
    k = rng.integers(0, 3)
    if k == 0:
        w = _wood_mat(rng)
        return Material("planks", w.color, w.color2, {"grain_per_m": w.params["grain_per_m"],
                                                      "plank_width": float(rng.uniform(0.1, 0.2)),
                                                      "plank_length": float(rng.uniform(0.8, 1.5))})
    if k == 1:
        c = _rgb(rng, 0.35, 0.85)
        return Material("tiles", c, _rgb(rng, 0.15, 0.35), {"tile": float(rng.uniform(0.25, 0.45)),
                                                          "grout": 0.006, "contrast": 0.18,
                                                          "checker": bool(rng.random() < 0.4),
                                                          "alt": _rgb(rng, 0.2, 0.7)})
    return Material("speckle", _rgb(rng, 0.45, 0.75), _rgb(rng, 0.2, 0.4), {"chips_per_m2": 500.0})


# ---- layout -----------------------------------------------------------------------------------------------
def _walls(Lx, Ly) -> list[Wall]:
    ex, ey = np.eye(3)[0], np.eye(3)[1]
    return [
        Wall(0, np.array([0.0, 0, 0]), ex, ey, Lx),
        Wall(1, np.array([Lx, 0.0, 0]), ey, -ex, Ly),
        Wall(2, np.array([Lx, Ly, 0.0]), -ex, -ey, Lx),
        Wall(3, np.array([0.0, Ly, 0]), -ey, ex, Ly),
    ]


class _Occupancy:
    """Intervals along each wall already used, with the height they reach (for posters and windows)."""

    def __init__(self):
        self.items = {i: [] for i in range(4)}  # wall -> list of (s0, s1, h0, h1, kind)

    def free(self, wall, s0, s1, h0, h1, gap=0.05):
        for a, b, c, d, _ in self.items[wall]:
            if s0 < b + gap and s1 > a - gap and h0 < d + gap and h1 > c - gap:
                return False
        return True

    def add(self, wall, s0, s1, h0, h1, kind):
        self.items[wall].append((s0, s1, h0, h1, kind))


def build_room(rng: np.random.Generator) -> Room:
    """A random furnished room. Same generator state -> same room."""
    Lx = round(float(rng.uniform(4.0, 6.0)), 2)
    Ly = round(float(rng.uniform(3.0, 5.0)), 2)
    H = round(float(rng.uniform(2.6, 3.0)), 2)
    room = Room((Lx, Ly, H), _walls(Lx, Ly))
    occ = _Occupancy()
    # the free floor between opposite walls must keep >= 1.9 m so the camera loop fits
    budget = [min(0.8, (Ly - 1.9) / 2), min(0.8, (Lx - 1.9) / 2)] * 2
    wall_mats = _add_shell(room, rng)
    # drawn before the door: the door, window and baseboard frames share this one trim colour
    frame_mat = Material("plain", _rgb(rng, 0.85, 0.98))
    door_span = _add_door(room, occ, frame_mat, rng)
    _add_windows(room, occ, frame_mat, rng)
    _add_furniture(room, occ, budget, rng)
    _add_wall_trim(room, occ, wall_mats, door_span, frame_mat, rng)
    return room


def _wall_materials(walls, rng) -> list:
    """One material per wall: one wall plain paint, the others tiles (20 %) or plaster."""
    plain_wall = int(rng.integers(0, 4))
    wall_mats = []
    for w in walls:
        if w.index == plain_wall:
            wall_mats.append(Material("plain", _paint(rng)))
        elif rng.random() < 0.2:
            c = _rgb(rng, 0.5, 0.9)
            wall_mats.append(Material("tiles", c, _rgb(rng, 0.3, 0.5),
                                      {"tile": float(rng.uniform(0.15, 0.3)), "grout": 0.004, "contrast": 0.15}))
        else:
            wall_mats.append(_plaster_mat(rng))
    return wall_mats


def _ceiling_mat(rng) -> Material:
    """Ceiling tiles (60 %) or plain bright paint."""
    if rng.random() < 0.6:
        return Material("tiles", _rgb(rng, 0.8, 0.95), _rgb(rng, 0.4, 0.6),
                        {"tile": 0.6, "grout": 0.015, "contrast": 0.25})
    return Material("plain", _rgb(rng, 0.85, 0.97))


def _add_shell(room: Room, rng) -> list:
    """Add the walls, floor and ceiling; returns the wall materials (the trim pass needs them)."""
    Lx, Ly, H = room.size
    wall_mats = _wall_materials(room.walls, rng)
    for w, m in zip(room.walls, wall_mats):
        obj = room.new_object()
        # from the top corner: u along the wall, v down, so u x v = the inward normal (the visible side)
        room.add_quad(w.origin + H * Z_UP, w.along, -Z_UP, w.length, H, m, obj, "wall")
    room.add_quad((0, 0, 0), (1, 0, 0), (0, 1, 0), Lx, Ly, _floor_mat(rng), room.new_object(), "floor")
    ceil = _ceiling_mat(rng)
    room.add_quad((0, 0, H), (0, 1, 0), (1, 0, 0), Ly, Lx, ceil, room.new_object(), "ceiling")
    return wall_mats


def _add_door(room: Room, occ: _Occupancy, frame_mat: Material, rng) -> tuple:
    """Add a framed door with a handle on a random wall; returns (wall index, s0, s1) of its frame."""
    H = room.size[2]
    dw = room.walls[int(rng.integers(0, 4))]
    door_w, door_h, fw = float(rng.uniform(0.8, 0.95)), float(rng.uniform(2.0, 2.15)), 0.07
    s0 = float(rng.uniform(0.25 + fw, dw.length - 0.25 - fw - door_w))
    leaf = _wood_mat(rng) if rng.random() < 0.5 else _plain(rng, 0.3, 0.8)
    room.add_wall_box(dw, s0, s0 + door_w, 0, door_h, 0, 0.012, {"side": frame_mat, "front": leaf}, "door",
                      skip=("bottom", "back"))
    room.add_wall_box(dw, s0 - fw, s0, 0, door_h + fw, 0, 0.025, {"side": frame_mat}, "door_frame",
                      skip=("bottom", "back"))
    room.add_wall_box(dw, s0 + door_w, s0 + door_w + fw, 0, door_h + fw, 0, 0.025, {"side": frame_mat},
                      "door_frame", skip=("bottom", "back"))
    room.add_wall_box(dw, s0, s0 + door_w, door_h, door_h + fw, 0, 0.025, {"side": frame_mat}, "door_frame",
                      skip=("back",))
    hs = s0 + door_w - 0.08 if rng.random() < 0.5 else s0 + 0.06
    metal = Material("plain", _rgb(rng, 0.25, 0.45))
    room.add_wall_box(dw, hs, hs + 0.02, 1.0, 1.03, 0.012, 0.07, {"side": metal}, "handle", skip=("back",))
    occ.add(dw.index, s0 - fw - 0.15, s0 + door_w + fw + 0.15, 0.0, H, "door")
    room.blockers.append(dw.aabb(s0 - fw - 0.15, s0 + door_w + fw + 0.15, 0.0, H, 0.0, 0.9))  # the doorway
    return (dw.index, s0 - fw, s0 + door_w + fw)


def _add_windows(room: Room, occ: _Occupancy, frame_mat: Material, rng):
    """Add 1-2 windows, each on a random wall where it fits (or none after 20 tries)."""
    H = room.size[2]
    n_windows = int(rng.integers(1, 3))
    for _ in range(n_windows):
        for _try in range(20):
            w = room.walls[int(rng.integers(0, 4))]
            ww, wh = float(rng.uniform(0.8, 1.5)), float(rng.uniform(1.0, 1.4))
            sill = float(rng.uniform(0.85, 1.0))
            if ww + 0.6 > w.length or sill + wh > H - 0.25:
                continue
            s = float(rng.uniform(0.3, w.length - 0.3 - ww))
            if not occ.free(w.index, s - 0.1, s + ww + 0.1, sill - 0.1, sill + wh + 0.1):
                continue
            _add_window(room, occ, w, s, ww, wh, sill, frame_mat, rng)
            break


def _add_window(room: Room, occ: _Occupancy, w: Wall, s, ww, wh, sill, frame_mat: Material, rng):
    """Add one window (glass, frame, sill, mullion, maybe a transom) at a free spot of wall ``w``."""
    glass = Material("plain", tuple(np.clip(np.array([0.75, 0.85, 0.95]) * rng.uniform(0.9, 1.05), 0, 1)))
    wf = 0.06
    room.add_wall_box(w, s, s + ww, sill, sill + wh, 0, 0.005, {"side": glass}, "window",
                      skip=("back",))
    mats = {"side": frame_mat}
    room.add_wall_box(w, s - wf, s, sill, sill + wh, 0, 0.04, mats, "window_frame", skip=("back",))
    room.add_wall_box(w, s + ww, s + ww + wf, sill, sill + wh, 0, 0.04, mats, "window_frame", skip=("back",))
    room.add_wall_box(w, s - wf, s + ww + wf, sill + wh, sill + wh + wf, 0, 0.04, mats, "window_frame",
                      skip=("back",))
    room.add_wall_box(w, s - wf - 0.04, s + ww + wf + 0.04, sill - 0.03, sill, 0, 0.13, mats, "window_sill",
                      skip=("back",))
    mid = s + ww / 2
    room.add_wall_box(w, mid - 0.02, mid + 0.02, sill, sill + wh, 0.005, 0.03, mats, "window_frame",
                      skip=("back",))
    if rng.random() < 0.5:
        hm = sill + wh * rng.uniform(0.55, 0.7)
        room.add_wall_box(w, s, s + ww, hm - 0.02, hm + 0.02, 0.005, 0.03, mats, "window_frame",
                          skip=("back",))
    occ.add(w.index, s - wf - 0.04, s + ww + wf + 0.04, sill - 0.05, sill + wh + wf, "window")
    room.blockers.append(w.aabb(s - wf - 0.04, s + ww + wf + 0.04, sill - 0.03, sill + wh + wf, 0.0, 0.13))


def _add_furniture(room: Room, occ: _Occupancy, budget: list, rng):
    """Add cabinets, shelves and desks (sometimes stairs) in random order, each where it fits."""
    plain_front = Material("plain", _paint(rng))
    kinds = ["cabinet", "shelf", "desk", "cabinet", "shelf", "desk", "cabinet"]
    rng.shuffle(kinds)
    if rng.random() < 0.5:
        kinds.insert(int(rng.integers(0, 3)), "stairs")
    for kind in kinds:
        for _try in range(30):
            if _try_place_furniture(room, occ, kind, budget, rng, plain_front):
                break


def _try_place_furniture(room: Room, occ: _Occupancy, kind: str, budget: list, rng, plain_front) -> bool:
    """Draw one random spot for ``kind`` and add it there if it fits; False when it does not."""
    w = room.walls[int(rng.integers(0, 4))]
    spec = _furniture_spec(kind, rng)
    width, depth, height = spec["w"], min(spec["d"], budget[w.index]), spec["h"]
    if depth < 0.3 or width + 0.2 > w.length:
        return False
    s = float(rng.uniform(0.05, w.length - 0.05 - width))
    if not occ.free(w.index, s, s + width, 0.0, height):
        return False
    lo, hi = w.aabb(s, s + width, 0, height, 0.02, 0.02 + depth)
    others = [(b_lo, b_hi) for b_lo, b_hi, _ in room.obstacles] + room.blockers
    if any(np.all(lo < b_hi + 0.05) and np.all(hi > b_lo - 0.05) for b_lo, b_hi in others):
        return False
    _FURNITURE[kind](room, w, s, width, depth, height, spec, rng, plain_front)
    room.obstacles.append((lo, hi, kind))
    occ.add(w.index, s, s + width, 0.0, height, kind)
    room.band[w.index] = max(room.band[w.index], 0.02 + depth)
    room.has_stairs |= kind == "stairs"
    return True


def _add_wall_trim(room: Room, occ: _Occupancy, wall_mats: list, door_span: tuple, frame_mat: Material, rng):
    """Add baseboards to every wall and pictures to every textured one, wall by wall."""
    for w, m in zip(room.walls, wall_mats):
        _add_baseboards(room, w, door_span, frame_mat)
        if m.plain:
            continue  # keep the plain wall plain: only its edges are there to match
        _add_pictures(room, occ, w, rng)


def _add_baseboards(room: Room, w: Wall, door_span: tuple, frame_mat: Material):
    """Add the baseboard along wall ``w``, broken where the door is."""
    segs = [(0.0, w.length)]
    if w.index == door_span[0]:
        segs = [(0.0, door_span[1]), (door_span[2], w.length)]
    for a, b in segs:
        if b - a > 0.05:
            room.add_wall_box(w, a, b, 0, 0.08, 0, 0.015, {"side": frame_mat}, "baseboard",
                              skip=("back", "bottom"))


def _add_pictures(room: Room, occ: _Occupancy, w: Wall, rng):
    """Add 1-2 framed posters to wall ``w``, each where it fits (or none after 20 tries)."""
    H = room.size[2]
    for _ in range(int(rng.integers(1, 3))):
        for _try in range(20):
            pw, ph = float(rng.uniform(0.4, 1.0)), float(rng.uniform(0.35, 0.8))
            h0 = float(rng.uniform(1.0, min(2.1, H - 0.3 - ph)))
            s = float(rng.uniform(0.2, max(0.21, w.length - 0.2 - pw)))
            if s + pw > w.length - 0.1 or not occ.free(w.index, s, s + pw, h0, h0 + ph):
                continue
            fr = Material("plain", _rgb(rng, 0.05, 0.6))
            room.add_wall_box(w, s, s + pw, h0, h0 + ph, 0, 0.02, {"side": fr}, "picture_frame", skip=("back",))
            m_in = 0.035
            room.add_wall_box(w, s + m_in, s + pw - m_in, h0 + m_in, h0 + ph - m_in, 0, 0.026,
                              {"side": fr, "front": _poster_mat(rng)}, "picture", skip=("back",))
            occ.add(w.index, s, s + pw, h0, h0 + ph, "picture")
            break


def _furniture_spec(kind, rng) -> dict:
    if kind == "cabinet":
        tall = rng.random() < 0.4
        return {"w": float(rng.uniform(0.6, 1.3)), "d": float(rng.uniform(0.4, 0.6)),
                "h": float(rng.uniform(1.6, 2.0) if tall else rng.uniform(0.75, 0.95)), "tall": tall}
    if kind == "shelf":
        return {"w": float(rng.uniform(0.7, 1.2)), "d": float(rng.uniform(0.3, 0.4)), "h": float(rng.uniform(1.2, 2.0))}
    if kind == "desk":
        return {"w": float(rng.uniform(1.0, 1.6)), "d": float(rng.uniform(0.6, 0.8)),
                "h": float(rng.uniform(0.72, 0.77))}
    if kind == "stairs":
        n = int(rng.integers(3, 6))
        run = float(rng.uniform(0.26, 0.3))
        return {"w": n * run, "d": float(rng.uniform(0.7, 0.8)), "h": n * float(rng.uniform(0.16, 0.19)), "n": n,
                "run": run}
    raise ValueError(kind)


def _cabinet(room: Room, w: Wall, s, width, depth, height, spec, rng, plain_front):
    body = _wood_mat(rng) if rng.random() < 0.6 else _plaster_mat(rng)
    dark = Material("plain", _rgb(rng, 0.1, 0.3))
    d0, d1 = 0.02, 0.02 + depth - 0.018
    # recessed plinth under the body, as on kitchen cabinets: one more horizontal edge near the floor
    room.add_wall_box(w, s + 0.02, s + width - 0.02, 0.0, 0.1, d0, d1 - 0.05, {"side": dark}, "plinth",
                      skip=("bottom", "back", "top"))
    room.add_wall_box(w, s, s + width, 0.1, height, d0, d1, {"side": body, "front": plain_front}, "cabinet")
    gap = 0.004
    front = Material("plain", tuple(np.clip(np.array(plain_front.color) * rng.uniform(0.9, 1.1), 0, 1)))
    metal = Material("plain", _rgb(rng, 0.2, 0.5))
    n_doors = max(1, int(round(width / 0.5)))
    rows = [(0.1, height, "door")]
    if not spec.get("tall") and rng.random() < 0.5:
        rows = [(0.1, height - 0.2, "door"), (height - 0.2, height, "drawer")]
    for h0, h1, part in rows:
        for k in range(n_doors):
            a = s + width * k / n_doors + gap
            b = s + width * (k + 1) / n_doors - gap
            room.add_wall_box(w, a, b, h0 + gap, h1 - gap, d1, d1 + 0.018, {"side": front}, "cabinet_front",
                              skip=("back",))
            if part == "drawer":
                hx0, hx1, hh0, hh1 = (a + b) / 2 - 0.06, (a + b) / 2 + 0.06, (h0 + h1) / 2 - 0.01, (h0 + h1) / 2 + 0.01
            else:
                hx = b - 0.05 if k % 2 == 0 else a + 0.03
                hh = min(h1 - 0.12, 1.05)
                hx0, hx1, hh0, hh1 = hx, hx + 0.02, hh - 0.07, hh + 0.07
            room.add_wall_box(w, hx0, hx1, hh0, hh1, d1 + 0.018, d1 + 0.04, {"side": metal}, "handle",
                              skip=("back",))
    if not spec.get("tall"):
        top = Material("speckle", _rgb(rng, 0.3, 0.8), _rgb(rng, 0.1, 0.3), {"chips_per_m2": 600.0})
        room.add_wall_box(w, s - 0.01, s + width + 0.01, height, height + 0.03, 0.02, 0.02 + depth + 0.02,
                          {"side": top}, "countertop", skip=("back",))
        _tabletop_objects(room, w, s, width, depth, height + 0.03, rng)


def _shelf(room: Room, w: Wall, s, width, depth, height, spec, rng, plain_front):
    wood = _wood_mat(rng)
    t = 0.02
    d0, d1 = 0.02, 0.02 + depth
    back = _plaster_mat(rng) if rng.random() < 0.5 else _wood_mat(rng)
    room.add_wall_box(w, s, s + width, 0, height, d0, d0 + 0.01, {"side": back}, "shelf_back", skip=("bottom",))
    room.add_wall_box(w, s, s + t, 0, height, d0 + 0.01, d1, {"side": wood}, "shelf_side", skip=("bottom",))
    room.add_wall_box(w, s + width - t, s + width, 0, height, d0 + 0.01, d1, {"side": wood}, "shelf_side",
                      skip=("bottom",))
    n_boards = max(2, int(height / 0.38))
    levels = np.linspace(0.05, height - t, n_boards + 1)
    for i, h in enumerate(levels):
        room.add_wall_box(w, s + t, s + width - t, h, h + t, d0 + 0.01, d1, {"side": wood}, "shelf_board",
                          skip=("back",) + (("bottom",) if i == 0 else ()))
        if i == len(levels) - 1:
            break
        # books stand on every board but the top one
        space = levels[i + 1] - h - t
        a = s + t + rng.uniform(0.0, 0.1)
        while True:
            bw = float(rng.uniform(0.02, 0.06))
            if a + bw > s + width - t - 0.01:
                break
            if rng.random() < 0.15:
                a += float(rng.uniform(0.05, 0.2))  # a gap on the shelf
                continue
            bh = float(min(space - 0.02, rng.uniform(0.15, 0.32)))
            bd = float(min(depth - 0.03, rng.uniform(0.14, 0.24)))
            if bh > 0.08:
                mat = Material("plain", _rgb(rng, 0.1, 0.9, sat=0.8))
                room.add_wall_box(w, a, a + bw, h + t, h + t + bh, d0 + 0.02, d0 + 0.02 + bd, {"side": mat}, "book",
                                  skip=("back", "bottom"))
            a += bw + 0.002


def _tabletop_objects(room: Room, w: Wall, s, width, depth, top, rng):
    for _ in range(int(rng.integers(1, 4))):
        ow, od, oh = rng.uniform(0.1, 0.35), rng.uniform(0.08, 0.3), rng.uniform(0.05, 0.4)
        if ow + 0.05 > width or od + 0.05 > depth:
            continue
        a = float(rng.uniform(s + 0.02, s + width - ow - 0.02))
        d = float(rng.uniform(0.05, 0.02 + depth - od - 0.02))
        # objects may overlap each other (boxes interpenetrate cleanly) but stay on the top
        mat = _poster_mat(rng) if rng.random() < 0.5 else _plaster_mat(rng, contrast=0.3)
        room.add_wall_box(w, a, a + ow, top, top + oh, d, d + od, {"side": mat}, "object", skip=("bottom",))


def _desk(room: Room, w: Wall, s, width, depth, height, spec, rng, plain_front):
    top_mat = _wood_mat(rng) if rng.random() < 0.7 else Material("speckle", _rgb(rng, 0.4, 0.8), _rgb(rng, 0.1, 0.3))
    leg = Material("plain", _rgb(rng, 0.1, 0.5))
    tt = 0.035
    d0, d1 = 0.02, 0.02 + depth
    room.add_wall_box(w, s, s + width, height - tt, height, d0, d1, {"side": top_mat}, "table_top")
    ls = 0.045
    for a in (s + 0.03, s + width - 0.03 - ls):
        for d in (d0 + 0.03, d1 - 0.03 - ls):
            room.add_wall_box(w, a, a + ls, 0, height - tt, d, d + ls, {"side": leg}, "table_leg",
                              skip=("bottom", "top"))
    _tabletop_objects(room, w, s, width, depth, height, rng)


def _stairs(room: Room, w: Wall, s, width, depth, height, spec, rng, plain_front):
    n, run = spec["n"], spec["run"]
    rise = height / n
    tread = _wood_mat(rng)
    riser = Material("plain", _paint(rng))
    side = _plaster_mat(rng)
    up = rng.random() < 0.5  # climbs towards +s or -s
    for k in range(n):
        a = s + k * run if up else s + width - (k + 1) * run
        # columns side by side (not stacked) so no two boxes share a visible plane
        room.add_wall_box(w, a, a + run, 0, (k + 1) * rise, 0.02, 0.02 + depth,
                          {"side": riser, "top": tread, "front": side}, "stairs", skip=("bottom",))


_FURNITURE = {"cabinet": _cabinet, "shelf": _shelf, "desk": _desk, "stairs": _stairs}
