"""Track aggregation (lipmap/mapping/aggregate.py): lines that share detections merged, each spanning its track's
detections; known answers on constructed cameras and lines."""
from __future__ import annotations

import numpy as np

from lipmap import geometry as geo
from lipmap import viz
from lipmap.linemap import LineMap, edge_line_mask
from lipmap.mapping.aggregate import (
    AggregateConfig,
    absorb_targets,
    aggregate_linemap,
    extended,
    merge_groups,
    shared_detection_pairs,
    track_extents,
)
from lipmap.scene import Camera, View

CAM = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))
CENTERS = [np.array([x, y, 0.0]) for x, y in [(0, 0), (0.2, 0), (-0.2, 0.05)]]
VIEWS = [View(f"seq-01/frame-{i:06d}.color.png", CAM, viz.look_at(c, (0.0, 0.0, 2.0), up=(0.0, 1.0, 0.0)),
              color_path=None) for i, c in enumerate(CENTERS)]
# one physical edge 1 m long, at 2 m
EDGE = np.array([[-0.5, 0.1, 2.0], [0.5, 0.1, 2.0]])


def _point(t):
    d = (EDGE[1] - EDGE[0]) / np.linalg.norm(EDGE[1] - EDGE[0])
    return EDGE[0] + t * d


def _detection(view, t0, t1, shift_px=0.0):
    """The detection of the edge's stretch [t0, t1] (metres along it) in ``view``, moved ``shift_px`` across."""
    seg = np.stack([_point(t0), _point(t1)])
    proj, _ = geo.project_segments(seg[None], view.cam_from_world, view.camera)
    a, b = proj[0]
    n = np.array([-(b - a)[1], (b - a)[0]]) / np.linalg.norm(b - a)
    return np.concatenate([a + shift_px * n, b + shift_px * n])


def test_shared_detection_pairs_known_answer():
    rows = np.array([[0, 0, 5], [1, 0, 5], [2, 0, 5], [1, 1, 3], [3, 1, 3], [4, 2, 9], [0, 0, 6]])
    assert shared_detection_pairs(rows).tolist() == [[0, 1], [0, 2], [1, 2], [1, 3]]
    assert shared_detection_pairs(rows[[0, 3, 5]]).shape == (0, 2)


def test_merge_groups_join_only_lines_that_agree_in_3d():
    near = EDGE + [0.0, 0.01, 0.0]  # 1 cm off, parallel
    far = EDGE + [0.0, 0.05, 0.0]  # 5 cm off
    turned = np.array([[0.0, -0.4, 2.0], [0.0, 0.6, 2.0]])  # crosses the edge at right angles
    lines = np.stack([EDGE, near, far, turned])
    pairs = np.array([[0, 1], [0, 2], [0, 3]])
    labels = merge_groups(lines, pairs, max_angle_deg=2.0, max_dist=0.02)
    assert labels[0] == labels[1] and len({labels[0], labels[2], labels[3]}) == 3
    assert len(set(merge_groups(lines, pairs, 2.0, 0.06)[:3])) == 1  # a looser gate takes the 5 cm one too


def test_track_extents_cast_detection_endpoints_onto_the_line():
    """A detection of the stretch [t0, t1] gives back t0 and t1 (metres from the line's first endpoint), also when
    it lies a pixel off the line's projection (its endpoints are moved onto it first)."""
    line = np.stack([_point(0.3), _point(0.6)])  # the 3D line knows only 30 cm of the edge
    segs = np.array([_detection(VIEWS[0], 0.1, 0.9), _detection(VIEWS[1], 0.25, 0.7, shift_px=1.0),
                     _detection(VIEWS[2], 0.0, 1.0)])
    rows = np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0]])
    ids, vals = track_extents(line[None], rows, segs, VIEWS)
    assert (ids == 0).all()
    np.testing.assert_allclose(np.sort(vals), np.sort(np.array([0.1, 0.9, 0.25, 0.7, 0.0, 1.0]) - 0.3), atol=2e-3)
    # grown to the extremes; past one outlier at each end, to the next ones; never shrunk
    np.testing.assert_allclose(extended(line[None], ids, vals)[0], np.stack([_point(0.0), _point(1.0)]), atol=2e-3)
    np.testing.assert_allclose(extended(line[None], ids, vals, 1)[0], np.stack([_point(0.1), _point(0.9)]), atol=2e-3)
    np.testing.assert_allclose(extended(line[None], ids[:2], vals[:2], 1)[0], line)  # too few values: as it was
    np.testing.assert_allclose(extended(line[None], ids[:2], np.array([0.05, 0.1]))[0], line)  # inside: not shrunk


