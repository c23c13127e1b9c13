"""Poses from 3, 2, 1 and 0 point matches: the lines go first (localization.linesfirst), on a synthetic room whose
lines run along three directions, as an indoor map's do."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap import geometry as geo
from lipmap.linemap import LineMap
from lipmap.poses import make_T, pose_errors, rotation_between
from lipmap.scene import Camera
from localization import LocalizationConfig, Localizer
from localization.hypotheses import HypothesisConfig, dominant_directions, vanishing_points
from localization.linesfirst import (LinesFirstConfig, _about, interpretation_normals, lines_first_poses,
                                     turn_votes, voted_centres, vp_rotations)

CAM = Camera(640, 480, (525, 525, 320, 240))


def _room(seed=0, n=400):
    """Axis-aligned segments on the walls, floor and ceiling of a 6 x 5 x 3 m room (world z up)."""
    rng = np.random.default_rng(seed)
    size = np.array([6.0, 5.0, 3.0])
    lines = []
    for _ in range(n):
        axis = rng.integers(3)  # the direction the segment runs along
        face = rng.integers(3)  # the coordinate that is fixed on a wall
        while face == axis:
            face = rng.integers(3)
        a = rng.uniform(0, size)
        a[face] = rng.choice([0.0, size[face]])
        b = a.copy()
        b[axis] = np.clip(a[axis] + rng.choice([-1, 1]) * rng.uniform(0.3, 1.5), 0, size[axis])
        lines.append([a, b])
    return np.array(lines)


def _camera(yaw=30.0, centre=(2.0, 1.5, 1.4)):
    """cam_from_world of a camera at ``centre`` looking along world +x turned by ``yaw`` (deg), level."""
    # camera axes in the world: x right, y down, z forward
    fwd = Rotation.from_euler("z", yaw, degrees=True).apply([1.0, 0, 0])
    down = np.array([0, 0, -1.0])
    right = np.cross(down, fwd)
    R = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    return make_T(R, -R @ np.asarray(centre))


def _observe(T, lines, rng, noise=0.3):
    """The segments the camera sees (both ends in front, clipped to the image, >= 40 px), with pixel noise."""
    proj, ok = geo.project_segments(lines, T, CAM)
    seg = proj.reshape(-1, 4)
    inside = ok & np.all((seg[:, [0, 2]] > 0) & (seg[:, [0, 2]] < 640) & (seg[:, [1, 3]] > 0) & (seg[:, [1, 3]] < 480), 1)
    seg = seg[inside]
    seg = seg[geo.segment_lengths(seg) >= 40]
    return seg + rng.normal(0, noise, seg.shape)


def _points(T, n, rng):
    """``n`` 3D points on the walls the camera sees, and their pixels."""
    X = []
    while len(X) < n:
        p = rng.uniform([0, 0, 0], [6, 5, 3])
        p[rng.integers(2)] = rng.choice([0.0, 6.0])
        uv, z = geo.project_points(p[None], T, CAM)
        if z[0] > 0.5 and 20 < uv[0, 0] < 620 and 20 < uv[0, 1] < 460:
            X.append(p)
    X = np.array(X)
    return geo.project_points(X, T, CAM)[0] + rng.normal(0, 0.5, (n, 2)), X


def _view(T, cm=50.0, deg=12.0):
    """A retrieved image's pose: ``cm`` away and turned by ``deg``."""
    R = Rotation.from_euler("zy", [deg, deg / 3], degrees=True).as_matrix() @ T[:3, :3]
    C = -T[:3, :3].T @ T[:3, 3] + np.array([cm, -cm / 2, 10]) / 100
    return make_T(R, -R @ C)


@pytest.fixture(scope="module")
def room():
    rng = np.random.default_rng(1)
    lines = _room()
    T = _camera()
    return {"lines": lines, "T": T, "seen": _observe(T, lines, rng), "dirs": dominant_directions(lines, 3),
            "pts": _points(T, 6, rng)}


def test_the_rotation_from_vanishing_points_near_a_retrieved_image(room):
    T, seen = room["T"], room["seen"]
    n, w = interpretation_normals(seen, CAM)
    vps = vanishing_points(seen, CAM, HypothesisConfig(vp_count=2))
    rots = vp_rotations(n, np.minimum(w, 200) / 200, vps, room["dirs"], [_view(T)], LinesFirstConfig())
    err = [pose_errors(make_T(R, T[:3, 3]), T)[1] for R, _ in rots]
    assert min(err) < 0.5  # degrees, from a view 12 deg off


