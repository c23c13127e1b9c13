import numpy as np
from scipy.spatial.transform import Rotation

from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera
from localization.estimate import PointLinePoseConfig, pnpl_pose, estimate_pose_points

CAM = Camera(640, 480, (525, 525, 320, 240))


def _project(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * 525 + [320, 240]


def _scene(seed, n_pts=6, n_lines=40, noise=1.0):
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_euler("xyz", rng.uniform(-10, 10, 3), degrees=True).as_matrix(), rng.uniform(-0.3, 0.3, 3))
    Tinv = np.linalg.inv(T)
    Xc = np.c_[rng.uniform(-1.5, 1.5, (n_pts, 2)), rng.uniform(2, 5, n_pts)]
    X = Xc @ Tinv[:3, :3].T + Tinv[:3, 3]
    a = np.c_[rng.uniform(-1.5, 1.5, (n_lines, 2)), rng.uniform(2, 5, n_lines)]
    b = a + rng.normal(0, 0.5, (n_lines, 3))
    A = a @ Tinv[:3, :3].T + Tinv[:3, 3]
    B = b @ Tinv[:3, :3].T + Tinv[:3, 3]
    x = _project(T, X) + rng.normal(0, noise, (n_pts, 2))
    la, lb = _project(T, A), _project(T, B)
    # 2D segments: sub-segments of the projections, with endpoint noise, as a detector would give
    t0, t1 = rng.uniform(0, 0.3, n_lines)[:, None], rng.uniform(0.7, 1, n_lines)[:, None]
    l2 = np.stack([la + t0 * (lb - la), la + t1 * (lb - la)], 1) + rng.normal(0, noise * 0.5, (n_lines, 2, 2))
    return T, x, X, l2, np.stack([A, B], 1)


def test_lines_improve_a_few_noisy_points():
    gains = []
    for seed in range(8):
        T, x, X, l2, l3 = _scene(seed)
        pt = estimate_pose_points(x, X, CAM)
        pl = pnpl_pose(x, X, l2, l3, CAM, initial=pt["cam_from_world"], conf=PointLinePoseConfig())
        assert pl["success"] and pl["n_line_inliers"] >= 30
        gains.append(pose_errors(T, pt["cam_from_world"])[0] - pose_errors(T, pl["cam_from_world"])[0])
        assert pose_errors(T, pl["cam_from_world"])[0] < 0.01
    assert np.median(gains) > 0


def test_outlier_lines_are_rejected():
    T, x, X, l2, l3 = _scene(3, n_pts=20)
    l3_bad = l3.copy()
    l3_bad[:10] += np.random.default_rng(0).normal(0, 0.5, (10, 2, 3))  # 10 of 40 wrong matches
    pl = pnpl_pose(x, X, l2, l3_bad, CAM)
    assert pose_errors(T, pl["cam_from_world"])[0] < 0.01
    assert pl["line_inliers"][:10].sum() <= 1 and pl["line_inliers"][10:].mean() > 0.9


def test_too_few_lines_falls_back():
    T, x, X, l2, l3 = _scene(1)
    out = pnpl_pose(x, X, l2[:2], l3[:2], CAM)
    assert not out["success"] and "line matches" in out["reason"]
