"""Camera pose estimation with PoseLib: the initial pose from 2D-3D points (this part), and the joint
point+line refinement (added beside it).

PoseLib 2.0.5 facts this relies on (pinned by tests/test_estimate.py):
- ``poselib.estimate_absolute_pose(points2D, points3D, camera_dict, ransac_opt, bundle_opt)`` returns
  (CameraPose, info); ``CameraPose.R``/``.t`` are cam_from_world (x_cam = R x_world + t), ``.q`` wxyz.
- Its PINHOLE model is u = fx x/z + cx: pixel coordinates must use the same convention as the
  intrinsics. Ours are COLMAP's (pixel centre at +0.5; 7-Scenes cx = 320 is the image centre), so
  2D points go in COLMAP convention - half a pixel off biases the pose (test_pixel_convention).
- RANSAC is seeded through ``ransac_opt["seed"]`` (default 0 in PoseLib): same input -> same pose.
- Without ``bundle_opt["loss_scale"]`` the binding uses 0.5 x max_reproj_error (Cauchy loss).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from lipmap import logger
from lipmap.poses import make_T


@dataclass
class PointPoseConf:
    """RANSAC + bundle options of the point-only initial pose (hloc's defaults)."""

    max_reproj_error: float = 12.0  # px, as hloc's localize_sfm
    min_matches: int = 4  # fewer -> success=False without calling PoseLib
    min_inliers: int = 4  # fewer RANSAC inliers -> success=False (the pose is still returned)
    seed: int = 0
    min_iterations: int = 1000
    max_iterations: int = 100_000
    success_prob: float = 0.9999
    bundle: dict = field(default_factory=dict)  # extra PoseLib BundleOptions, e.g. {"loss_scale": 1.0}


def _camera_dict(camera) -> dict:
    if isinstance(camera, dict):
        return camera
    return camera.to_dict()


def _failure(n: int, reason: str) -> dict:
    return {
        "cam_from_world": None,
        "inliers": np.zeros(n, dtype=bool),
        "n_inliers": 0,
        "n_matches": n,
        "success": False,
        "reason": reason,
    }


def estimate_pose_points(p2d: np.ndarray, p3d: np.ndarray, camera, conf: Optional[PointPoseConf] = None) -> dict:
    """Absolute pose from 2D-3D point matches (PoseLib LO-RANSAC + bundle refinement).

    Never raises for a bad query: too few or degenerate matches give ``success=False``.

    Args:
        p2d: (N, 2) pixel coordinates, COLMAP convention.
        p3d: (N, 3) world points.
        camera: :class:`lipmap.scene.Camera` or a PoseLib camera dict.
        conf: :class:`PointPoseConf`.

    Returns:
        dict with **cam_from_world** (4, 4) or None, **inliers** (N,) bool, **n_inliers**,
        **n_matches**, **success**, and PoseLib's **info** (iterations, refinements, ...) on success.
    """
    conf = conf or PointPoseConf()
    p2d = np.asarray(p2d, dtype=np.float64).reshape(-1, 2)
    p3d = np.asarray(p3d, dtype=np.float64).reshape(-1, 3)
    n = len(p2d)
    if len(p3d) != n:
        raise ValueError(f"p2d has {n} points, p3d has {len(p3d)}")
    finite = np.isfinite(p2d).all(1) & np.isfinite(p3d).all(1)
    if finite.sum() < max(conf.min_matches, 4):
        return _failure(n, f"{int(finite.sum())} matches < {max(conf.min_matches, 4)}")
    import poselib

    ransac = {
        "max_reproj_error": float(conf.max_reproj_error),
        "seed": int(conf.seed),
        "min_iterations": int(conf.min_iterations),
        "max_iterations": int(conf.max_iterations),
        "success_prob": float(conf.success_prob),
    }
    idx = np.flatnonzero(finite)
    try:
        pose, info = poselib.estimate_absolute_pose(p2d[idx], p3d[idx], _camera_dict(camera), ransac, dict(conf.bundle))
    except Exception as e:  # PoseLib raises on malformed input only; keep the query as a failure
        logger.warning("PoseLib failed: %s", e)
        return _failure(n, f"PoseLib error: {e}")
    inliers = np.zeros(n, dtype=bool)
    inliers[idx] = np.asarray(info.pop("inliers"), dtype=bool)
    T = make_T(np.asarray(pose.R), np.asarray(pose.t))
    n_inl = int(inliers.sum())
    ok = bool(np.all(np.isfinite(T)) and n_inl >= max(conf.min_inliers, 4))
    out = {
        "cam_from_world": T if np.all(np.isfinite(T)) else None,
        "inliers": inliers,
        "n_inliers": n_inl,
        "n_matches": n,
        "success": ok,
        "info": info,
    }
    if not ok:
        out["reason"] = f"{n_inl} inliers < {max(conf.min_inliers, 4)}"
    return out


def subsample_matches(n: int, N: Optional[int], seed: int, query_name: str) -> np.ndarray:
    """A seeded random subset of N of n point matches, the same for every run and method.

    The random stream depends only on (seed, query_name) - not on the order queries are processed
    or on Python's salted ``hash`` - so point-only and point+line can be compared on exactly the
    same subset (emulating a low-texture query).

    Returns:
        sorted indices (min(n, N),) into the matches; all of them when N is None or N >= n.
    """
    if N is None or N >= n:
        return np.arange(n)
    if N < 0:
        raise ValueError(f"N must be >= 0, got {N}")
    digest = hashlib.sha256(query_name.encode("utf-8")).digest()
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, *np.frombuffer(digest[:16], dtype=np.uint32).tolist()])
    return np.sort(rng.choice(n, size=N, replace=False))
