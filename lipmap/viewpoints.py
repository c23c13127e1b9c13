"""Virtual cameras for figures: the world's up, a camera looking at a point, the scene's box, an overview camera.

Geometry only (NumPy, no drawing): :mod:`lipmap.viz` and :mod:`lipmap.viz3d` place their views with it, and
tests build posed views with :func:`look_at`.
"""
from __future__ import annotations

import numpy as np


def up_direction(views=None, points=None) -> np.ndarray:
    """World "up" :math:`(3,)`.

    From cameras: handheld and robot cameras keep their image x axis horizontal (little roll) while
    pitching freely, so up is the direction most orthogonal to all image x axes, signed against the
    mean image-down axis. Without cameras: the axis of least spread of ``points`` (rooms are wider
    than tall), signed to +z.
    """
    if views:
        R = np.array([np.asarray(v.cam_from_world)[:3, :3] for v in views if v.cam_from_world is not None])
        if len(R) >= 2:
            _, _, vt = np.linalg.svd(R[:, 0, :], full_matrices=False)
            up = vt[-1]
            down = R[:, 1, :].mean(0)
            if abs(up @ down) > 0.2 * np.linalg.norm(down):
                return -up * np.sign(up @ down)
        if len(R):
            down = R[:, 1, :].mean(0)
            return -down / np.linalg.norm(down)
    if points is not None and len(points) >= 3:
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
        return vt[2] * (1 if vt[2][2] >= 0 else -1)
    return np.array([0.0, 0.0, 1.0])


def look_at(center, target, up) -> np.ndarray:
    """cam_from_world (4, 4) of a camera at ``center`` looking at ``target`` with image-up ~ ``up``."""
    from .poses import make_T

    center, target, up = (np.asarray(x, dtype=float) for x in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-6:  # looking straight along up: any image x works
        x = np.cross(z, np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return make_T(R, -R @ center)


def scene_frame(points, up) -> dict:
    """Robust (1st-99th percentile) box of ``points`` in a frame with axes (e1, e2, up), e1 the main
    horizontal direction: ``{"center", "axes" (3, 3) rows, "lo" (3,), "hi" (3,)}`` (box coordinates)."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    c0 = np.median(p, axis=0)
    flat = (p - c0) - np.outer((p - c0) @ up, up)
    _, _, vt = np.linalg.svd(flat[:: max(1, len(flat) // 5000)], full_matrices=False)
    e1 = vt[0] - (vt[0] @ up) * up
    e1 /= np.linalg.norm(e1)
    axes = np.stack([e1, np.cross(up, e1), up])
    q = (p - c0) @ axes.T
    lo, hi = np.percentile(q, 1, axis=0), np.percentile(q, 99, axis=0)
    center = c0 + ((lo + hi) / 2) @ axes
    return {"center": center, "axes": axes, "lo": lo - (lo + hi) / 2, "hi": hi - (lo + hi) / 2}


def box_edges(frame: dict) -> np.ndarray:
    """The 12 edges (12, 2, 3) of the box of :func:`scene_frame`, in world coordinates."""
    lo, hi = frame["lo"], frame["hi"]
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    corners = frame["center"] + corners @ frame["axes"]
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return np.stack([corners[[a, b]] for a, b in pairs])


def overview_camera(points, up, width: int = 960, height: int = 720, elevation_deg: float = 40.0,
                    azimuth_deg: float = 35.0, fov_deg: float = 45.0, margin: float = 0.04):
    """An oblique virtual camera outside the bounding box of ``points`` that sees all of them.

    The camera sits on the bounding sphere of the points' robust box (:func:`scene_frame`), raised by
    ``elevation_deg`` above the horizontal plane, at ``azimuth_deg`` from the main horizontal axis;
    focal length and principal point are then fitted so the box fills the image.

    Returns:
        cam_from_world (4, 4), :class:`~lipmap.scene.Camera` and the scene frame (see :func:`scene_frame`).
    """
    from .scene import Camera

    frame = scene_frame(points, up)
    e1, e2, up = frame["axes"]
    center = frame["center"]
    radius = max(np.linalg.norm(frame["hi"] - frame["lo"]) / 2, 1e-3)
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    d = np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up
    dist = radius / np.sin(np.radians(fov_deg) / 2)
    T = look_at(center + dist * d, center, up)
    pc = box_edges(frame).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    f = (1 - 2 * margin) * min(width / max(np.ptp(xn), 1e-6), height / max(np.ptp(yn), 1e-6))
    cx = width / 2 - f * (xn.min() + xn.max()) / 2
    cy = height / 2 - f * (yn.min() + yn.max()) / 2
    return T, Camera(width, height, (f, f, cx, cy)), frame