@pytest.mark.parametrize("n_points", [0, 1, 2])
def test_lines_first_poses_hold_the_right_one(room, n_points):
    T, seen = room["T"], room["seen"]
    p2d, p3d = room["pts"]
    vps = vanishing_points(seen, CAM, HypothesisConfig(vp_count=2))
    poses = lines_first_poses(p2d[:n_points], p3d[:n_points], seen, CAM, [_view(T)], room["lines"], room["dirs"],
                              vps, LinesFirstConfig())
    assert len(poses) > 0
    best = min(poses, key=lambda P: pose_errors(P, T)[0])
    dt, dr = pose_errors(best, T)
    assert dt < 0.06 and dr < 0.5, (dt, dr)


def test_the_centre_is_voted_within_the_search_only(room):
    T = room["T"]
    n, w = interpretation_normals(room["seen"], CAM)
    C = -T[:3, :3].T @ T[:3, 3]
    near = voted_centres(T[:3, :3], room["seen"], n, w / w.max(), room["lines"], room["dirs"], C + [0.6, 0.4, 0.0], CAM,
                         LinesFirstConfig())
    assert min(pose_errors(P, T)[0] for P in near) < 0.05
    far = voted_centres(T[:3, :3], room["seen"], n, w / w.max(), room["lines"], room["dirs"], C + [3.0, 0.0, 0.0], CAM,
                        LinesFirstConfig())
    assert all(pose_errors(P, T)[0] > 0.5 for P in far)  # 3 m away: not within the 2 m searched


@pytest.mark.parametrize("n_points", [0, 1, 2, 3])
def test_below_three_matches_the_views_own_centre_stands_with_each_rotation(room, n_points):
    """The votes can miss beside a view (without a match, or along a wrong match's ray); with fewer than
    ``view_centres_below`` matches the view's centre, with each rotation from the vanishing points, is among the poses
    the lines score too (with ``view_centres_below=0``, or from 3 matches, it is not)."""
    T, seen = room["T"], room["seen"]
    p2d, p3d = room["pts"]
    V = _view(T, cm=8.0)
    CV = -V[:3, :3].T @ V[:3, 3]
    vps = vanishing_points(seen, CAM, HypothesisConfig(vp_count=2))
    on, off = (lines_first_poses(p2d[:n_points], p3d[:n_points], seen, CAM, [V], room["lines"], room["dirs"], vps,
                                 LinesFirstConfig(view_centres_below=b)) for b in (3, 0))
    at_view = [P for P in on if np.allclose(-P[:3, :3].T @ P[:3, 3], CV)]
    assert len(on) == len(off) + len(at_view) and not any(np.allclose(-P[:3, :3].T @ P[:3, 3], CV) for P in off)
    if n_points < 3:
        assert at_view and min(pose_errors(P, T)[1] for P in at_view) < 0.5  # the lines' rotation, not the view's 12 deg
    else:
        assert not at_view


@pytest.mark.parametrize("n_points", [0, 1, 2, 3])
def test_every_budget_gives_a_pose(room, n_points):
    """Through the per-query API, the retrieved image's pose given as ``initial``: 3, 2, 1 and 0 point matches."""
    T, seen = room["T"], room["seen"]
    p2d, p3d = room["pts"]
    loc = Localizer(LineMap(room["lines"]), LocalizationConfig())
    res = loc.localize(CAM, p2d[:n_points], p3d[:n_points], lines2d=seen, initial=_view(T))
    assert not res.point.success and res.point_line.success and res.rescued
    dt, dr = pose_errors(res.point_line.cam_from_world, T)
    assert dt < 0.02 and dr < 0.3, (dt, dr)
    if n_points < 2:  # no retrieved image and no pair of points for the two-point poses: no pose
        assert not loc.localize(CAM, p2d[:n_points], p3d[:n_points], lines2d=seen).point_line.success


def test_the_benchmark_loop_starts_the_lines_from_the_retrieved_images(room):
    """localize_query (run_eval's per-query call) hands the retrieved images' poses to the lines-first poses: one point
    match and a database image 50 cm / 12 deg away give the pose; without the retrieved image, none."""
    from dataclasses import replace

    from localization.linequery import LineQuery
    from localization.points import PointMatches
    from localization.query import localize_query

    T, seen = room["T"], room["seen"]
    p2d, p3d = room["pts"]

    class Source:  # a point source: one point match, one retrieved database image
        model = type("Model", (), {"__contains__": lambda self, n: n == "db",
                                   "cam_from_world": lambda self, n: _view(T)})()

        def __init__(self, retrieved):
            self.retrieved = retrieved

        def matches_for(self, name):
            return PointMatches(p2d[:1], p3d[:1], np.zeros(1, np.int64), np.zeros(1, np.int64))

        def retrieved_for(self, name):
            return self.retrieved

    conf = LocalizationConfig()
    rec = localize_query("q", CAM, Source(["db"]), seen, LineQuery(room["lines"]), conf, cam_from_world_gt=T)
    pl = rec["point+line"]
    assert pl["success"] and pl["rescued"] and pose_errors(np.array(pl["cam_from_world"]), T)[0] < 0.02
    assert not localize_query("q", CAM, Source([]), seen, LineQuery(room["lines"]), conf)["point+line"]["success"]
    off = replace(conf, line_rescue=replace(conf.line_rescue, hypotheses=replace(
        conf.line_rescue.hypotheses, lines_first=replace(conf.line_rescue.hypotheses.lines_first, views=0))))
    assert not localize_query("q", CAM, Source(["db"]), seen, LineQuery(room["lines"]), off)["point+line"]["success"]


