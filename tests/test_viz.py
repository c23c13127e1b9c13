"""lipmap.viz: overlays land on the right pixels, visibility, plane renders, virtual cameras, PR curves."""
from __future__ import annotations

import numpy as np

from lipmap import viz
from lipmap.linemap import LineMap
from lipmap.poses import make_T
from lipmap.scene import Camera, Scene, View
from lipmap.testing import rect

CAM = Camera(64, 48, (50.0, 50.0, 32.0, 24.0))


def _redness(arr):
    a = arr.astype(int)
    return (a[..., 0] > 180) & (a[..., 1] < 110) & (a[..., 2] < 110)


def test_overlay_array_pixel_convention():
    # y = 0.01 at z = 1 projects to v = 24 + 50 * 0.01 = 24.5: the centre of row 24 (COLMAP convention)
    line = np.array([[[-0.3, 0.01, 1.0], [0.3, 0.01, 1.0]]])  # u from 17 to 47
    segs, ok = viz.project_to_image(line, np.eye(4), CAM)
    assert ok.all()
    np.testing.assert_allclose(segs[0], [[17.0, 24.5], [47.0, 24.5]], atol=1e-9)
    arr = viz.overlay_array(np.zeros((48, 64, 3), np.uint8), CAM, [(segs, viz.PROJECTED_COLOR, 1.0)])
    assert arr.shape == (48, 64, 3)
    red = _redness(arr)
    rows = np.flatnonzero(red[:, 32])
    assert len(rows) and abs(rows.mean() - 24) <= 0.5, rows  # centred on row 24
    assert rows.min() >= 23 and rows.max() <= 25
    assert red[24, 19:46].all()  # along the whole segment
    assert not red[24, :15].any() and not red[24, 50:].any()  # and not beyond its ends
    assert not red[:20].any() and not red[29:].any()


def test_overlay_figure_projection_lands_where_expected():
    cam = Camera(160, 120, (100.0, 100.0, 80.0, 60.0))
    T = make_T(np.eye(3), [0.0, 0.0, 0.5])
    line = np.array([[[-0.2, -0.1, 1.5], [0.2, 0.1, 1.5]]])  # z_cam = 2: u = 80 -+ 10, v = 60 -+ 5
    segs, ok = viz.project_to_image(line, T, cam)
    np.testing.assert_allclose(segs[0], [[70, 55], [90, 65]], atol=1e-9)
    det = np.array([[10.0, 100.0, 40.0, 100.0]])
    fig = viz.overlay_figure(None, cam, det, [("left", segs), ("right", segs + np.array([0, 30.0]))], "test")
    arr = viz.figure_to_array(fig)
    red = _redness(arr)
    H = arr.shape[0]
    for ax, dv in zip(fig.axes[:2], (0.0, 30.0)):
        x, y = ax.transData.transform((80.0, 60.0 + dv))  # midpoint of the projected segment
        r, c = int(round(H - y)), int(round(x))
        assert red[r - 1 : r + 2, c - 1 : c + 2].any(), (r, c)
        x2, y2 = ax.transData.transform((80.0, 60.0 + dv + 12))  # 12 image px away: no line there
        assert not red[int(round(H - y2)), int(round(x2))]
        # the detected line is blue under it
        xb, yb = ax.transData.transform((25.0, 100.0))
        px = arr[int(round(H - yb)), int(round(xb))].astype(int)
        assert px[2] > 180 and px[0] < 120, px


def test_visible_line_indices_planes_and_depth():
    T = np.eye(4)
    front = [[-0.2, 0.0, 1.0], [0.2, 0.0, 1.0]]
    behind = [[-0.2, 0.05, 3.0], [0.2, 0.05, 3.0]]
    outside = [[5.0, 0.0, 1.0], [6.0, 0.0, 1.0]]
    back_of_camera = [[-0.2, 0.0, -1.0], [0.2, 0.0, -1.0]]
    lines = np.array([front, behind, outside, back_of_camera])
    wall = rect([0, 0, 2.0], 2.0, 2.0)[None]  # between the camera and the "behind" line
    assert list(viz.visible_line_indices(lines, T, CAM)) == [0, 1]
    assert list(viz.visible_line_indices(lines, T, CAM, corners=wall)) == [0]
    depth = np.full((48, 64), 2.0, np.float32)
    assert list(viz.visible_line_indices(lines, T, CAM, depth=depth)) == [0]
    assert list(viz.visible_line_indices(lines, T, CAM, depth=np.zeros((48, 64), np.float32))) == [0, 1]


def test_render_planes_normal_colour_and_outline():
    # a square facing the camera at z = 2 spanning u, v = 32 -+ 12.3, 24 -+ 12.3: pixel columns 20..43
    # (centres 20.5 .. 43.5) and rows 12..35 are inside
    corners = rect([0, 0, 2.0], 0.492, 0.492)[None]
    rgb, plane = viz.render_planes(corners, np.eye(4), CAM)
    assert plane.shape == (48, 64)
    assert np.array_equal(np.flatnonzero(plane[24] == 0), np.arange(20, 44))
    assert np.array_equal(np.flatnonzero(plane[:, 32] == 0), np.arange(12, 36))
    # normal turned to the camera = (0, 0, -1) -> (n + 1) / 2 = (0.5, 0.5, 0), head-on shading ~1
    np.testing.assert_allclose(rgb[24, 32], [0.5, 0.5, 0.0], atol=0.01)
    np.testing.assert_allclose(rgb[2, 2], viz.BACKGROUND)
    # the plane's first pixel (and the background's first) are outlined
    np.testing.assert_allclose(rgb[24, 20], 0.35 * rgb[24, 21], atol=0.002)
    np.testing.assert_allclose(rgb[24, 21], rgb[24, 32], atol=0.01)


