"""The PnPL RANSAC about a start pose (localization.near_ransac): its equations, minimal solves and costs against
known answers and readable references, and poses recovered from starts a few degrees and centimetres off among
mostly wrong line candidates."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera
from localization.estimate import PointLinePoseConfig, pnpl_residuals
from localization.near_ransac import (NearRansacConfig, match_equations, msac_costs, pnpl_near_start, solve_samples,
                                      solve_sample_reference)

CAM = Camera(640, 480, (525, 525, 320, 240))


def _project(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[..., :2] / Xc[..., 2:] * 525 + np.array([320, 240])


def _scene(seed=0, n_lines=60, n_pts=4, wrong=2, noise_px=0.0):
    """A camera before a box of 3D segments and points; each detection comes with its true 3D segment and ``wrong``
    others (the wide gate's candidates): (true pose, p2d, p3d, lines2d, lines3d, which candidates are right)."""
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_euler("xyz", rng.uniform(-20, 20, 3), degrees=True).as_matrix(), rng.uniform(-0.3, 0.3, 3))
    C = -T[:3, :3].T @ T[:3, 3]
    ahead = T[:3, :3].T @ np.array([0, 0, 1.0])

    def in_view(k):
        X = C + ahead * rng.uniform(2, 4, (k, 1)) + (T[:3, :3].T @ np.c_[rng.uniform(-1, 1, (k, 2)),
                                                                          np.zeros(k)].T).T
        return X

    a = in_view(n_lines)
    d = rng.normal(size=(n_lines, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    l3 = np.stack([a, a + 0.4 * d], 1)
    l2 = _project(T, l3) + rng.normal(0, noise_px, (n_lines, 2, 2))
    p3 = in_view(n_pts)
    p2 = _project(T, p3) + rng.normal(0, noise_px, (n_pts, 2))
    cand2 = np.repeat(l2, 1 + wrong, axis=0)
    cand3 = np.repeat(l3, 1 + wrong, axis=0)
    right = np.tile(np.r_[True, np.zeros(wrong, bool)], n_lines)
    cand3[~right] = l3[rng.integers(0, n_lines, (~right).sum())] + rng.normal(0, 0.3, ((~right).sum(), 1, 3))
    return T, p2, p3, cand2, cand3, right


def _off(T, cm, deg, seed=1):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis)).as_matrix() @ T[:3, :3]
    C = -T[:3, :3].T @ T[:3, 3] + cm / 100 * np.array([0.6, 0.0, 0.8])
    return make_T(R, -R @ C)


def test_right_matches_satisfy_their_equations_at_the_true_pose():
    T, p2, p3, l2, l3, right = _scene(noise_px=0.0)
    A, b = match_equations(p2, p3, l2[right], l3[right], T[:3, :3], CAM)
    assert A.shape == (len(p2) + right.sum(), 2, 6) and b.shape == (len(A), 2)
    np.testing.assert_allclose(A @ np.r_[np.zeros(3), T[:3, 3]], b, atol=1e-9)
    # a wrong candidate does not
    A, b = match_equations(p2[:0], p3[:0], l2[~right], l3[~right], T[:3, :3], CAM)
    assert np.median(np.abs(A @ np.r_[np.zeros(3), T[:3, 3]] - b)) > 1e-3


def test_batched_solves_agree_with_the_reference():
    rng = np.random.default_rng(3)
    A, b = rng.normal(size=(20, 2, 6)), rng.normal(size=(20, 2))
    pairs = np.array([[0, 1], [4, 7], [19, 2]])
    triples = np.array([[0, 1, 2], [5, 9, 13], [18, 3, 11]])
    w, t = solve_samples(A, b, pairs, triples, max_rotation_deg=1e9)
    ref = np.array([solve_sample_reference(A, b, s) for s in [*pairs, *triples]])
    np.testing.assert_allclose(np.c_[w, t], ref, atol=1e-9)


def test_a_triple_recovers_a_small_rotation_to_second_order():
    T, p2, p3, l2, l3, right = _scene()
    start = _off(T, 0, 2.0)
    A, b = match_equations(p2, p3, l2[right], l3[right], start[:3, :3], CAM)
    w, t = solve_samples(A, b, np.zeros((0, 2), int), np.array([[0, 5, 9]]), 15.0)
    R = Rotation.from_rotvec(w[0]).as_matrix() @ start[:3, :3]
    dt, dr = pose_errors(T, make_T(R, t[0]))
    assert dr < 0.1 and dt < 0.01  # 2 deg off: the linearisation's error is of the order of (2 deg)^2


def test_msac_costs_agree_with_the_residuals_of_pnpl_residuals():
    T, p2, p3, l2, l3, right = _scene(noise_px=1.0)
    rng = np.random.default_rng(0)
    w, t = rng.normal(0, 0.01, (5, 3)), T[:3, 3] + rng.normal(0, 0.02, (5, 3))
    costs = msac_costs(w, t, T[:3, :3], p2, p3, l2, l3, CAM.K, 6.0, 4.0)
    for k in range(5):
        rp, rl = pnpl_residuals(p2, p3, l2, l3, make_T(Rotation.from_rotvec(w[k]).as_matrix() @ T[:3, :3], t[k]), CAM)
        ref = np.minimum(rp ** 2, 36.0).sum() + np.minimum(rl.sum(1) ** 2, 16.0).sum()
        assert costs[k] == pytest.approx(ref, rel=1e-4)


@pytest.mark.parametrize("n_pts", [0, 3])
@pytest.mark.parametrize("cm, deg", [(0, 0), (20, 3), (10, 8)])
def test_pose_from_a_start_off_among_mostly_wrong_candidates(n_pts, cm, deg):
    T, p2, p3, l2, l3, right = _scene(n_pts=n_pts, noise_px=0.5)  # two of three candidates wrong
    r = pnpl_near_start(p2, p3, l2, l3, CAM, _off(T, cm, deg), pose_conf=PointLinePoseConfig(max_reproj_error=6.0))
    assert r["success"]
    dt, dr = pose_errors(T, r["cam_from_world"])
    assert dt < 0.01 and dr < 0.2
    assert r["line_inliers"][right].mean() > 0.9 and r["line_inliers"][~right].mean() < 0.1
    assert r["n_inliers"] == n_pts


def test_seeded_and_refuses_too_few_lines():
    T, p2, p3, l2, l3, right = _scene(noise_px=0.5)
    start = _off(T, 20, 3)
    a = pnpl_near_start(p2, p3, l2, l3, CAM, start, NearRansacConfig(pose_samples=50, translation_samples=20))
    b = pnpl_near_start(p2, p3, l2, l3, CAM, start, NearRansacConfig(pose_samples=50, translation_samples=20))
    np.testing.assert_array_equal(a["cam_from_world"], b["cam_from_world"])
    # a second pass linearises about the first pass's pose
    two = pnpl_near_start(p2, p3, l2, l3, CAM, _off(T, 20, 8), NearRansacConfig(passes=2))
    assert pose_errors(T, two["cam_from_world"])[0] < 0.01
    l3 = l3.copy()
    l3[2:] = np.nan  # unusable candidates are left out, not fatal
    r = pnpl_near_start(p2, p3, l2, l3, CAM, start)
    assert not r["success"] and "line matches" in r["reason"]
    assert r["line_inliers"].shape == (len(l2),)
