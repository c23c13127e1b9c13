import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap import InputError
from lipmap import poses


def _random_T(seed):
    rng = np.random.default_rng(seed)
    return poses.make_T(Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3))


class TestConversions:
    def test_quaternion_roundtrip(self):
        for s in range(5):
            T = _random_T(s)
            q, t = poses.qt_from_T(T)
            assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
            np.testing.assert_allclose(poses.T_from_qt(q, t), T, atol=1e-12)

    def test_convention_pin_wxyz(self):
        # 90 deg about z: wxyz = (cos45, 0, 0, sin45); a swapped order would give a different matrix.
        q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
        R = poses.qvec_wxyz_to_R(q)
        np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
        np.testing.assert_allclose(poses.wxyz_to_xyzw(q), [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
        np.testing.assert_allclose(poses.xyzw_to_wxyz(poses.wxyz_to_xyzw(q)), q)

    def test_invert_and_center(self):
        T = _random_T(7)
        np.testing.assert_allclose(poses.invert_T(T) @ T, np.eye(4), atol=1e-12)
        C = poses.camera_center(T)
        np.testing.assert_allclose(T[:3, :3] @ C + T[:3, 3], 0, atol=1e-12)

    def test_pose_errors_known(self):
        T = _random_T(1)
        R_delta = Rotation.from_rotvec([0, 0, np.radians(3.0)]).as_matrix()
        T2 = T.copy()
        T2[:3, :3] = R_delta @ T[:3, :3]
        T2[:3, 3] = R_delta @ T[:3, 3]  # rotate about the camera centre: centre unchanged
        dt, dr = poses.pose_errors(T, T2)
        assert dt < 1e-9 and abs(dr - 3.0) < 1e-9
        T3 = poses.make_T(T[:3, :3], T[:3, 3] + [0.05, 0, 0])
        dt, dr = poses.pose_errors(T, T3)
        assert abs(dt - 0.05) < 1e-12 and dr < 1e-6


class TestCheckRigid:
    def test_projects_nearly_orthonormal(self):
        T = _random_T(2)
        T[:3, :3] *= 1.00005  # like 7-Scenes files: trace up to 3.00015
        out = poses.check_rigid(T)
        np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)

    @pytest.mark.parametrize(
        "bad,msg",
        [
            (lambda T: T.__setitem__((0, 0), np.nan), "NaN"),
            (lambda T: T.__setitem__((0, slice(0, 3)), [2.0, 0, 0]), "not rigid"),
            (lambda T: T.__setitem__((3, 0), 1.0), "last row"),
            (lambda T: T.__setitem__((slice(0, 3), 0), -T[:3, 0]), "not rigid"),
        ],
    )
    def test_rejects(self, bad, msg):
        T = _random_T(3)
        bad(T)
        with pytest.raises(InputError, match=msg):
            poses.check_rigid(T, path="x/pose.txt")


def test_rotation_between_is_the_smallest_rotation_and_agrees_with_scipy():
    rotation_between = poses.rotation_between
    rng = np.random.default_rng(0)
    for _ in range(200):
        a, b = rng.normal(size=(2, 3))
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        R = rotation_between(a, b)
        np.testing.assert_allclose(R @ a, b, atol=1e-12)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        # the smallest rotation: its angle is the angle between the vectors (about a x b)
        assert np.isclose(np.linalg.norm(Rotation.from_matrix(R).as_rotvec()), np.arccos(np.clip(a @ b, -1, 1)), atol=1e-9)
        np.testing.assert_allclose(R, Rotation.align_vectors(b[None], a[None])[0].as_matrix(), atol=1e-9)
    for a in (np.array([1.0, 0, 0]), np.array([0, 0.6, 0.8])):  # opposite vectors: half a turn about an axis across
        R = rotation_between(a, -a)
        np.testing.assert_allclose(R @ a, -a, atol=1e-12)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
    np.testing.assert_allclose(rotation_between(a, a), np.eye(3), atol=1e-12)
