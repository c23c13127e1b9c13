"""Vanishing-point-aligned two-point pose hypotheses (localization.hypotheses, ``HypothesisConfig.upright``)."""
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera
from localization.hypotheses import (HypothesisConfig, dominant_directions, line_verified_poses, p3p_hypotheses,
                                     upright_hypotheses, vanishing_points)

CAM = Camera(640, 480, (525, 525, 320, 240))
AXES = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()  # the room's axes, not the world's


def _project(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * 525 + [320, 240]


def _room(seed=0, n=90, n_clutter=15):
    """A camera in a 'room' of segments along three orthogonal axes (most along the first), a few in random
    directions, their detections (0.3 px noise) and the true pose."""
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_euler("xyz", rng.uniform(-15, 15, 3), degrees=True).as_matrix(), rng.uniform(-0.3, 0.3, 3))
    Tinv = np.linalg.inv(T)
    dirs = np.concatenate([AXES[rng.choice(3, n, p=[0.5, 0.3, 0.2])], rng.normal(size=(n_clutter, 3))])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    centre_cam = np.c_[rng.uniform(-1.0, 1.0, (len(dirs), 2)), rng.uniform(2.5, 4.0, len(dirs))]
    centre = centre_cam @ Tinv[:3, :3].T + Tinv[:3, 3]
    half = rng.uniform(0.2, 0.5, len(dirs))[:, None] * dirs
    ends = np.stack([centre - half, centre + half], 1)
    l2 = np.concatenate([_project(T, ends[:, 0]), _project(T, ends[:, 1])], 1) + rng.normal(0, 0.3, (len(ends), 4))
    return T, ends, l2


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(abs(a @ b), 0, 1)))


def test_dominant_directions_are_the_room_axes_by_length():
    T, ends, _ = _room(0)
    d = dominant_directions(ends, 3)
    assert d.shape == (3, 3)
    for found, axis in zip(d, AXES):  # the first axis holds the most line length, then the second
        assert _angle_deg(found, axis) < 0.5
    # lines along a single direction have one dominant direction: none is made up
    assert len(dominant_directions(ends[:2].repeat(5, 0), 3)) == 1


def test_vanishing_points_are_the_room_axes_seen_from_the_camera():
    for seed in range(3):
        T, ends, l2 = _room(seed)
        vps = vanishing_points(l2, CAM, HypothesisConfig(vp_count=2), seed=0)
        assert len(vps) == 2
        seen = AXES @ T[:3, :3].T  # the axes in the camera frame
        assert _angle_deg(vps[0], seen[0]) < 1.0  # the strongest: the first axis
        assert min(_angle_deg(vps[1], s) for s in seen[1:]) < 1.5
        # seeded: the same answer twice
        assert np.array_equal(vps, vanishing_points(l2, CAM, HypothesisConfig(vp_count=2), seed=0))


def test_two_right_matches_and_a_vanishing_point_give_the_pose():
    T, ends, l2 = _room(1)
    rng = np.random.default_rng(5)
    X = np.c_[rng.uniform(-1, 1, (2, 2)), rng.uniform(2, 4, 2)] @ np.linalg.inv(T)[:3, :3].T + np.linalg.inv(T)[:3, 3]
    vp = (T[:3, :3] @ AXES[0])[None]
    poses = upright_hypotheses(_project(T, X), X, CAM, vp, AXES, HypothesisConfig())
    # 1 vanishing point x 3 directions x 2 signs x 1 pair, up to 2 solutions each
    assert 0 < len(poses) <= 12
    assert min(pose_errors(T, P)[0] for P in poses) < 1e-6
    assert min(pose_errors(T, P)[1] for P in poses) < 1e-4


def test_upright_poses_find_a_query_whose_matches_hold_only_two_right_ones():
    T, ends, l2 = _room(2, n=150)
    rng = np.random.default_rng(7)
    Tinv = np.linalg.inv(T)
    X = np.c_[rng.uniform(-1, 1, (5, 2)), rng.uniform(2.5, 4, 5)] @ Tinv[:3, :3].T + Tinv[:3, 3]
    p2d = _project(T, X)
    p2d[2:] += rng.uniform(60, 120, (3, 2)) * rng.choice([-1, 1], (3, 2))  # three wrong matches
    conf = HypothesisConfig(box_margin=5.0)  # this camera stands before the lines, outside their box
    p3p, _ = p3p_hypotheses(p2d, X, CAM, conf)
    assert min(pose_errors(T, P)[0] for P in p3p) > 0.05  # no triple of right matches: P3P misses the pose
    without = line_verified_poses(p2d, X, l2, ends, CAM, replace(conf, upright=False))
    assert not without or pose_errors(T, without[0])[0] > 0.05
    poses = line_verified_poses(p2d, X, l2, ends, CAM, conf)
    assert poses and pose_errors(T, poses[0])[0] < 0.01 and pose_errors(T, poses[0])[1] < 0.5


def test_upright_poses_are_skipped_when_a_p3p_pose_explains_enough_matches(monkeypatch):
    import localization.hypotheses as H

    T, ends, l2 = _room(3)
    rng = np.random.default_rng(2)
    Tinv = np.linalg.inv(T)
    X = np.c_[rng.uniform(-1, 1, (6, 2)), rng.uniform(2.5, 4, 6)] @ Tinv[:3, :3].T + Tinv[:3, 3]
    calls = []
    real = H.upright_hypotheses
    monkeypatch.setattr(H, "upright_hypotheses", lambda *a, **k: calls.append(1) or real(*a, **k))
    conf = HypothesisConfig(box_margin=5.0, upright_below=5)
    poses = H.line_verified_poses(_project(T, X), X, l2, ends, CAM, conf)  # six right matches: P3P explains all
    assert not calls and pose_errors(T, poses[0])[0] < 1e-6
    H.line_verified_poses(_project(T, X), X, l2, ends, CAM, replace(conf, upright_below=0))
    assert calls


def test_rescue_takes_the_longest_query_lines():
    from localization.query import longest_lines

    lines = np.array([[0, 0, 10, 0], [0, 0, 50, 0], [0, 0, 30, 0], [0, 0, 40, 0]], float)
    assert np.array_equal(longest_lines(lines, 2), lines[[1, 3]])  # kept in their order
    assert np.array_equal(longest_lines(lines, 0), lines) and np.array_equal(longest_lines(lines, 9), lines)
