"""Training targets: each view's depth and normals on its training grid, in memory or read on demand."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from ..normals import normals_from_depth
from .config import PlaneOptConfig
from .init import LazyDepthFrames, resize_nearest, working_downscale


@dataclass
class ViewTarget:
    """Supervision of one view at the working resolution (tensors on the optimization device)."""

    view: object
    camera: object  # scaled Camera
    cam_from_world: torch.Tensor  # (4, 4)
    depth: torch.Tensor  # (h, w), 0 = invalid
    normal: torch.Tensor  # (h, w, 3) camera frame, 0 = invalid
    depth_valid: torch.Tensor  # (h, w) bool
    normal_valid: torch.Tensor  # (h, w) bool

    @functools.cached_property
    def has_targets(self) -> tuple:
        """(any valid depth, any valid normal): read from the device once per target, not once per step."""
        return bool(self.depth_valid.any()), bool(self.normal_valid.any())


def training_camera(camera, conf: PlaneOptConfig):
    """The camera a view of ``camera`` trains at under ``conf`` (``conf.downscale``, 0 = towards ``target_width``).

    The one definition of the training grid: the targets, the renders and the line term's regions all take it from
    the :class:`ViewTarget`, never from a scale factor of their own (a width ratio rounds the height differently:
    1752x1168 / 5 is 350x234, but 1168 x 350 / 1752 rounds to 233).
    """
    ds = working_downscale(conf.downscale, camera.width, conf.target_width)
    return camera if ds <= 1 else camera.scaled(1.0 / ds)


def view_target(frame, conf: PlaneOptConfig, device=None) -> ViewTarget:
    """The :class:`ViewTarget` of one :class:`~lipmap.planes.init.DepthFrame` (full-resolution depth).

    Normals come from ``view.load_normals()`` when the view has a normal map, else from the
    full-resolution depth (:func:`lipmap.normals.normals_from_depth`), then both maps are resized
    to the working resolution (:func:`training_camera`) by nearest sampling.
    """
    cam = training_camera(frame.camera, conf)
    normals = frame.view.load_normals() if getattr(frame.view, "normal_path", None) is not None else None
    if normals is None:
        step = conf.normal_step or max(2, frame.camera.width // 80)
        normals = normals_from_depth(frame.depth, frame.camera, step=step)
    depth = resize_nearest(frame.depth, cam.width, cam.height)
    normals = resize_nearest(normals, cam.width, cam.height)
    depth = np.where(np.isfinite(depth) & (depth > 0) & (depth <= conf.max_depth), depth, 0).astype(np.float32)
    normals = np.nan_to_num(normals).astype(np.float32)
    d = torch.as_tensor(depth, device=device)
    n = torch.as_tensor(normals, device=device)
    return ViewTarget(frame.view, cam, torch.as_tensor(frame.cam_from_world, dtype=torch.float32, device=device),
                      d, n, d > 0, n.norm(dim=-1) > 0.5)


def prepare_targets(frames: list, conf: PlaneOptConfig, device=None) -> list:
    """:class:`ViewTarget` per :class:`~lipmap.planes.init.DepthFrame`, all in memory (see :func:`view_target`)."""
    return [view_target(f, conf, device) for f in frames]


class TargetStore:
    """The :class:`ViewTarget` of each of ``views`` (those with depth and a pose), built from the view's files on
    first use and kept in an LRU of ``conf.cache_views``: memory does not grow with the number of views."""

    def __init__(self, views, conf: PlaneOptConfig, device=None):
        from ..frames import LRU

        self.views = list(views)
        self.frames = LazyDepthFrames(self.views)
        self._lru = LRU(lambda i: view_target(self.frames[i], conf, device), conf.cache_views)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> ViewTarget:
        return self._lru(int(i))

    def stats(self) -> dict:
        return self._lru.stats()

    def release(self) -> None:
        """Drop the cached targets (they are read again on use): the coarse ones once the fine phase begins."""
        self._lru.clear()