def _map(lines, dets, edge_line):
    """LineMap of ``lines`` whose track k holds the detections ``dets[k]`` (list of (view index, segment))."""
    tracks = [[(VIEWS[vi].name, di, seg) for vi, di, seg in t] for t in dets]
    corners = np.zeros((len(edge_line), 4, 3))
    return LineMap(np.asarray(lines, float), tracks, planes={"corners": corners, "edge_line": np.asarray(edge_line)},
                   metadata={"n_edge_lines": 3})


def test_aggregate_merges_fragments_and_spans_the_track():
    """Two plane-edge fragments of one edge (0.5 cm apart, both found in view 0's detection) become one line with
    both tracks, and that line spans the detections (the whole edge); an on-plane line elsewhere is untouched and
    stays after the edges; the planes' edge -> line table follows."""
    frag_a = np.stack([_point(0.1), _point(0.3)])
    frag_b = np.stack([_point(0.5), _point(0.7)]) + [0.0, 0.005, 0.0]
    edge_c = np.array([[0.3, -0.3, 2.2], [0.3, 0.0, 2.2]])
    other = np.array([[-0.3, -0.3, 2.5], [-0.3, 0.2, 2.5]])
    whole = [_detection(v, 0.0, 1.0) for v in VIEWS]
    dets = [[(0, 4, whole[0]), (1, 2, whole[1])],  # fragment a: views 0 and 1
            [(0, 4, whole[0]), (2, 7, whole[2])],  # fragment b: views 0 and 2, the same detection in view 0
            [(1, 1, geo.project_segments(edge_c[None], VIEWS[1].cam_from_world, CAM)[0][0].reshape(4))],
            [(1, 0, _detection(VIEWS[1], 0.0, 0.1))]]  # an unrelated on-plane line (its track is not its geometry)
    lm = _map([frag_a, frag_b, edge_c, other], dets, edge_line=[[0, -1, -1, -1], [1, -1, -1, 2]])
    out = aggregate_linemap(lm, VIEWS, AggregateConfig(enabled=True))
    assert len(out) == 3 and out.metadata["n_edge_lines"] == 2
    assert edge_line_mask(out).tolist() == [True, True, False]
    assert out.planes["edge_line"].tolist() == [[0, -1, -1, -1], [0, -1, -1, 1]]
    np.testing.assert_allclose(out.lines[1], edge_c, atol=1e-9)
    assert sorted((o.image_name, o.line2d_index) for o in out.tracks[0]) == sorted(
        (VIEWS[vi].name, di) for vi, di in [(0, 4), (1, 2), (2, 7)])
    assert out.supports[0, 0] == 3
    np.testing.assert_allclose(np.linalg.norm(out.lines[0, 1] - out.lines[0, 0]), 1.0, atol=0.01)  # the whole edge
    # the fit tilts by the fragments' 5 mm disagreement over their 40 cm, and the extension carries that to the ends
    assert geo.point_line_distance(EDGE, out.lines[0][None]).max() < 0.01
    assert geo.point_line_distance(np.stack([frag_a.mean(0), frag_b.mean(0)]), out.lines[0][None]).max() < 0.003
    np.testing.assert_allclose(out.lines[2], other)  # one view, its own extent: never shrunk, not moved

    kept = aggregate_linemap(lm, VIEWS, AggregateConfig(enabled=True, merge=False, extend=False))
    np.testing.assert_allclose(kept.lines, lm.lines)
    assert aggregate_linemap(lm, VIEWS, AggregateConfig(enabled=False)) is lm