def test_seen_alike_from_rotated_ends_agrees_with_the_world_frame():
    """voted_translations tests its pairs from the map lines' ends rotated once per rotation (``_alike``); that is
    seen_alike's answer from the world frame, on random segments and centres in and out of view."""
    from localization.linesfirst import _alike, _segment_frames, seen_alike

    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=4).as_matrix()
    P = 2000
    centres = rng.uniform(-1, 1, (P, 3))
    # ends in front of the camera at 0.2-9 m (some outside the depth range), in world coordinates
    Y = np.concatenate([rng.uniform(-2, 2, (P, 2, 2)), rng.uniform(0.2, 9, (P, 2, 1))], -1)
    ends = Y @ R + centres[:, None]
    segments = rng.uniform(0, 640, (P, 4))
    conf = LinesFirstConfig()
    want = seen_alike(R, centres, ends, segments, CAM, conf)
    got = _alike((ends @ R.T) - (centres @ R.T)[:, None], *_segment_frames(segments), CAM, conf)
    assert 0.05 < want.mean() < 0.95  # both answers occur
    np.testing.assert_array_equal(got, want)


def test_ten_matches_with_one_right_get_their_pose_from_the_lines(room):
    """With 10 matches of which one is right, neither P3P (three right) nor the two-point poses (two) can hold the pose;
    the lines-first poses along the right match's ray do, and they now join below 11 matches (not 6)."""
    from dataclasses import replace

    from localization.hypotheses import line_verified_poses

    T, seen = room["T"], room["seen"]
    rng = np.random.default_rng(7)
    p2d, p3d = room["pts"]
    w2d, w3d = _points(T, 10, rng)
    p2d = np.concatenate([p2d[:1], w2d[:9]])
    p3d = np.concatenate([p3d[:1], np.roll(w3d, 1, axis=0)[:9]])  # each wrong pixel paired with another point
    conf = HypothesisConfig()
    assert conf.lines_first.below > 10
    poses = line_verified_poses(p2d, p3d, seen, room["lines"], CAM, conf, views=[_view(T)])
    dt, dr = pose_errors(poses[0], T)
    assert dt < 0.05 and dr < 1.0, (dt, dr)
    old = line_verified_poses(p2d, p3d, seen, room["lines"], CAM, replace(conf, lines_first=LinesFirstConfig(below=6)),
                              views=[_view(T)])
    assert all(pose_errors(P, T)[0] > 0.05 for P in old)


def test_the_turn_is_voted_by_the_other_directions_lines_only(room):
    """Lines through the aligned vanishing point (vertical ones here) say nothing of the turn about it, yet the plane of
    each holds a horizontal direction at one turn: a stack of them at one bearing (a door frame) made a peak there."""
    T, rng = room["T"], np.random.default_rng(3)
    d = room["lines"][:, 1] - room["lines"][:, 0]
    upright = np.abs(d[:, 2]) > 0.9 * np.linalg.norm(d, axis=1)
    # eight vertical edges on the far wall, 10 deg from where the x direction's vanishing point lies
    frame = np.array([[[6.0, 2.2 + 0.015 * k, 0.3], [6.0, 2.2 + 0.015 * k, 2.3]] for k in range(8)])
    seen = np.concatenate([_observe(T, np.concatenate([room["lines"][upright], frame]), rng),
                           _observe(T, room["lines"][~upright], rng)[:6]])
    n, w = interpretation_normals(seen, CAM)
    w = np.minimum(w, 200) / 200
    v = T[:3, :3] @ [0, 0, 1.0]  # the vertical vanishing point, exact
    R1 = _view(T, deg=8.0)[:3, :3]
    R1 = rotation_between(R1 @ [0, 0, 1.0], v) @ R1  # the view's rotation with its vertical on v
    turns = np.radians(np.arange(-30, 30.01, 0.25))
    Ra = _about(v, turns)
    votes = turn_votes(Ra, np.array([[1.0, 0, 0], [0, 1.0, 0]]) @ R1.T, n, w, v, np.sin(np.radians(1.5)))
    err = [pose_errors(make_T(R @ R1, T[:3, 3]), T)[1] for R in Ra]
    # degrees: the votes are flat within the lines' tolerance (refine_rotation settles the turn); with the vertical
    # lines voting, the frame's turn won, 11 deg off
    assert err[int(np.argmax(votes))] < 3.0
    assert votes[int(np.argmin(err))] == votes.max()
