"""Depth registration: re-project a depth map from the depth sensor into the colour camera."""
from __future__ import annotations

import numpy as np

from ..geometry import backproject_depth, project_cam_points

# 7-Scenes / Kinect v1: colour_from_depth estimated from pose.txt (depth camera, KinectFusion) and the
# dSLAM pseudo-GT (colour camera) of RedKitchen frames 0-490: colour_from_depth = dslam_cw @ posetxt_wc,
# constant to < 0.1 mm over the frames. Besides the 2.56 cm baseline along x it holds a ~0.65 deg
# rotation; ``lipmap-loc info`` and the tests re-estimate it from the pgt files when present.
SEVENSCENES_COLOR_FROM_DEPTH = np.array(
    [
        [0.99997, 0.00267, -0.00790, -0.02555],
        [-0.00274, 0.99996, -0.00815, 0.00010],
        [0.00788, 0.00817, 0.99994, 0.00201],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def splat_depth(points_cam: np.ndarray, camera) -> np.ndarray:
    """Z-buffered nearest-pixel depth image (H, W) of camera-frame points; 0 where nothing lands."""
    uv, z = project_cam_points(points_cam, camera) if len(points_cam) else (np.zeros((0, 2)), np.zeros(0))
    col = np.floor(uv[:, 0]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
    row = np.floor(uv[:, 1]).astype(np.int64, copy=False) if len(uv) else np.zeros(0, np.int64)
    ok = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    flat = row[ok] * camera.width + col[ok]
    zs = z[ok]
    out = np.full(camera.width * camera.height, np.inf, dtype=np.float64)
    np.minimum.at(out, flat, zs)
    out[~np.isfinite(out)] = 0.0
    return out.reshape(camera.height, camera.width).astype(np.float32)


def register_depth(depth: np.ndarray, depth_camera, color_camera, color_from_depth) -> np.ndarray:
    """Depth (H_d, W_d) metres in the depth camera -> depth (H_c, W_c) metres in the colour camera.

    Back-project with the depth intrinsics, move by ``color_from_depth`` (4x4), re-project with the
    colour intrinsics, keep the nearest surface per pixel. Colour pixels that no depth pixel reaches
    stay 0 (invalid); single-pixel cracks from the focal-length change are filled from their
    neighbours so the registered map is as dense as the sensor's.
    """
    pts, _ = backproject_depth(depth, depth_camera)
    T = np.eye(4) if color_from_depth is None else np.asarray(color_from_depth, dtype=float)
    pts = pts @ T[:3, :3].T + T[:3, 3]
    out = splat_depth(pts, color_camera)
    return _fill_cracks(out)


def _fill_cracks(depth: np.ndarray) -> np.ndarray:
    """Fill isolated empty pixels with the min of their valid 3x3 neighbours (5+ valid neighbours)."""
    import cv2

    valid = depth > 0
    big = np.where(valid, depth, np.inf).astype(np.float32)
    nb_min = cv2.erode(big, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    count = cv2.filter2D(valid.astype(np.float32), -1, np.ones((3, 3), np.float32), borderType=cv2.BORDER_CONSTANT)
    fill = (~valid) & (count >= 5) & np.isfinite(nb_min)
    out = depth.copy()
    out[fill] = nb_min[fill]
    return out


def cross_view_depth_residuals(depth_i, view_i, depth_j, view_j, max_residual: float = 0.5) -> np.ndarray:
    """|z_projected - z_observed| (metres) of frame i's depth points re-projected into frame j.

    Back-projects the valid depth of view i (colour camera, ``view_i.cam_from_world``), moves the
    points into view j, and compares their depth with view j's depth map at the landing pixel.
    Residuals above ``max_residual`` (occlusions) are dropped. Measures how consistent depth and poses
    are: registration that is right makes it small.
    """
    pts, _ = backproject_depth(depth_i, view_i.camera)
    j_from_i = view_j.cam_from_world @ np.linalg.inv(view_i.cam_from_world)
    pts = pts @ j_from_i[:3, :3].T + j_from_i[:3, 3]
    uv, z = project_cam_points(pts, view_j.camera)
    ok = z > 0.1
    col = np.floor(uv[ok, 0]).astype(int)
    row = np.floor(uv[ok, 1]).astype(int)
    z = z[ok]
    inb = (col >= 0) & (col < view_j.camera.width) & (row >= 0) & (row < view_j.camera.height)
    zj = depth_j[row[inb], col[inb]]
    res = np.abs(z[inb] - zj)[zj > 0]
    return res[res < max_residual]
