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
- ``poselib.refine_absolute_pose(points2D, points3D, CameraPose, camera_dict, bundle_opt)`` is that same final
  bundle alone, so RANSAC and refinement can be split to choose the loss scale from the RANSAC inliers.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from lipmap import geometry as geo
from lipmap import logger
from lipmap.poses import make_T


@dataclass
class PointPoseConfig:
    """RANSAC + bundle options of the point-only initial pose (hloc's RANSAC threshold).

    The final refinement (on the RANSAC inliers) uses a Cauchy loss whose scale is ``loss_scale`` px, or with
    ``loss_scale=None`` the median reprojection error of the inliers at the RANSAC pose, clipped to
    [``min_loss_scale``, 0.5 x ``max_reproj_error``]. ``loss_scale=6.0`` is PoseLib's binding default (the former
    one here); COLMAP's refinement, the one of hloc's ``localize_sfm``, uses 1 px.
    """

    max_reproj_error: float = 12.0  # px, as hloc's localize_sfm
    min_matches: int = 4  # fewer -> success=False without calling PoseLib
    min_inliers: int = 4  # fewer RANSAC inliers -> success=False (the pose is still returned)
    seed: int = 0
    min_iterations: int = 1000
    max_iterations: int = 100_000
    success_prob: float = 0.9999
    # px; None: the inliers' own scale (fixed 6 px lets mismatches pull clean poses, 1 px drops real 1-3 px inliers)
    loss_scale: Optional[float] = None
    min_loss_scale: float = 1.0  # px, COLMAP's: below it the fit follows keypoint rounding (float16 in hloc's files)
    bundle: dict = field(default_factory=dict)  # more PoseLib BundleOptions of the refinement: {"max_iterations": 50}


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


def estimate_pose_points(p2d: np.ndarray, p3d: np.ndarray, camera, conf: Optional[PointPoseConfig] = None) -> dict:
    """Absolute pose from 2D-3D point matches (PoseLib LO-RANSAC + bundle refinement).

    Never raises for a bad query: too few or degenerate matches give ``success=False``.

    Args:
        p2d: (N, 2) pixel coordinates, COLMAP convention.
        p3d: (N, 3) world points.
        camera: :class:`lipmap.scene.Camera` or a PoseLib camera dict.
        conf: :class:`PointPoseConfig`.

    Returns:
        dict with **cam_from_world** (4, 4) or None, **inliers** (N,) bool, **n_inliers**,
        **n_matches**, **success**, and PoseLib's **info** (iterations, refinements, ...) on success.
    """
    conf = conf or PointPoseConfig()
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
    adaptive = conf.loss_scale is None
    # adaptive: RANSAC alone first (its LO already fits the inliers), then the bundle at the scale they show
    bundle = {"max_iterations": 0} if adaptive else {"loss_type": "CAUCHY", "loss_scale": float(conf.loss_scale),
                                                     **conf.bundle}
    idx = np.flatnonzero(finite)
    cam = _camera_dict(camera)
    try:
        pose, info = poselib.estimate_absolute_pose(p2d[idx], p3d[idx], cam, ransac, bundle)
        inl = np.asarray(info.pop("inliers"), dtype=bool)
        if adaptive and inl.sum() >= 4:
            scale = adaptive_loss_scale(pose, p2d[idx][inl], p3d[idx][inl], cam, conf)
            pose, _ = poselib.refine_absolute_pose(p2d[idx][inl], p3d[idx][inl], pose, cam,
                                                   {"loss_type": "CAUCHY", "loss_scale": scale, **conf.bundle})
            info["loss_scale"] = scale
    except Exception as e:  # PoseLib raises on malformed input only; keep the query as a failure
        logger.warning("PoseLib failed: %s", e)
        return _failure(n, f"PoseLib error: {e}")
    inliers = np.zeros(n, dtype=bool)
    inliers[idx] = inl
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