def test_absorb_targets_take_single_image_lines_lying_along_a_tracked_line():
    long = EDGE  # seen in 3 images
    along = np.stack([_point(0.2), _point(0.35)]) + [0.0, 0.01, 0.0]  # 1 cm off, within it
    off = np.stack([_point(0.5), _point(0.65)]) + [0.0, 0.03, 0.0]  # 3 cm off
    turned = np.array([[0.6, 0.1, 2.0], [0.75, 0.1 + 0.15 * np.tan(np.radians(10)), 2.0]])  # 10 deg
    past = np.stack([_point(0.9), _point(1.2)])  # two thirds beyond the tracked line's end
    lines = np.stack([long, along, off, turned, past])
    n_img = np.array([3, 1, 1, 1, 1])
    assert absorb_targets(lines, n_img, 0.02, 3.0, 0.7).tolist() == [-1, 0, -1, -1, -1]
    assert absorb_targets(lines, n_img, 0.02, 3.0, 0.3).tolist() == [-1, 0, -1, -1, 0]
    assert absorb_targets(lines, np.array([1, 1, 1, 1, 1]), 0.02, 3.0, 0.7).tolist() == [-1] * 5  # none tracked


def test_aggregate_absorbs_a_single_image_edge_into_the_tracked_line():
    """A single-image plane edge along a tracked on-plane line joins it: its detection enters the track, the planes'
    table points at the line, which now counts as a plane edge and moves before the on-plane lines."""
    whole = [_detection(v, 0.0, 1.0) for v in VIEWS]
    short = np.stack([_point(0.4), _point(0.5)]) + [0.0, 0.005, 0.0]
    lm = _map([short, EDGE], [[(2, 3, _detection(VIEWS[2], 0.4, 0.5))], [(0, 1, whole[0]), (1, 1, whole[1])]],
              edge_line=[[0, -1, -1, -1]])
    lm.metadata["n_edge_lines"] = 1
    out = aggregate_linemap(lm, VIEWS, AggregateConfig(enabled=True))
    assert len(out) == 1 and out.metadata["aggregate"]["absorbed"] == 1 and out.metadata["n_edge_lines"] == 1
    assert out.planes["edge_line"].tolist() == [[0, -1, -1, -1]] and out.supports[0, 0] == 3
    np.testing.assert_allclose(out.lines[0], EDGE, atol=2e-3)
    assert len(aggregate_linemap(lm, VIEWS, AggregateConfig(enabled=True, absorb=False))) == 2


def _plane_depth(view, z_world=2.0):
    """The camera-frame depth map of the world plane z = ``z_world`` seen from ``view`` (COLMAP pixel centres)."""
    from lipmap.poses import invert_T

    H, W = view.camera.height, view.camera.width
    uv = np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2)
    T = invert_T(view.cam_from_world)
    rays = geo.unproject_points(uv, 1.0, view.camera) @ T[:3, :3].T
    X = T[:3, 3] + ((z_world - T[2, 3]) / rays[:, 2])[:, None] * rays
    return geo.transform_points(view.cam_from_world, X)[:, 2].reshape(H, W)


def test_track_extents_with_a_depth_check_drop_endpoints_off_the_sensor_depth():
    """With the sensor depth of the surface the edge lies on, every endpoint counts; where a view's depth says the
    surface is elsewhere (1 m from the camera), that view's endpoints do not; where it has no depth, they count."""
    line = np.stack([_point(0.3), _point(0.6)])
    segs = np.array([_detection(VIEWS[0], 0.1, 0.9), _detection(VIEWS[1], 0.25, 0.7), _detection(VIEWS[2], 0.0, 1.0)])
    rows = np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0]])
    true = {v.name: _plane_depth(v) for v in VIEWS}
    _, vals = track_extents(line[None], rows, segs, VIEWS, depth_by_view=true, depth_tol=0.05)
    assert len(vals) == 6
    other = {**true, VIEWS[2].name: np.full_like(true[VIEWS[2].name], 1.0)}
    _, vals = track_extents(line[None], rows, segs, VIEWS, depth_by_view=other, depth_tol=0.05)
    np.testing.assert_allclose(np.sort(vals), np.sort(np.array([0.1, 0.9, 0.25, 0.7]) - 0.3), atol=2e-3)
    holes = {**true, VIEWS[2].name: np.zeros_like(true[VIEWS[2].name])}
    assert len(track_extents(line[None], rows, segs, VIEWS, depth_by_view=holes, depth_tol=0.05)[1]) == 6
    assert len(track_extents(line[None], rows, segs, VIEWS, depth_by_view=other, depth_tol=0.0)[1]) == 6  # off