def test_up_direction_ignores_pitch():
    from scipy.spatial.transform import Rotation

    # z-up world: a level camera looking along +x has rows x_cam = (0,-1,0), y_cam = (0,0,-1), z_cam = (1,0,0)
    R0 = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
    views = []
    for i, (yaw, pitch) in enumerate([(0, -30), (40, -35), (100, -25), (200, -40)]):
        Rw = Rotation.from_euler("z", yaw, degrees=True).as_matrix()
        Rp = Rotation.from_euler("x", pitch, degrees=True).as_matrix()  # pitch about the camera x axis
        views.append(View(f"v{i}", CAM, make_T(Rp @ R0 @ Rw.T, [0, 0, 0]), color_path=None))
    np.testing.assert_allclose(viz.up_direction(views), [0, 0, 1], atol=1e-6)


def test_overview_camera_sees_everything_from_outside():
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0, 0], [4, 3, 2.5], size=(500, 3))
    T, cam, frame = viz.overview_camera(pts, [0, 0, 1.0], 320, 240)
    from lipmap.geometry import project_points

    uv, z = project_points(pts, T, cam)
    assert (z > 0).all()
    assert (uv[:, 0] >= 0).all() and (uv[:, 0] <= 320).all() and (uv[:, 1] >= 0).all() and (uv[:, 1] <= 240).all()
    C = -T[:3, :3].T @ T[:3, 3]
    assert C[2] > 2.5  # above the scene
    assert not ((C >= pts.min(0)) & (C <= pts.max(0))).all()  # outside its box
    up_img = project_points(np.array([[2, 1.5, 0.0], [2, 1.5, 2.5]]), T, cam)[0]
    assert up_img[1, 1] < up_img[0, 1]  # world up is image up


def test_pr_curve_known_answer(tmp_path):
    gt = np.stack([np.linspace(0, 1, 2001), np.zeros(2001), np.zeros(2001)], 1)  # 0.5 mm spacing
    lines = np.array([[[0.0, 0.01, 0.0], [1.0, 0.01, 0.0]]])  # 1 cm off the ground truth
    d = viz.pr_curve(LineMap(lines), gt, thresholds=[0.005, 0.0099, 0.0115, 0.05])
    # (recall: GT points lie up to 5 mm along the line from the 1 cm-spaced samples -> <= 11.2 mm)
    np.testing.assert_allclose(d["line"]["precision"], [0, 0, 1, 1])
    np.testing.assert_allclose(d["line"]["recall"], [0, 0, 1, 1])
    np.testing.assert_allclose(d["junction"]["precision"], [0, 0, 1, 1])
    out = viz.plot_pr_curve(LineMap(lines), gt, tmp_path / "pr.png", thresholds=np.geomspace(0.001, 0.2, 12))
    import cv2

    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 500


def test_render_linemap_views_writes_both(tmp_path):
    import cv2

    cam = Camera(80, 60, (60.0, 60.0, 40.0, 30.0))
    img = np.full((60, 80, 3), 120, np.uint8)
    cv2.imwrite(str(tmp_path / "m0.png"), img)
    panel = rect([0, 0, 3.0], 1.0, 0.75)
    lines = np.stack([panel, np.roll(panel, -1, axis=0)], 1)  # the 4 edges
    corners = np.stack([panel, rect([0, 0, 5.0], 4, 3)])
    tracks = [[("m0.png", i, np.array([0, 0, 10.0, 10.0]))] for i in range(4)]
    lm = LineMap(lines, tracks, planes={"corners": corners}, metadata={"method": "lipmap"})
    view = View("m0.png", cam, make_T(np.eye(3), [0.1, 0.0, 0.0]), color_path=tmp_path / "m0.png")
    scene = Scene("s", "synthetic", tmp_path, [view], [])
    paths = viz.render_linemap_views(lm, scene, tmp_path)
    assert [p.name for p in paths] == ["linemap.png", "planes.png"]
    for p in paths:
        im = cv2.imread(str(p))
        assert im is not None and im.shape[1] > 600
    # without a scene: the overview only
    paths = viz.render_linemap_views(LineMap(lines), None, tmp_path / "alone")
    assert [p.name for p in paths] == ["linemap.png"]


def test_linemap_figure_colour_bar_names_the_unverified_lines():
    """A line no detection verifies (support 0) shares the colour of support 1 on the log scale, and the bar says so."""
    panel = rect([0, 0, 3.0], 1.0, 0.75)
    lines = np.stack([panel, np.roll(panel, -1, axis=0)], 1)
    tracks = [[], [("a.png", 0, np.zeros(4))], [("a.png", 1, np.zeros(4)), ("b.png", 0, np.zeros(4))], []]
    fig = viz.linemap_figure(LineMap(lines, tracks))
    bar = fig.axes[-1]
    labels = [t.get_text() for t in bar.get_yticklabels()]
    assert labels[0] == "0-1" and "2" in labels and "track test" in bar.get_ylabel()
