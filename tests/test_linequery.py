import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap import geometry as geo
from lipmap.mapping.assign import corner_edges
from lipmap.poses import make_T
from lipmap.testing import SMALL_CAMERA, rect, wall_scene
from localization.linequery import LineQuery, LineQueryConfig


def _map():
    corners, views = wall_scene()
    # map lines: the panel's 4 edges and 4 edges of a small frame on the back wall hidden by the panel
    hidden = rect([0.1, -0.05, 4.99], 0.3, 0.2)
    lines = np.concatenate([corner_edges(corners[:1])[0], corner_edges(hidden[None])[0]])
    edge_line = np.full((2, 4), -1)
    edge_line[0] = [0, 1, 2, 3]
    return corners, views, lines, edge_line


def _query_lines(lines3d, T, shrink=0.1):
    seg, _ = geo.project_segments(lines3d, T, SMALL_CAMERA)
    seg = seg.reshape(-1, 4)
    d = seg[:, 2:] - seg[:, :2]
    return np.concatenate([seg[:, :2] + shrink * d, seg[:, 2:] - shrink * d], 1)


@pytest.mark.parametrize("method", ["raycast", "projection"])
def test_line_query_matches_visible_lines_under_perturbed_pose(method):
    corners, views, lines, edge_line = _map()
    T_true = views[1].cam_from_world
    q = _query_lines(lines[:4], T_true)
    # initial pose off by 1 cm and 0.2 deg
    dR = Rotation.from_euler("xy", [0.1, 0.15], degrees=True).as_matrix()
    T_init = make_T(dR @ T_true[:3, :3], T_true[:3, 3] + [0.01, 0.0, 0.0])
    lq = LineQuery(lines, corners, edge_line)
    m = lq.match(q, T_init, SMALL_CAMERA, LineQueryConfig(method=method, max_dist_px=8, max_angle_deg=3))
    assert sorted(zip(m["query_idx"], m["line_idx"])) == [(0, 0), (1, 1), (2, 2), (3, 3)]


def test_projection_ignores_occluded_lines():
    corners, views, lines, edge_line = _map()
    T = views[0].cam_from_world
    lq = LineQuery(lines, corners, edge_line)
    vis = lq.visible_lines(T, SMALL_CAMERA, 0.05)
    assert set(vis) == {0, 1, 2, 3}  # the back-wall frame lies behind the panel
    # a query line drawn exactly where the hidden frame projects must not match it
    q = _query_lines(lines[4:], T, shrink=0.0)
    m = lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection"))
    assert not np.isin(m["line_idx"], [4, 5, 6, 7]).any()


def test_short_and_empty():
    corners, views, lines, edge_line = _map()
    lq = LineQuery(lines, corners, edge_line)
    m = lq.match(np.zeros((0, 4)), views[0].cam_from_world, SMALL_CAMERA, LineQueryConfig())
    assert len(m["query_idx"]) == 0
    m = LineQuery(np.zeros((0, 2, 3))).match(np.array([[0, 0, 100, 0.0]]), views[0].cam_from_world, SMALL_CAMERA, LineQueryConfig())
    assert len(m["line_idx"]) == 0


@pytest.mark.parametrize("method", ["raycast", "projection"])
def test_min_support_keeps_unverified_map_lines_out_of_the_query(method):
    corners, views, lines, edge_line = _map()
    T = views[1].cam_from_world
    q = _query_lines(lines[:4], T)
    supports = np.array([[5, 6], [1, 1], [3, 3], [2, 2], [1, 1], [1, 1], [1, 1], [1, 1]])
    lq = LineQuery(lines, corners, edge_line, supports)
    m = lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method=method, min_support=2))
    assert sorted(m["line_idx"]) == [0, 2, 3]  # line 1 is seen in one mapping image only
    assert sorted(lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method=method))["line_idx"]) == [0, 1, 2, 3]
    # by default a line no mapping image verifies (support 0) is left out; min_support 0 queries it too
    supports[1] = 0
    lq = LineQuery(lines, corners, edge_line, supports)
    assert sorted(lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method=method))["line_idx"]) == [0, 2, 3]
    assert sorted(lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method=method, min_support=0))["line_idx"]) == [0, 1, 2, 3]


