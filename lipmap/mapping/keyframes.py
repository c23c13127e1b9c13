"""Keyframe selection by camera motion: the views a map is built from, so that its cost follows the scene, not the frame rate.

A view becomes a keyframe when the camera has moved more than ``min_translation`` or turned more than
``min_rotation_deg`` since the last keyframe, or when its frame number is ``max_frame_gap`` or more past
the last keyframe's (a SLAM front end's rules: motion, and a bound on the time between keyframes). The
first view of each sequence is always one. The plane optimization, the line extraction and the tracks use
the keyframes.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .. import logger
from ..poses import camera_center, rotation_error_deg


@dataclass
class KeyframeConfig:
    """When a view is a new keyframe; both motion thresholds 0 keep every view."""

    # 5 cm / 5 deg: the RedKitchen mini (7 cm, 3 deg between frames) keeps nearly every frame by motion, while
    # a 30 Hz sequence keeps about one frame in seven
    min_translation: float = 0.05  # metres since the last keyframe
    min_rotation_deg: float = 5.0  # degrees since the last keyframe
    # an already subsampled set (every 5th frame or sparser) stays whole: thinning it again halved the
    # held-out split's views and edge lines; at 30 Hz it keeps one frame in five where motion kept one in seven
    max_frame_gap: int = 5  # frames since the last keyframe (number in the image name; 0: off)

    @property
    def enabled(self) -> bool:
        return self.min_translation > 0 or self.min_rotation_deg > 0


def _sequence(name: str) -> str:
    return name.rsplit("/", 1)[0] if "/" in name else ""


def select_keyframes(views: Sequence, conf: KeyframeConfig | None = None) -> np.ndarray:
    """Indices of the keyframes among ``views`` (in their order, which should be the capture order).

    Args:
        views: :class:`~lipmap.scene.View` with ``cam_from_world``; views without a pose are skipped.

    Returns:
        :math:`(K,)` int64 increasing indices.
    """
    conf = conf or KeyframeConfig()
    if not conf.enabled:
        return np.array([i for i, v in enumerate(views) if v.cam_from_world is not None], dtype=np.int64)
    keep, last = [], None
    for i, v in enumerate(views):
        if v.cam_from_world is None:
            continue
        T = np.asarray(v.cam_from_world, dtype=float)
        if (last is None or _sequence(v.name) != _sequence(views[last].name)
                or _moved(views[last].cam_from_world, T, conf) or _frame_gap(views[last].name, v.name, conf)):
            keep.append(i)
            last = i
    return np.asarray(keep, dtype=np.int64)


def frame_number(name: str) -> int | None:
    """The frame number in an image name: the last run of digits before the first dot of its file name
    (``seq-01/frame-000120.color.png`` -> 120); None when there is none."""
    digits = re.findall(r"\d+", name.rsplit("/", 1)[-1].split(".", 1)[0])
    return int(digits[-1]) if digits else None


def _frame_gap(last_name: str, name: str, conf: KeyframeConfig) -> bool:
    if conf.max_frame_gap <= 0:
        return False
    a, b = frame_number(last_name), frame_number(name)
    return a is not None and b is not None and b - a >= conf.max_frame_gap


def _moved(T_last: np.ndarray, T: np.ndarray, conf: KeyframeConfig) -> bool:
    if conf.min_translation > 0 and np.linalg.norm(camera_center(T) - camera_center(T_last)) > conf.min_translation:
        return True
    return conf.min_rotation_deg > 0 and rotation_error_deg(T_last[:3, :3], T[:3, :3]) > conf.min_rotation_deg


def keyframe_views(views: Sequence, conf: KeyframeConfig | None = None) -> list:
    """The keyframe views (see :func:`select_keyframes`), logged."""
    conf = conf or KeyframeConfig()
    idx = select_keyframes(views, conf)
    if len(idx) < len(views):
        logger.info("keyframes: %d of %d views (moved > %.0f cm, turned > %.0f deg or %d frames on)", len(idx),
                    len(views), conf.min_translation * 100, conf.min_rotation_deg, conf.max_frame_gap)
    return [views[i] for i in idx]


__all__ = ["KeyframeConfig", "frame_number", "keyframe_views", "select_keyframes"]
