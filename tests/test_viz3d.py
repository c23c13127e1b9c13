"""lipmap.viz3d: one trace per group, geometry that lands where the poses say, a page that needs no network.
(test_report_html.py opens the pages in a real browser.)"""
from __future__ import annotations

import numpy as np
import pytest

from lipmap import geometry as geo
from lipmap import viz3d
from lipmap.errors import InputError
from lipmap.linemap import LineMap
from lipmap.poses import camera_center, make_T
from lipmap.scene import Camera
from lipmap.testing import rect

CAM = Camera(64, 48, (40.0, 50.0, 30.0, 26.0))  # off-centre principal point, fx != fy: a swap would show


def _rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _lipmap_map(n_edges=3, n_on_plane=5, seed=0):
    rng = np.random.default_rng(seed)
    n = n_edges + n_on_plane
    lines = rng.normal(size=(n, 2, 3))
    corners = np.stack([rect([0, 0, 3.0], 1.0, 0.5), rect([1, 0, 4.0], 0.5, 0.5)])
    edge_line = np.full((2, 4), -1)
    edge_line.ravel()[:n_edges] = np.arange(n_edges)
    supports = np.stack([np.arange(1, n + 1), np.arange(1, n + 1) * 2], 1)
    return LineMap(lines, supports=supports, planes={"corners": corners, "edge_line": edge_line},
                   metadata={"method": "lipmap"})


class TestSegmentsXYZ:
    def test_one_polyline_with_gaps(self):
        lines = np.arange(12, dtype=float).reshape(2, 2, 3)
        xyz = viz3d.segments_xyz(lines)
        assert xyz.shape == (6, 3) and xyz.dtype == np.float32
        np.testing.assert_array_equal(xyz[[0, 1, 3, 4]], lines.reshape(4, 3))
        assert np.isnan(xyz[[2, 5]]).all()

    def test_empty_and_bad_shape(self):
        assert viz3d.segments_xyz(np.zeros((0, 2, 3))).shape == (0, 3)
        with pytest.raises(InputError):
            viz3d.segments_xyz(np.zeros((3, 2, 2)))


class TestPlotLinemap:
    def test_one_trace_per_kind_with_support_hover(self):
        lm = _lipmap_map(3, 5)
        fig = viz3d.init_figure()
        idx = viz3d.plot_linemap(fig, lm)
        assert [fig.data[i].meta["kind"] for i in idx] == ["plane edge", "on-plane"]
        assert [fig.data[i].meta["n"] for i in idx] == [3, 5]
        edges = fig.data[idx[0]]
        np.testing.assert_array_equal(np.asarray(edges.customdata), np.repeat([1, 2, 3], 3))  # support per vertex
        np.testing.assert_allclose(np.asarray(edges.x, dtype=float)[[0, 1]], lm.lines[0, :, 0], rtol=1e-6)

    def test_lift_and_unknown_maps_are_one_kind(self):
        lm = LineMap(np.zeros((4, 2, 3)), metadata={"method": "lift"})
        assert set(viz3d.line_kinds(lm)) == {"lift"}
        assert set(viz3d.line_kinds(LineMap(np.zeros((2, 2, 3))))) == {"line"}
        # a lipmap map without an edge table cannot tell its kinds apart: not guessed
        assert set(viz3d.line_kinds(LineMap(np.zeros((2, 2, 3)), metadata={"method": "lipmap"}))) == {"line"}

    def test_color_switch_restyles_every_line_trace(self):
        lm = _lipmap_map(3, 5)
        fig = viz3d.init_figure()
        idx = viz3d.plot_linemap(fig, lm)
        (menu,) = fig.layout.updatemenus
        by_kind, by_support = menu.buttons
        assert list(by_kind.args[1]) == idx and list(by_support.args[1]) == idx
        assert list(by_kind.args[0]["line.color"]) == [viz3d.KIND_COLORS["plane edge"], viz3d.KIND_COLORS["on-plane"]]
        colors = by_support.args[0]["line.color"]
        assert [len(c) for c in colors] == [9, 15]  # one value per vertex, gaps included
        np.testing.assert_allclose(colors[1][::3], np.round(np.log10([4, 5, 6, 7, 8]), 3))
        assert list(by_support.args[0]["line.cmax"]) == [pytest.approx(np.log10(8), abs=1e-3)] * 2
        assert list(by_support.args[0]["line.showscale"]) == [True, False]  # one colour bar for all kinds