def adaptive_loss_scale(pose, p2d: np.ndarray, p3d: np.ndarray, camera: dict, conf: PointPoseConfig) -> float:
    """The Cauchy scale (px) of the adaptive refinement: the median reprojection error of the RANSAC inliers.

    Args:
        pose: PoseLib CameraPose (cam_from_world) found by RANSAC.
        p2d: (K, 2) inlier pixels; p3d: (K, 3) their world points; camera: PoseLib camera dict (any model).
    """
    import poselib

    cam = poselib.Camera(camera["model"], list(camera["params"]), int(camera["width"]), int(camera["height"]))
    x = p3d @ np.asarray(pose.R).T + np.asarray(pose.t)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(cam.project(x[:, :2] / x[:, 2:]) - p2d, axis=1)
    scale = np.median(err[np.isfinite(err)]) if np.isfinite(err).any() else np.inf
    return float(np.clip(scale, conf.min_loss_scale, 0.5 * conf.max_reproj_error))


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


# ----------------------------------------------------------------------------------------------
# joint point + line refinement
# ----------------------------------------------------------------------------------------------
@dataclass
class PointLinePoseConfig:
    """Options of the joint point+line pose (PoseLib PnPL: LO-RANSAC over points and lines + bundle).

    ``max_line_error`` is PoseLib's ``RansacOptions.max_epipolar_error``: the line inlier threshold,
    in pixels, on the distance of the projected 3D endpoints to the 2D line (PoseLib's default, 1 px,
    is tighter than LSD's endpoint noise on real images; chosen by measurement, see docs/localization.md).
    """

    max_reproj_error: float = 12.0  # px, points (as the point-only pose; a rescued query uses LineRescueConfig's)
    max_line_error: float = 2.0  # px, lines -> RansacOptions.max_epipolar_error
    min_lines: int = 3  # fewer line matches -> keep the point-only pose
    seed: int = 0
    # from a pose with hundreds of point inliers RANSAC is done long before 100 samples: 20 costs nothing in accuracy
    # and saves a third of the narrowing rounds' PnPL time (docs/localization.md, `-minit` variants)
    min_iterations: int = 20
    max_iterations: int = 10_000
    success_prob: float = 0.9999
    bundle: dict = field(default_factory=dict)
    # the final refinement: "poselib" is PoseLib's (one Cauchy scale, half the point threshold, for points and lines
    # alike); "weighted" gives each kind the Cauchy scale of its own RANSAC inliers' median residual, so a kind is
    # weighted by its noise (a Cauchy loss weighs small residuals by 1 / scale^2)
    refine: str = "weighted"
    min_scale: float = 1.0  # px: the weighted refinement's scales stay at or above it (COLMAP's point scale)
    line_scale_factor: float = 1.0  # the line scale, times this (weights lines by 1 / factor^2 beside the points)
    refine_iterations: int = 10  # of the weighted refinement, from RANSAC's locally optimised pose (100: the same poses, 30 % slower)
    # the weighted refinement stops once a step moves the pose less than this (PoseLib's step_tol; metres and radians
    # in one norm). From a pose that RANSAC or the last round already optimised, the last of its steps move it by
    # micrometres: 1e-5 (10 um) leaves poses within 0.1 mm of PoseLib's 1e-8 and halves a refinement's time
    refine_step_tol: float = 1e-5


def _point_line_input(p2d, p3d, lines2d, lines3d):
    """float64 (N, 2), (N, 3), (M, 2, 2), (M, 2, 3) arrays, and the result of a call that finds no pose."""
    p2d = np.asarray(p2d, dtype=np.float64).reshape(-1, 2)
    p3d = np.asarray(p3d, dtype=np.float64).reshape(-1, 3)
    l2 = np.asarray(lines2d, dtype=np.float64).reshape(-1, 2, 2)
    l3 = np.asarray(lines3d, dtype=np.float64).reshape(-1, 2, 3)
    fail = {"cam_from_world": None, "success": False, "n_inliers": 0, "n_line_inliers": 0,
            "line_inliers": np.zeros(len(l2), bool), "inliers": np.zeros(len(p2d), bool), "n_lines": len(l2)}
    return p2d, p3d, l2, l3, fail


