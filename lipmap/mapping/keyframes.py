"""Keyframe selection by camera motion: the views a map is built from, so that its cost follows the scene, not the frame rate.

A view becomes a keyframe when the camera has moved more than ``min_translation`` or turned more than
``min_rotation_deg`` since the last keyframe (a SLAM front end's rule). The first view of each
sequence is always one. The plane optimization, the line extraction and the tracks use the keyframes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .. import logger
from ..poses import camera_center, rotation_error_deg


@dataclass
class KeyframeConfig:
    """When a view is a new keyframe; both thresholds 0 keep every view."""

    # 5 cm / 5 deg: the RedKitchen mini (7 cm, 3 deg between frames) keeps nearly every frame, while a
    # 30 Hz sequence (1-2 cm per frame) keeps about one frame in four
    min_translation: float = 0.05  # metres since the last keyframe
    min_rotation_deg: float = 5.0  # degrees since the last keyframe

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
        if last is None or _sequence(v.name) != _sequence(views[last].name) or _moved(views[last].cam_from_world, T, conf):
            keep.append(i)
            last = i
    return np.asarray(keep, dtype=np.int64)


def _moved(T_last: np.ndarray, T: np.ndarray, conf: KeyframeConfig) -> bool:
    if conf.min_translation > 0 and np.linalg.norm(camera_center(T) - camera_center(T_last)) > conf.min_translation:
        return True
    return conf.min_rotation_deg > 0 and rotation_error_deg(T_last[:3, :3], T[:3, :3]) > conf.min_rotation_deg


def keyframe_views(views: Sequence, conf: KeyframeConfig | None = None) -> list:
    """The keyframe views (see :func:`select_keyframes`), logged."""
    conf = conf or KeyframeConfig()
    idx = select_keyframes(views, conf)
    if len(idx) < len(views):
        logger.info("keyframes: %d of %d views (moved > %.0f cm or turned > %.0f deg)", len(idx), len(views),
                    conf.min_translation * 100, conf.min_rotation_deg)
    return [views[i] for i in idx]


__all__ = ["KeyframeConfig", "select_keyframes", "keyframe_views"]
