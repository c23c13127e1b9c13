"""Small hand-made scenes with known answers, shared by the tests of mapping and localization."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .poses import make_T
from .scene import Camera, View

SMALL_CAMERA = Camera(320, 240, (262.5, 262.5, 160.0, 120.0))


def rect(center, half_x: float, half_y: float, axes=np.eye(3)) -> np.ndarray:
    """Corners (4, 3) of a rectangle in the paper's vertex order v1..v4 (axes rows: X, Y, normal)."""
    c = np.asarray(center, float)
    X, Y = np.asarray(axes)[0] * half_x, np.asarray(axes)[1] * half_y
    return np.stack([c + X + Y, c + X - Y, c - X - Y, c - X + Y])


def raycast_depth(corners: np.ndarray, view) -> np.ndarray:
    """True z-depth (H, W) of ``view`` by ray casting rectangles (K, 4, 3); 0 where no rectangle is hit."""
    from .mapping.assign import PlaneRaycaster, plane_depth

    return plane_depth(PlaneRaycaster(corners), view)


def wall_scene(camera: Camera = SMALL_CAMERA):
    """A 1.2 x 0.8 m panel 3 m in front of a large back wall, seen by three cameras.

    Returns corners (2, 4, 3) - panel first - and three views.
    """
    wall = rect([0.1, -0.05, 3.0], 0.6, 0.4)
    back = rect([0, 0, 5.0], 4, 3)
    views = []
    for i, (yaw, tx) in enumerate([(0.0, 0.0), (4.0, 0.15), (-5.0, -0.2)]):
        R = Rotation.from_euler("y", yaw, degrees=True).as_matrix()
        views.append(View(f"v{i}", camera, make_T(R, [tx, 0.02 * i, 0]), color_path=None))
    return np.stack([wall, back]), views


def kill_at(event: str, count: int = 1):
    """A pipeline ``checkpoint`` callback that SIGKILLs this process at the ``count``-th ``event``.

    The pipelines call ``checkpoint(event)`` right after an artifact or a journal entry is written, so
    a test can kill a run exactly there and check that a rerun resumes from what it left and ends with
    the same results as an uninterrupted run.
    """
    import os
    import signal

    seen = {"n": 0}

    def checkpoint(name: str) -> None:
        if name == event:
            seen["n"] += 1
            if seen["n"] >= count:
                os.kill(os.getpid(), signal.SIGKILL)

    return checkpoint