def _camera_pose(T: np.ndarray):
    """A (4, 4) cam_from_world as PoseLib's CameraPose."""
    import poselib

    pose = poselib.CameraPose()
    pose.R, pose.t = np.asarray(T[:3, :3], dtype=np.float64), np.asarray(T[:3, 3], dtype=np.float64)
    return pose


def pnpl_pose(
    p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, lines3d: np.ndarray, camera,
    initial: Optional[np.ndarray] = None, conf: Optional[PointLinePoseConfig] = None,
) -> dict:
    """Pose from 2D-3D points and 2D-3D lines with ``poselib.estimate_absolute_pose_pnpl``.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3).
        lines2d: (M, 2, 2) query segments (COLMAP pixels); lines3d: (M, 2, 3) matched 3D segments.
        initial: (4, 4) cam_from_world to seed RANSAC with (the point-only pose).

    Returns:
        dict with **cam_from_world** (or None), **success**, **n_inliers** (points), **n_line_inliers**,
        **line_inliers** (M,) bool, **n_lines**; never raises for a bad query.
    """
    conf = conf or PointLinePoseConfig()
    p2d, p3d, l2, l3, fail = _point_line_input(p2d, p3d, lines2d, lines3d)
    n, m = len(p2d), len(l2)
    okp = np.isfinite(p2d).all(1) & np.isfinite(p3d).all(1)
    okl = np.isfinite(l2).all((1, 2)) & np.isfinite(l3).all((1, 2))
    if okl.sum() < conf.min_lines:
        return {**fail, "reason": f"{int(okl.sum())} line matches < {conf.min_lines}"}
    if okp.sum() + okl.sum() < 4:
        return {**fail, "reason": "fewer than 4 correspondences"}
    import poselib

    ransac = {
        "max_reproj_error": float(conf.max_reproj_error),
        "max_epipolar_error": float(conf.max_line_error),
        "seed": int(conf.seed),
        "min_iterations": int(conf.min_iterations),
        "max_iterations": int(conf.max_iterations),
        "success_prob": float(conf.success_prob),
    }
    kw = {}
    if initial is not None and np.all(np.isfinite(initial)):
        kw["initial_pose"] = _camera_pose(initial)
    li = np.flatnonzero(okl)
    pi = np.flatnonzero(okp)
    if conf.refine not in ("poselib", "weighted"):
        raise ValueError(f"PointLinePoseConfig.refine must be 'poselib' or 'weighted', got {conf.refine!r}")
    weighted = conf.refine == "weighted"
    try:
        pose, info = poselib.estimate_absolute_pose_pnpl(
            p2d[pi], p3d[pi], l2[li, 0], l2[li, 1], l3[li, 0], l3[li, 1], _camera_dict(camera), ransac,
            {"max_iterations": 0} if weighted else dict(conf.bundle), **kw,
        )
    except Exception as e:  # malformed input only; the query keeps its point-only pose
        logger.warning("PoseLib PnPL failed: %s", e)
        return {**fail, "reason": f"PoseLib error: {e}"}
    line_inl = np.zeros(m, bool)
    line_inl[li] = np.asarray(info.get("inliers_lines", np.zeros(len(li))), dtype=bool)
    pt_inl = np.zeros(n, bool)
    pt_inl[pi] = np.asarray(info.get("inliers_points", info.get("inliers", np.zeros(len(pi)))), dtype=bool)
    if weighted and pt_inl.sum() + line_inl.sum() >= 4:
        pose = _weighted_refinement(p2d[pt_inl], p3d[pt_inl], l2[line_inl], l3[line_inl], pose, camera, conf)
    T = make_T(np.asarray(pose.R), np.asarray(pose.t))
    ok = bool(np.all(np.isfinite(T)) and pt_inl.sum() + line_inl.sum() >= 4)
    return {"cam_from_world": T if np.all(np.isfinite(T)) else None, "success": ok, "n_inliers": int(pt_inl.sum()),
            "n_line_inliers": int(line_inl.sum()), "line_inliers": line_inl, "inliers": pt_inl, "n_lines": len(l2)}


