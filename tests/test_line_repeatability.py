"""benchmarks/line_repeatability.py: detections placed on the planes, looked for in the next view, known answers on the
panel-and-wall scene."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import benchmark_module
from lipmap import geometry as geo
from lipmap.mapping.assign import PlaneRaycaster
from lipmap.testing import wall_scene


def _bench():
    return benchmark_module("line_repeatability.py")


def _project(seg3d, view):
    p, valid = geo.project_segments(seg3d, view.cam_from_world, view.camera)
    assert valid.all()
    return p.reshape(-1, 4)


def _rotated(det, angle):
    """Each 2D segment (N, 4) turned by ``angle`` rad about its midpoint."""
    R = Rotation.from_euler("z", angle).as_matrix()[:2, :2]
    a, b = det[:, :2], det[:, 2:]
    m = (a + b) / 2
    return np.concatenate([m + (a - m) @ R.T, m + (b - m) @ R.T], 1)


def test_detections_are_placed_on_the_planes_and_found_again_by_the_paper_gate():
    bench = _bench()
    corners, views = wall_scene()
    caster = PlaneRaycaster(corners)
    on_panel = np.array([[-0.3, -0.1, 3.0], [0.4, 0.1, 3.0]])  # the panel spans x -0.5..0.7, y -0.45..0.35
    on_wall = np.array([[-1.5, 1.0, 5.0], [-0.9, 1.2, 5.0]])  # the back wall, left of and above the panel
    across = np.array([[0.2, 0.0, 3.0], [0.2, 0.0, 3.0]])  # from the panel out past its right border onto the wall
    a = views[0]
    det_a = np.concatenate([_project(on_panel[None], a), _project(on_wall[None], a)])
    # the third runs in the image from inside the panel to well past its border
    inside = _project(across[None], a)[0, :2]
    det_a = np.concatenate([det_a, [[inside[0], inside[1], inside[0] + 120.0, inside[1] + 4.0]]])

    segs, ok = bench.lift_to_planes(det_a, a, caster)
    assert ok.tolist() == [True, True, False]  # the one across the occluding border is on no single 3D line
    np.testing.assert_allclose(segs[0, :, 2], 3.0, atol=1e-6)
    np.testing.assert_allclose(segs[1, :, 2], 5.0, atol=1e-6)
    # the lifted segment lies on the true line (5 % to 95 % of the detection)
    d = on_panel[1] - on_panel[0]
    for p in segs[0]:
        assert np.linalg.norm(np.cross(p - on_panel[0], d)) / np.linalg.norm(d) < 1e-6

    b = views[1]
    # view 1 finds the panel line exactly and the wall line turned by 0.04 rad
    det_b = np.concatenate([_project(on_panel[None], b), _rotated(_project(on_wall[None], b), 0.04)])
    dets = {a.name: det_a, b.name: det_b}
    m = bench.measure(lambda view, image: dets[view.name], [a, b], {a.name: None, b.name: None}, caster, [1])
    p = m["pairs"][1]
    assert len(p["angle"]) == 2
    order = np.argsort(p["angle"])
    assert p["angle"][order[0]] < 1e-6 and p["dist"][order[0]] < 1e-3
    assert p["angle"][order[1]] == pytest.approx(0.04, abs=1e-6)
    assert bench.share(p, 0.01, 2.0) == 0.5  # the paper's gate finds the panel line only
    assert bench.share(p, 0.05, 50.0) == 1.0
    assert m["detections_per_view"] == 2.5


def test_unknown_detector_names_the_choices():
    with pytest.raises(SystemExit, match="unknown detector 'sold2'.*lsd"):
        _bench().detector("sold2")


def test_lines_from_a_file_are_read_per_view(tmp_path):
    import h5py

    corners, views = wall_scene()
    path = tmp_path / "lines2d.h5"
    seg = np.array([[10.0, 20.0, 200.0, 40.0]])
    with h5py.File(path, "w") as f:
        f.create_group(views[0].name).create_dataset("lines", data=seg)
    read = _bench().detector(str(path))
    np.testing.assert_allclose(read(views[0], None), seg)
    with pytest.raises(SystemExit, match="has no lines for image v1"):
        read(views[1], None)
    with pytest.raises(SystemExit, match="does not exist"):
        _bench().detector(str(tmp_path / "missing.h5"))
