"""Rigid pose conversions: the ONE place for 4x4 <-> (R, t) <-> quaternions (wxyz / xyzw).

Conventions:
- Poses are named by their frames: ``cam_from_world`` maps world points into the camera,
  ``x_cam = R @ x_world + t`` (pycolmap, PoseLib, hloc results files).
- Quaternions are ``wxyz`` (PoseLib, COLMAP, hloc) unless a function says ``xyzw`` (scipy).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import InputError


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3, 3) rotation and (3,) translation -> (4, 4) homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def split_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(4, 4) -> (R (3, 3), t (3,))."""
    T = np.asarray(T, dtype=float)
    return T[:3, :3].copy(), T[:3, 3].copy()


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, without a general matrix inverse."""
    R, t = split_T(T)
    return make_T(R.T, -R.T @ t)


def qvec_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """Unit (or not) quaternion wxyz -> rotation matrix (normalised first)."""
    q = np.asarray(q, dtype=float).reshape(4)
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def R_to_qvec_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion wxyz with w >= 0 (a canonical sign)."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q[..., [3, 0, 1, 2]]


def T_from_qt(q_wxyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    return make_T(qvec_wxyz_to_R(q_wxyz), t)


def qt_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, t = split_T(T)
    return R_to_qvec_wxyz(R), t


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation :math:`(3, 3)` taking unit vector ``a`` to unit vector ``b`` (Rodrigues; about any axis
    across ``a`` when they are opposite). As scipy's ``Rotation.align_vectors(b, a)`` for one pair, 100x cheaper."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)  # half a turn about it
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest proper rotation (SVD) to a 3x3 matrix: 7-Scenes pose files are not exactly orthonormal."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


def check_rigid(T: np.ndarray, path=None, tol: float = 1e-2) -> np.ndarray:
    """Validate a 4x4 rigid transform read from a file; return it with an exactly orthonormal rotation.

    Raises InputError for NaN/inf entries, a bad last row, or a rotation block that is far from
    orthonormal (tol on |R R^T - I|) or a reflection.
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise InputError(f"pose must be a 4x4 matrix, got shape {T.shape}", path)
    if not np.all(np.isfinite(T)):
        raise InputError("pose contains NaN or infinite values", path)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(f"pose last row must be [0 0 0 1], got {T[3].tolist()}", path)
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or np.linalg.det(R) <= 0:
        raise InputError(
            f"pose is not rigid: rotation block deviates from orthonormal by {err:.3g} (det {np.linalg.det(R):.3g})",
            path,
        )
    return make_T(project_to_rotation(R), T[:3, 3])


def camera_center(cam_from_world: np.ndarray) -> np.ndarray:
    """World position of the camera centre, C = -R^T t."""
    R, t = split_T(cam_from_world)
    return -R.T @ t


def rotation_error_deg(R_gt: np.ndarray, R_est: np.ndarray) -> float:
    """Angle of R_gt^T R_est in degrees (hloc's 7-Scenes rotation error)."""
    cos = (np.trace(np.asarray(R_gt).T @ np.asarray(R_est)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def pose_errors(cam_from_world_gt: np.ndarray, cam_from_world_est: np.ndarray) -> tuple[float, float]:
    """(translation error in metres = camera-centre distance, rotation error in degrees)."""
    dt = float(np.linalg.norm(camera_center(cam_from_world_gt) - camera_center(cam_from_world_est)))
    dr = rotation_error_deg(cam_from_world_gt[:3, :3], cam_from_world_est[:3, :3])
    return dt, dr