def local_pnpl_pose(
    p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, lines3d: np.ndarray, camera, initial: np.ndarray,
    conf: Optional[PointLinePoseConfig] = None,
) -> dict:
    """:func:`pnpl_pose` without RANSAC, for a start whose inliers are already known: the points and lines within
    ``conf``'s thresholds at ``initial`` go straight into the same final refinement (``conf.refine``). From a pose
    that hundreds of point inliers fix to a pixel, RANSAC's samples only find that pose again.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3); lines2d: (M, 2, 2); lines3d: (M, 2, 3); initial: (4, 4).

    Returns:
        the dict of :func:`pnpl_pose`; its inliers are counted at the refined pose.
    """
    conf = conf or PointLinePoseConfig()
    p2d, p3d, l2, l3, fail = _point_line_input(p2d, p3d, lines2d, lines3d)
    okl = np.isfinite(l2).all((1, 2)) & np.isfinite(l3).all((1, 2))
    if okl.sum() < conf.min_lines:
        return {**fail, "reason": f"{int(okl.sum())} line matches < {conf.min_lines}"}
    initial = np.asarray(initial, dtype=np.float64)
    rp, rl = pnpl_residuals(p2d, p3d, l2, l3, initial, camera)
    pt_inl, line_inl = _within_thresholds(rp, rl, conf.max_reproj_error, conf.max_line_error)
    if pt_inl.sum() + line_inl.sum() < 4:
        return {**fail, "reason": "fewer than 4 correspondences within the thresholds at the start"}
    if conf.refine == "weighted":
        pose = _weighted_refinement(p2d[pt_inl], p3d[pt_inl], l2[line_inl], l3[line_inl], _camera_pose(initial),
                                    camera, conf, residuals=(rp[pt_inl], rl[line_inl]))
        T = make_T(np.asarray(pose.R), np.asarray(pose.t))
    else:  # PoseLib's one Cauchy scale for both kinds, half the point threshold
        half = 0.5 * conf.max_reproj_error
        r = refine_pnpl_pose(p2d[pt_inl], p3d[pt_inl], l2[line_inl], l3[line_inl], camera, initial, half, half,
                             conf.max_reproj_error, conf.max_line_error)
        if r["cam_from_world"] is None:
            return {**fail, "reason": r["reason"]}
        T = r["cam_from_world"]
    return _pose_result(T, p2d, p3d, l2, l3, camera, conf.max_reproj_error, conf.max_line_error, fail)


def _pose_result(T, p2d, p3d, l2, l3, camera, max_reproj_error: float, max_line_error: float, fail: dict) -> dict:
    """The dict of :func:`pnpl_pose` for a refined pose ``T``: its inliers counted at ``T`` (``fail`` when ``T``
    is not finite)."""
    if not np.all(np.isfinite(T)):
        return {**fail, "reason": "refinement diverged"}
    pt_inl, line_inl = inliers_at(p2d, p3d, l2, l3, T, camera, max_reproj_error, max_line_error)
    return {"cam_from_world": T, "success": bool(pt_inl.sum() + line_inl.sum() >= 4), "n_inliers": int(pt_inl.sum()),
            "n_line_inliers": int(line_inl.sum()), "line_inliers": line_inl, "inliers": pt_inl, "n_lines": len(l2)}