def test_a_map_without_tracks_queries_every_line(caplog):
    from lipmap.linemap import LineMap

    corners, views, lines, edge_line = _map()
    T = views[1].cam_from_world
    q = _query_lines(lines[:4], T)
    bare = LineMap(lines, planes={"corners": corners, "edge_line": edge_line})  # e.g. lines imported without tracks
    assert not bare.supports.any()
    with caplog.at_level("WARNING", logger="lipmap"):
        lq = LineQuery.from_linemap(bare)
    assert "No line of the map has a track" in caplog.text
    assert sorted(lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection"))["line_idx"]) == [0, 1, 2, 3]
    tracked = LineMap(lines, [[("a.png", 0, q[0])]] + [[] for _ in range(len(lines) - 1)],
                      planes={"corners": corners, "edge_line": edge_line})
    m = LineQuery.from_linemap(tracked).match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection"))
    assert m["line_idx"].tolist() == [0]  # with tracks, the lines no image verifies stay out


def test_one_to_one_keeps_the_best_query_line_of_each_map_line():
    corners, views, lines, edge_line = _map()
    T = views[1].cam_from_world
    q = _query_lines(lines[:1], T)
    d = q[0, 2:] - q[0, :2]
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    near = q + 1.5 * np.concatenate([n, n])  # a second detection 1.5 px beside the first
    both = np.concatenate([near, q])
    lq = LineQuery(lines, corners, edge_line)
    conf = LineQueryConfig(method="projection", max_dist_px=4, one_to_one=False)
    assert sorted(lq.match(both, T, SMALL_CAMERA, conf)["query_idx"]) == [0, 1]
    m = lq.match(both, T, SMALL_CAMERA, LineQueryConfig(method="projection", max_dist_px=4, one_to_one=True))
    assert m["query_idx"].tolist() == [1] and m["line_idx"].tolist() == [0]  # the exact one wins


def test_min_margin_drops_query_lines_with_an_equally_good_runner_up():
    corners, views, lines, edge_line = _map()
    T = views[1].cam_from_world
    q = _query_lines(lines[:1], T)
    # a second map line parallel to line 0 and a few mm beside it: its projection lies ~1-2 px from the first
    shift = 0.004 * np.cross(lines[0, 1] - lines[0, 0], T[2, :3])
    shift /= max(np.linalg.norm(shift), 1e-12) / 0.004
    twin = np.concatenate([lines, (lines[:1] + shift)])
    conf = LineQueryConfig(method="projection", max_dist_px=4, min_margin=0.0)
    lq = LineQuery(twin, corners, edge_line)
    assert lq.match(q, T, SMALL_CAMERA, conf)["query_idx"].tolist() == [0]  # the nearer twin wins
    assert len(lq.match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection", max_dist_px=4, min_margin=6.0, margin_dup_3d=0.0))["query_idx"]) == 0
    alone = LineQuery(lines, corners, edge_line)  # without the twin, the runner-up (if any) is far: kept
    assert alone.match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection", max_dist_px=4, min_margin=6.0))["line_idx"].tolist() == [0]


def test_margin_ignores_a_runner_up_that_is_the_same_line_in_3d():
    """``margin_dup_3d``: a twin a few mm beside the best line in 3D is the same line mapped twice and does not make
    the query line ambiguous; a line that projects as close but lies 20 % deeper along the rays still does."""
    corners, views, lines, edge_line = _map()
    T = views[1].cam_from_world
    q = _query_lines(lines[:1], T)
    shift = 0.004 * np.cross(lines[0, 1] - lines[0, 0], T[2, :3])
    shift /= max(np.linalg.norm(shift), 1e-12) / 0.004
    C = -T[:3, :3].T @ T[:3, 3]
    deeper = C + 1.2 * (lines[:1] - C) + shift  # projects like the twin, ~20 % of the depth away in 3D
    conf = LineQueryConfig(method="projection", max_dist_px=4, min_margin=6.0, margin_dup_3d=0.03)
    twin = LineQuery(np.concatenate([lines, lines[:1] + shift]), corners, edge_line)
    assert twin.match(q, T, SMALL_CAMERA, conf)["line_idx"].tolist() == [0]
    far = LineQuery(np.concatenate([lines, deeper]), corners=None)
    assert len(far.match(q, T, SMALL_CAMERA, LineQueryConfig(method="projection", max_dist_px=4, min_margin=0.0))["query_idx"]) == 1
    assert len(far.match(q, T, SMALL_CAMERA, conf)["query_idx"]) == 0


def test_projection_candidates_equal_a_float64_reference():
    """The float32 screening of the projection query (angle, and the query line's midpoint near the projected line)
    keeps exactly the pairs of a plain float64 test of every (query line, map line) pair: angle, both query
    endpoints' distance to the projected line, overlap."""
    rng = np.random.default_rng(0)
    cam = SMALL_CAMERA
    T = make_T(np.eye(3), np.zeros(3))
    a = np.c_[rng.uniform(-1.5, 1.5, (400, 2)), rng.uniform(2, 5, 400)]
    lines = np.stack([a, a + rng.normal(0, 0.3, (400, 3))], 1)
    lines[::7, 1, 2] = -1.0  # some lines cross behind the camera
    proj, _ = geo.project_segments(lines, T, cam)
    # query lines: projections moved by up to ~10 px and turned by up to ~4 deg, so many sit at the gates
    q = proj.reshape(-1, 4)[::2] + rng.normal(0, 4, (200, 4))
    q = q[np.all(np.isfinite(q), 1) & (np.linalg.norm(q[:, 2:] - q[:, :2], axis=1) >= 20)]
    conf = LineQueryConfig(max_dist_px=8, max_angle_deg=3, min_overlap=0.3, max_candidates=10_000, min_margin=0,
                           one_to_one=False)
    lq = LineQuery(lines)
    got = set(zip(*lq._projection(q, T, cam, conf, visible=np.arange(len(lines)))))
    qs = geo.as_segments2d(q)[:, None]
    with np.errstate(invalid="ignore"):
        ang = geo.angle_distance(qs, proj[None])
        dist = geo.perpendicular_distance(qs, proj[None], "max")
        ov = geo.overlap_ratio(proj[None], qs)
    ok = (ang <= np.radians(3)) & (dist <= 8) & (ov >= 0.3)
    ref = set(zip(*np.nonzero(ok)))
    # pairs whose midpoint passes the screen but one endpoint lies outside the gate: the exact test must drop them
    with np.errstate(invalid="ignore"):
        mid = geo.perpendicular_distance(np.repeat(qs.mean(-2, keepdims=True), 2, -2), proj[None], "max")
    assert ((ang <= np.radians(3)) & (mid <= 8) & (dist > 8) & (ov >= 0.3)).sum() > 0
    assert len(ref) > 50 and got == {(int(i), int(j)) for i, j in ref}
