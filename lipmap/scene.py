"""Camera, View and Scene: the data model every step reads.

Conventions (pinned by tests):
- ``View.cam_from_world`` is a 4x4 rigid transform, x_cam = R x_world + t (pycolmap / PoseLib).
- Pixel coordinates follow COLMAP: the centre of pixel (col i, row j) is at (i + 0.5, j + 0.5), so
  7-Scenes' cx = 320, cy = 240 is the exact image centre of a 640x480 image. OpenCV (LSD, SIFT in
  OpenCV) and hloc keypoints put the centre at integers: add 0.5 at those boundaries.
- Depth maps are float32 metres in the COLOUR camera (registered), 0 where invalid.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. ``params`` = (fx, fy, cx, cy) in COLMAP pixel convention."""

    width: int
    height: int
    params: tuple
    model: str = "PINHOLE"

    def __post_init__(self):
        if self.model != "PINHOLE":
            raise InputError(f"unsupported camera model {self.model!r}; only PINHOLE is supported")
        if len(self.params) != 4:
            raise InputError(f"PINHOLE camera needs 4 params (fx, fy, cx, cy), got {len(self.params)}")
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))

    @property
    def fx(self) -> float:
        return self.params[0]

    @property
    def fy(self) -> float:
        return self.params[1]

    @property
    def cx(self) -> float:
        return self.params[2]

    @property
    def cy(self) -> float:
        return self.params[3]

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, scale: float) -> "Camera":
        """The camera of the image resized by ``scale`` (exact in COLMAP's pixel convention)."""
        w, h = int(round(self.width * scale)), int(round(self.height * scale))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, (self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy))

    def to_dict(self) -> dict:
        """PoseLib's camera dict (also what we store in JSON)."""
        return {"model": self.model, "width": self.width, "height": self.height, "params": list(self.params)}

    def to_pycolmap(self, camera_id: int = 1):
        import pycolmap

        return pycolmap.Camera(
            model=self.model, width=self.width, height=self.height, params=list(self.params), camera_id=camera_id
        )

    def pixel_rays(self) -> np.ndarray:
        """Unnormalised camera-frame ray directions (z = 1) through every pixel centre, (H, W, 3)."""
        u = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)


@dataclass
class View:
    """One posed image with its optional depth, normals and 2D lines.

    ``name`` is the image path relative to the scene root, as hloc names images
    (``seq-01/frame-000000.color.png``), so hloc's files match without renaming.
    ``depth_camera``/``color_from_depth`` describe an unregistered depth sensor (7-Scenes);
    both None means the depth map already lives in the colour camera.
    """

    name: str
    camera: Camera
    cam_from_world: Optional[np.ndarray]
    color_path: Path
    depth_path: Optional[Path] = None
    normal_path: Optional[Path] = None
    lines_path: Optional[Path] = None
    depth_camera: Optional[Camera] = None
    color_from_depth: Optional[np.ndarray] = None
    depth_scale: float = 1000.0  # depth PNG units per metre
    meta: dict = field(default_factory=dict)

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:3, 3]

    @property
    def center(self) -> np.ndarray:
        from .poses import camera_center

        return camera_center(self.cam_from_world)

    def load_color(self, gray: bool = False) -> np.ndarray:
        from .imageio import read_color

        return read_color(self.color_path, gray=gray, expected_size=(self.camera.width, self.camera.height))

    def load_depth(self, register: bool = True) -> np.ndarray:
        """Depth in metres (H, W) float32 in the colour camera; 0 = invalid.

        With ``register`` and an unregistered sensor, depth is re-projected into the colour camera;
        without it, the raw depth image is returned as if it were the colour camera's (wrong by the
        sensor baseline: kept only to measure what registration buys).
        """
        from .imageio import read_depth
        from .datasets.registration import register_depth

        if self.depth_path is None:
            raise InputError(f"view {self.name} has no depth map")
        dcam = self.depth_camera or self.camera
        depth = read_depth(self.depth_path, expected_size=(dcam.width, dcam.height), scale=self.depth_scale)
        if register and self.depth_camera is not None:
            return register_depth(depth, self.depth_camera, self.camera, self.color_from_depth)
        return depth

    def load_normals(self) -> Optional[np.ndarray]:
        """Camera-frame unit normals (H, W, 3) from ``normal_path`` (or None if there is none)."""
        if self.normal_path is None:
            return None
        from .imageio import read_normals

        return read_normals(self.normal_path, expected_size=(self.camera.width, self.camera.height))

    def with_pose(self, cam_from_world: np.ndarray) -> "View":
        return replace(self, cam_from_world=np.asarray(cam_from_world, dtype=float))


@dataclass
class Scene:
    """Mapping views, query views (whose poses are the ground truth) and scene metadata."""

    name: str
    dataset: str
    root: Path
    mapping: list
    query: list
    pose_source: str = "posetxt"
    gt_mesh: Optional[Path] = None
    depth_registered: bool = True
    meta: dict = field(default_factory=dict)

    def all_views(self) -> list:
        return list(self.mapping) + list(self.query)

    def view(self, name: str) -> View:
        for v in self.all_views():
            if v.name == name:
                return v
        raise KeyError(f"no view named {name!r} in scene {self.name}")

    @property
    def query_gt(self) -> dict:
        """Ground-truth cam_from_world of every query, by name (None: invalid ground truth)."""
        return {v.name: v.cam_from_world for v in self.query}
