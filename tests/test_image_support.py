"""lipmap.image_support: the share of each 3D line's visible length that the images show, known answers on
constructed views."""
from __future__ import annotations

import numpy as np

from lipmap import geometry as geo
from lipmap import viz
from lipmap.image_support import image_support
from lipmap.linemap import LineMap
from lipmap.scene import Camera, View

CAM = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))
VIEWS = [View(f"v{i}", CAM, viz.look_at(np.array([x, 0.0, 0.0]), (0.0, 0.0, 2.0), up=(0.0, 1.0, 0.0)),
              color_path=None) for i, x in enumerate((0.0, 0.2))]
LINE = np.array([[-0.4, 0.1, 2.0], [0.4, 0.1, 2.0]])  # 80 cm at 2 m: ~210 px in each view


def _part(view, t0, t1, shift_px=0.0):
    """The detection of LINE's stretch [t0, t1] (fractions of its length) in ``view``, moved ``shift_px`` across."""
    seg = LINE[0] + np.array([[t0], [t1]]) * (LINE[1] - LINE[0])
    proj, _ = geo.project_segments(seg[None], view.cam_from_world, view.camera)
    a, b = proj[0]
    n = np.array([-(b - a)[1], (b - a)[0]]) / np.linalg.norm(b - a)
    return np.concatenate([a + shift_px * n, b + shift_px * n])


def _support(dets: dict, depth=None) -> dict:
    """``image_support`` of LINE in the views of ``dets`` ({view index: [segments]}; the other views have no lines)."""
    lines_by_view = {VIEWS[i].name: np.array(d).reshape(-1, 4) for i, d in dets.items()}
    return image_support(LineMap(LINE[None], [[]]), VIEWS, lines_by_view, depth)


def test_a_line_its_detections_cover_is_fully_shown():
    r = _support({0: [_part(VIEWS[0], 0, 1)], 1: [_part(VIEWS[1], 0, 1)]})
    assert r["per_line"][0] == 1.0 and r["shown"] == 1.0


def test_a_line_past_its_detections_is_shown_only_where_they_are():
    """Detections of the first half in one view and of the first 3/4 in the other: about 5/8 shown (samples are
    32 per view); two detections end to end show what one would."""
    r = _support({0: [_part(VIEWS[0], 0, 0.5)], 1: [_part(VIEWS[1], 0, 0.75)]})
    assert abs(r["per_line"][0] - 0.625) < 0.05
    split = _support({0: [_part(VIEWS[0], 0, 0.25), _part(VIEWS[0], 0.25, 0.5)], 1: [_part(VIEWS[1], 0, 0.75)]})
    assert abs(split["per_line"][0] - r["per_line"][0]) < 1e-9


def test_a_detection_beside_or_turned_from_the_line_shows_nothing():
    assert _support({0: [_part(VIEWS[0], 0, 1, shift_px=1.5)]})["per_line"][0] == 1.0
    assert _support({0: [_part(VIEWS[0], 0, 1, shift_px=3.0)]})["per_line"][0] == 0.0
    a, b = _part(VIEWS[0], 0, 1).reshape(2, 2)
    c, t = (a + b) / 2, np.radians(3.0)
    turned = ((np.stack([a, b]) - c) @ np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]).T + c).reshape(4)
    assert _support({0: [turned]})["per_line"][0] == 0.0
    assert _support({})["per_line"].shape == (1,) and np.isnan(_support({})["shown"])


def test_a_view_that_sees_the_line_without_detecting_it_counts_and_one_that_cannot_see_it_does_not():
    """View 1 sees the line and detects nothing: half shown over the two views. With a sensor depth of 1 m in view 1
    (a surface in front of the line, 2 m away) it cannot see the line and does not count."""
    r = _support({0: [_part(VIEWS[0], 0, 1)], 1: []})
    assert r["per_line"][0] == 0.5 and r["views"][0] == 2
    wall = {VIEWS[1].name: np.full((CAM.height, CAM.width), 1.0, np.float32)}
    r = _support({0: [_part(VIEWS[0], 0, 1)], 1: []}, wall)
    assert r["per_line"][0] == 1.0 and r["views"][0] == 1
    no_depth = {VIEWS[1].name: np.zeros((CAM.height, CAM.width), np.float32)}  # 0: unknown, no occlusion test
    assert _support({0: [_part(VIEWS[0], 0, 1)], 1: []}, no_depth)["views"][0] == 2