class TestPlotPlanes:
    def test_one_mesh_two_triangles_per_plane_coloured_by_normal(self):
        corners = np.stack([rect([0, 0, 3.0], 1.0, 0.5), rect([0, 0, 5.0], 2.0, 1.0, axes=np.eye(3)[[1, 2, 0]])])
        fig = viz3d.init_figure()
        i = viz3d.plot_planes(fig, corners)
        mesh = fig.data[i]
        assert mesh.type == "mesh3d" and mesh.meta == {"role": "planes", "n": 2, "n_all": 2}
        assert len(mesh.x) == 8 and len(mesh.i) == 4
        # plane 0 faces +-z -> blue (n+1)/2 = (.5, .5, 1) or (.5, .5, 0); plane 1 faces +-x
        assert list(mesh.facecolor[:2]) == ["rgb(127,127,255)"] * 2 or list(mesh.facecolor[:2]) == ["rgb(127,127,0)"] * 2
        assert mesh.facecolor[2] in ("rgb(255,127,127)", "rgb(0,127,127)")

    def test_only_the_largest_beyond_the_cap(self):
        corners = np.stack([rect([0, 0, z], r, r) for z, r in ((1.0, 0.1), (2.0, 0.3), (3.0, 0.2))])
        fig = viz3d.init_figure()
        i = viz3d.plot_planes(fig, corners, max_planes=2)
        mesh = fig.data[i]
        assert mesh.meta["n"] == 2 and "largest 2 of 3" in mesh.name
        assert sorted(set(np.round(np.asarray(mesh.z, dtype=float), 3))) == [2.0, 3.0]

    def test_no_planes_no_trace(self):
        fig = viz3d.init_figure()
        assert viz3d.plot_planes(fig, None) is None and viz3d.plot_planes(fig, np.zeros((0, 4, 3))) is None
        assert len(fig.data) == 0


class TestCameras:
    def test_frustum_apex_at_centre_and_corners_on_the_image_border(self):
        T = make_T(_rot_y(30), [0.2, -0.1, 0.5])
        xyz = viz3d.frustums(T[None], CAM, size=0.3)
        assert xyz.shape == (12, 3) and np.isnan(xyz[-1]).all()
        apex = xyz[:-1][viz3d._APEX[:-1]]
        np.testing.assert_allclose(apex, np.repeat(camera_center(T)[None], 3, 0), atol=1e-6)
        rim = xyz[:4].astype(float)
        uv, z = geo.project_points(rim, T, CAM)
        np.testing.assert_allclose(z, 0.3, atol=1e-6)
        np.testing.assert_allclose(uv, [[0, 0], [64, 0], [64, 48], [0, 48]], atol=1e-4)

    def test_one_trace_per_group_with_hover_and_links_on_the_apex(self):
        T = np.stack([make_T(np.eye(3), [x, 0, 0]) for x in (0.0, 1.0, 2.0)])
        fig = viz3d.init_figure()
        i = viz3d.plot_cameras(fig, T, CAM, "queries", values=[1.0, 5.0, 20.0], cmin=0, cmax=10,
                               hovertext=["a", "b", "c"], customdata=["", "b.png", ""], group="q")
        tr = fig.data[i]
        assert len(fig.data) == 1 and tr.meta == {"role": "cameras", "group": "q", "n": 3} and len(tr.x) == 36
        text = np.asarray(tr.hovertext)
        assert sorted(set(text[text != ""])) == ["a", "b", "c"]
        assert np.asarray(tr.customdata).tolist().count("b.png") == 3  # the 3 apex vertices of camera 1
        np.testing.assert_array_equal(np.asarray(tr.line.color)[::12], [1.0, 5.0, 20.0])
        assert (tr.line.cmin, tr.line.cmax) == (0, 10)

    def test_mismatched_cameras(self):
        with pytest.raises(InputError, match="2 poses but 3 cameras"):
            viz3d.frustums(np.stack([np.eye(4)] * 2), [CAM] * 3, 0.1)
        assert viz3d.plot_cameras(viz3d.init_figure(), np.zeros((0, 4, 4)), CAM) is None


def test_linemap_html_is_one_offline_file(tmp_path):
    from types import SimpleNamespace

    lm = _lipmap_map()
    views = [SimpleNamespace(cam_from_world=make_T(np.eye(3), [0, 0, -d]), camera=CAM, name=f"v{d}",
                             center=np.array([0, 0, d])) for d in (1.0, 2.0)]
    path = viz3d.save_linemap_html(lm, tmp_path / "linemap.html", views=views)
    page = path.read_text()
    assert page.count("Plotly.newPlot") == 1 and "<script src=" not in page
    fig = viz3d.linemap_figure(lm, views)
    assert [t.meta["role"] for t in fig.data] == ["lines", "lines", "planes", "cameras"]