def pnpl_residuals(p2d, p3d, lines2d, lines3d, T: np.ndarray, camera) -> tuple:
    """Pixel residuals at pose ``T``: of each point :math:`(N,)` (reprojection error; inf behind the camera) and of
    each line's two 3D endpoints to its detection's infinite line :math:`(M, 2)` (PoseLib's line residual)."""
    uv, z = geo.project_points(np.asarray(p3d, dtype=float).reshape(-1, 3), T, camera)
    rp = np.where(np.asarray(z) > 0, np.linalg.norm(np.asarray(uv) - np.asarray(p2d).reshape(-1, 2), axis=1), np.inf)
    X = np.asarray(lines3d, dtype=float).reshape(-1, 3)
    uvl, zl = geo.project_points(X, T, camera)
    ends = np.asarray(uvl).reshape(-1, 2, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        rl = geo.point_line_distance(ends, np.asarray(lines2d, dtype=float).reshape(-1, 1, 2, 2))
    rl = np.where(np.asarray(zl).reshape(-1, 2) > 0, rl, np.inf)
    return rp, rl


def inliers_at(p2d, p3d, l2, l3, T, camera, max_reproj_error: float, max_line_error: float) -> tuple:
    """The points (N,) and lines (M,) within the thresholds at pose ``T`` (a line by both projected endpoints)."""
    return _within_thresholds(*pnpl_residuals(p2d, p3d, l2, l3, T, camera), max_reproj_error, max_line_error)


def _within_thresholds(rp, rl, max_reproj_error: float, max_line_error: float) -> tuple:
    with np.errstate(invalid="ignore"):
        return rp <= max_reproj_error, np.all(rl <= max_line_error, axis=1)


def _weighted_refinement(p2d, p3d, l2, l3, pose, camera, conf: PointLinePoseConfig, residuals=None):
    """PoseLib's point+line refinement from ``pose`` over the inliers, each kind at the Cauchy scale of its own median
    residual (at least ``conf.min_scale``, at most half its inlier threshold). ``residuals``: those of
    :func:`pnpl_residuals` at ``pose``, when the caller has them."""
    import poselib

    if residuals is None:
        residuals = pnpl_residuals(p2d, p3d, l2, l3, make_T(np.asarray(pose.R), np.asarray(pose.t)), camera)
    rp, rl = residuals

    def scale(r, thr):
        r = r[np.isfinite(r)]
        return float(np.clip(np.median(r) if len(r) else thr, conf.min_scale, 0.5 * thr))

    sp = scale(rp, conf.max_reproj_error)
    sl = scale(rl.ravel(), conf.max_line_error) * conf.line_scale_factor
    bundle = {"loss_type": "CAUCHY", "max_iterations": conf.refine_iterations, "step_tol": conf.refine_step_tol,
              **conf.bundle}
    try:
        refined, _ = poselib.refine_absolute_pose_pnpl(
            p2d, p3d, l2[:, 0], l2[:, 1], l3[:, 0], l3[:, 1], pose, _camera_dict(camera),
            {**bundle, "loss_scale": sp}, {**bundle, "loss_scale": sl})
    except Exception as e:  # malformed input only: the RANSAC pose stands
        logger.warning("PoseLib PnPL refinement failed: %s", e)
        return pose
    return refined


def refine_pnpl_pose(
    p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, lines3d: np.ndarray, camera, initial: np.ndarray,
    point_scale: float, line_scale: float, max_reproj_error: float, max_line_error: float,
) -> dict:
    """Robust point+line refinement from ``initial`` (``poselib.refine_absolute_pose_pnpl``, Cauchy losses), without
    RANSAC: for a start already near the pose, one refinement instead of a thousand minimal samples.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3); lines2d: (M, 2, 2); lines3d: (M, 2, 3); initial: (4, 4).
        point_scale, line_scale: px, the Cauchy scales (residuals well beyond them barely pull).
        max_reproj_error, max_line_error: px, the inlier thresholds counted at the refined pose (a line's residual
            is the farther of its projected 3D endpoints from the detection's infinite line, as PoseLib's).

    Returns:
        the dict of :func:`pnpl_pose`.
    """
    import poselib

    p2d, p3d, l2, l3, fail = _point_line_input(p2d, p3d, lines2d, lines3d)
    if len(p2d) + len(l2) < 4:
        return {**fail, "reason": "fewer than 4 correspondences"}
    try:
        pose, _ = poselib.refine_absolute_pose_pnpl(
            p2d, p3d, l2[:, 0], l2[:, 1], l3[:, 0], l3[:, 1], _camera_pose(initial), _camera_dict(camera),
            {"loss_type": "CAUCHY", "loss_scale": float(point_scale)},
            {"loss_type": "CAUCHY", "loss_scale": float(line_scale)})
    except Exception as e:  # malformed input only
        logger.warning("PoseLib PnPL refinement failed: %s", e)
        return {**fail, "reason": f"PoseLib error: {e}"}
    return _pose_result(make_T(np.asarray(pose.R), np.asarray(pose.t)), p2d, p3d, l2, l3, camera, max_reproj_error,
                        max_line_error, fail)
