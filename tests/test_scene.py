import numpy as np
import pytest

from lipmap import InputError
from lipmap.datasets.registration import register_depth
from lipmap.geometry import backproject_depth as backproject, project_cam_points as project
from lipmap.scene import Camera


def test_camera_pixel_convention_pin():
    cam = Camera(640, 480, (525, 525, 320, 240))
    rays = cam.pixel_rays()
    # COLMAP convention: the ray through the principal point lies between pixels 319 and 320.
    assert rays.shape == (480, 640, 3)
    np.testing.assert_allclose(rays[240, 320, :2], [0.5 / 525, 0.5 / 525])
    np.testing.assert_allclose(rays[239, 319, :2], [-0.5 / 525, -0.5 / 525])


def test_camera_scaled_is_exact():
    cam = Camera(640, 480, (525, 525, 320, 240))
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    p = np.array([[0.3, -0.2, 2.0]])
    uv, _ = project(p, cam)
    uv2, _ = project(p, half)
    np.testing.assert_allclose(uv2, uv * 0.5)


def test_camera_rejects_bad_model():
    with pytest.raises(InputError):
        Camera(10, 10, (1, 1, 5, 5), model="OPENCV")


def test_backproject_project_roundtrip():
    cam = Camera(64, 48, (50, 52, 31, 25))
    depth = np.random.default_rng(0).uniform(0.5, 3, (48, 64)).astype(np.float32)
    pts, idx = backproject(depth, cam)
    uv, z = project(pts, cam)
    np.testing.assert_allclose(z, depth.reshape(-1)[idx], rtol=1e-6)
    np.testing.assert_allclose(np.floor(uv[:, 0]), idx % 64)
    np.testing.assert_allclose(np.floor(uv[:, 1]), idx // 64)


def test_register_depth_known_answer():
    # A fronto-parallel wall at 2 m seen by a depth camera shifted 5 cm along x: registered depth
    # is still 2 m where covered, and the covered region shifts by f * b / z pixels.
    dcam = Camera(80, 60, (70, 70, 40, 30))
    ccam = Camera(80, 60, (60, 60, 40, 30))
    depth = np.full((60, 80), 2.0, np.float32)
    c_from_d = np.eye(4)
    c_from_d[0, 3] = 0.05
    reg = register_depth(depth, dcam, ccam, c_from_d)
    valid = reg > 0
    np.testing.assert_allclose(reg[valid], 2.0, atol=1e-6)
    cols = np.flatnonzero(valid[30])
    # depth camera covers x in [-40/70*2, 40/70*2] + 0.05 in the colour frame.
    lo = (-40 / 70 * 2 + 0.05) / 2 * 60 + 40
    hi = (40 / 70 * 2 + 0.05) / 2 * 60 + 40
    assert abs(cols.min() - np.floor(lo)) <= 1 and abs(cols.max() - np.floor(hi)) <= 1
    assert valid[30, int(lo) + 1 : int(hi) - 1].all()  # no cracks inside
