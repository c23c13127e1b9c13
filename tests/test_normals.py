"""normals_from_depth: known planes, orientation towards the camera, holes and discontinuities."""
from __future__ import annotations

import numpy as np
import pytest

from lipmap.errors import InputError
from lipmap.normals import normals_from_depth
from lipmap.scene import Camera

CAM = Camera(64, 48, (50.0, 50.0, 32.0, 24.0))


def plane_depth(n, d):
    """z-depth of the plane n . X = d seen by CAM."""
    rays = CAM.pixel_rays()
    return (d / (rays @ n)).astype(np.float32)


def test_tilted_plane():
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    depth = plane_depth(n, -2.0)  # n . X = -2 with n towards the camera
    out = normals_from_depth(depth, CAM)
    assert np.allclose(out, n, atol=1e-4)


def test_faces_camera_whatever_the_plane_sign():
    n = np.array([0.0, 0.0, 1.0])
    out = normals_from_depth(plane_depth(n, 2.0), CAM)
    assert np.allclose(out, [0, 0, -1], atol=1e-6)


def test_holes_and_discontinuity():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 32:] = 3.0  # a step: both sides stay fronto-parallel, not smeared across
    depth[10:14, 10:14] = 0  # a hole
    depth[20, 20] = np.nan
    out = normals_from_depth(depth, CAM)
    valid = depth > 0
    valid &= np.isfinite(depth)
    assert np.all(out[~valid] == 0)
    assert np.allclose(out[valid], [0, 0, -1], atol=1e-6)
    assert np.allclose(np.linalg.norm(out[valid], axis=-1), 1, atol=1e-5)


def test_isolated_pixel_has_no_normal():
    depth = np.zeros((48, 64), np.float32)
    depth[5, 5] = 1.0
    assert np.all(normals_from_depth(depth, CAM) == 0)


def test_size_mismatch():
    with pytest.raises(InputError):
        normals_from_depth(np.ones((10, 10)), CAM)
