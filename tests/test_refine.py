"""Multi-view line refinement: known answers on constructed cameras and lines."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from lipmap import geometry as geo
from lipmap import viz
from lipmap.linemap import LineMap
from lipmap.mapping.extract import ExtractConfig, add_tracks
from lipmap.mapping.refine import (
    RefineConfig,
    refine_linemap,
    refine_segments,
    reprojection_residuals,
)
from lipmap.scene import Camera, View

CAM = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))


def look_at(center, target=(0.0, 0.0, 2.0)):
    """cam_from_world of a camera at ``center`` looking at ``target``."""
    return viz.look_at(center, target, up=(0.0, 1.0, 0.0))


# five cameras 10-30 cm apart, 2 m from the lines: the narrow baselines of a handheld sequence
CENTERS = [np.array([x, y, 0.0]) for x, y in [(0, 0), (0.15, 0), (-0.15, 0.05), (0.3, -0.05), (-0.3, 0.0)]]
VIEWS = [View(f"seq-01/frame-{i:06d}.color.png", CAM, look_at(c), color_path=None) for i, c in enumerate(CENTERS)]
TRUE = np.array([[[-0.4, -0.2, 2.0], [0.4, -0.25, 2.1]],
                 [[-0.3, 0.3, 1.9], [-0.25, -0.3, 2.0]],
                 [[0.1, 0.25, 2.2], [0.5, 0.1, 2.3]]])


def observations(lines, views):
    """Every view's exact projection of every line: (line index, segments (M, 2, 2), projections (M, 3, 4))."""
    li, seg, P = [], [], []
    for v in views:
        proj, _ = geo.project_segments(lines, v.cam_from_world, v.camera)
        li += list(range(len(lines)))
        seg.append(proj)
        P += [geo.projection_matrices(v.cam_from_world, v.camera)] * len(lines)
    return np.array(li), np.concatenate(seg), np.stack(P)


def perturbed(lines, rng, shift=0.015, deg=1.0):
    """Each line shifted ``shift`` metres sideways (across the views' rays, where they can see it) and turned
    ``deg`` about the viewing ray through its midpoint."""
    out = []
    for s in lines:
        mid, d = s.mean(0), s[1] - s[0]
        ray = mid / np.linalg.norm(mid)
        n = np.cross(d, ray)
        R = Rotation.from_rotvec(np.deg2rad(deg) * rng.choice([-1, 1]) * ray).as_matrix()
        out.append((s - mid) @ R.T + mid + shift * n / np.linalg.norm(n))
    return np.array(out)


def line_offset(a, b):
    """Largest distance of a's endpoints to b's infinite line, per line (m)."""
    return geo.point_line_distance(a, b[:, None]).max(-1)


def test_backprojected_plane_gives_the_pixel_distance_to_the_segment_line():
    rng = np.random.default_rng(0)
    seg = np.array([[100.0, 120.0], [500.0, 300.0]])
    v = VIEWS[1]
    X = rng.uniform([-0.5, -0.4, 1.5], [0.5, 0.4, 2.5], size=(20, 3))
    plane = geo.backprojected_planes(seg[None], geo.projection_matrices(v.cam_from_world, v.camera))[0]
    uv, z = geo.project_points(X, v.cam_from_world, v.camera)
    expected = geo.point_line_distance(uv, np.broadcast_to(seg, (20, 2, 2)))
    assert np.allclose(np.abs(X @ plane[:3] + plane[3]) / z, expected, atol=1e-9)


def test_refinement_recovers_lines_shifted_1_5_cm_from_five_narrow_views():
    rng = np.random.default_rng(1)
    start = perturbed(TRUE, rng)
    li, seg, P = observations(TRUE, VIEWS)
    before = np.abs(reprojection_residuals(start, li, seg, P)).max()
    out = refine_segments(start, li, seg, P, RefineConfig(iterations=10))
    assert before > 2.0  # pixels: the start is clearly off in the views
    assert np.abs(reprojection_residuals(out, li, seg, P)).max() < 0.5
    assert line_offset(out, TRUE).max() < 0.004 < line_offset(start, TRUE).min()


def test_an_outlying_detection_does_not_drag_the_line():
    rng = np.random.default_rng(2)
    start = perturbed(TRUE, rng)
    li, seg, P = observations(TRUE, VIEWS)
    bad = seg.copy()
    first = np.flatnonzero(li == 0)[0]
    bad[first] += np.array([0.0, 25.0])  # one view's detection of line 0 is another line 25 px away
    out = refine_segments(start, li, bad, P, RefineConfig(iterations=10))
    assert line_offset(out[:1], TRUE[:1]).max() < 0.006
    # without the robust weights (huge scale: least squares) the same outlier pulls it well off
    ls = refine_segments(start, li, bad, P, RefineConfig(iterations=10, robust_px=1e6))
    assert line_offset(ls[:1], TRUE[:1]).max() > 2 * line_offset(out[:1], TRUE[:1]).max()


def test_a_line_seen_once_does_not_move_and_the_prior_holds_the_unseen_direction():
    li, seg, P = observations(TRUE, VIEWS[:1])
    start = TRUE + 0.01
    assert np.array_equal(refine_segments(start, li, seg, P), start)
    # two views: the endpoints may slide along the line, and the prior keeps them where they were
    li, seg, P = observations(TRUE, VIEWS[:2])
    out = refine_segments(TRUE, li, seg, P)
    assert np.abs(out - TRUE).max() < 1e-6


def test_refine_linemap_lengthens_the_strict_tracks_of_lines_lifted_from_one_view():
    rng = np.random.default_rng(3)
    start = perturbed(TRUE, rng, shift=0.01, deg=0.5)
    by_view = {v.name: geo.project_segments(TRUE, v.cam_from_world, v.camera)[0].reshape(-1, 4) for v in VIEWS}
    # each line starts with one observation: the detection it was lifted from, in view 0
    tracks = [[(VIEWS[0].name, i, by_view[VIEWS[0].name][i])] for i in range(len(TRUE))]
    lm = LineMap(start, tracks)
    strict = ExtractConfig()
    before = add_tracks(lm, VIEWS, by_view, strict).supports[:, 0]
    refined = refine_linemap(lm, VIEWS, by_view, RefineConfig(iterations=10))
    after = add_tracks(refined, VIEWS, by_view, strict).supports[:, 0]
    assert before.max() <= 2 and np.all(after == len(VIEWS))
    assert refined.metadata["n_refined"] == len(TRUE)
    assert line_offset(refined.lines, TRUE).max() < 0.004


def test_disabled_refinement_returns_the_map_unchanged():
    lm = LineMap(TRUE, [[] for _ in TRUE])
    assert refine_linemap(lm, VIEWS, {}, RefineConfig(enabled=False)) is lm


def test_refine_lines_must_name_which_lines():
    import pytest

    from lipmap.errors import InputError
    from lipmap.mapping.pipeline import get_conf

    assert get_conf({"refine": {"lines": "all"}}).refine.lines == "all"
    with pytest.raises(InputError, match="refine.lines must be one of on-plane, edges, all, got 'edge'"):
        get_conf({"refine": {"lines": "edge"}})


def test_no_observations():
    out = refine_segments(TRUE, np.zeros(0, int), np.zeros((0, 2, 2)), np.zeros((0, 3, 4)))
    assert np.array_equal(out, TRUE)
