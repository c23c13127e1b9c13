"""benchmarks/edge_depth.py: a plane edge on the surface and one floating in front of it, told apart by the sensor
depth of the views that track them."""

import numpy as np
import pytest

from conftest import benchmark_module
from lipmap import geometry as geo
from lipmap.datasets import load_scene
from lipmap.datasets.synthetic import SynthConfig, generate_scene
from lipmap.linemap import LineMap
from lipmap.planes.io import save_planes
from lipmap.planes.primitives import Planes

MINI = SynthConfig("mini", 240, 180, 196.875, 196.875, 120.0, 90.0, n_mapping=4, n_query=1, texels_per_m=200.0)


def _bench():
    return benchmark_module("edge_depth.py")


def test_a_floating_plane_edge_is_found_with_its_plane_in_front_of_the_surface(tmp_path):
    generate_scene(tmp_path / "data", seed=1, preset=MINI)
    scene = load_scene("synthetic", tmp_path / "data", "room-s1")
    v = scene.mapping[0]
    depth = v.load_depth()
    H, W = depth.shape
    z = float(depth[H // 2, W // 2])
    assert z > 1.0
    R, t = v.cam_from_world[:3, :3], v.cam_from_world[:3, 3]
    centre_cam = np.array([(W / 2 + 0.5 - v.camera.cx) / v.camera.fx, (H / 2 + 0.5 - v.camera.cy) / v.camera.fy, 1.0])
    to_world = lambda p: (p - t) @ R  # noqa: E731
    facing = -(R.T @ np.array([0.0, 0.0, 1.0]))  # towards the camera
    # two 6 x 6 cm planes on the ray through the image centre: on the surface, and half way to it
    planes = Planes.from_normals([to_world(centre_cam * z), to_world(centre_cam * z / 2)], [facing, facing], [0.03, 0.015])
    corners = planes.corners().numpy().astype(float)
    lines = np.stack([corners[0, :2], corners[1, :2]])  # each plane's first edge
    tracks = []
    for line in lines:
        seg, _ = geo.project_segments(line[None], v.cam_from_world, v.camera)
        tracks.append([(v.name, 0, seg.reshape(4))])
    edge_line = np.full((2, 4), -1)
    edge_line[0, 0], edge_line[1, 0] = 0, 1
    p = planes.numpy()
    lm = LineMap(lines, tracks, planes={"center": p["center"], "quaternion": p["quat"], "radii": p["radii"],
                                        "corners": corners, "edge_line": edge_line},
                 metadata={"n_edge_lines": 2, "keyframes": {"min_translation": 0.0, "min_rotation_deg": 0.0}})
    lm.save(tmp_path / "map" / "linemap.h5")
    save_planes(tmp_path / "map" / "planes.h5", planes)

    bench = _bench()
    a = bench.analyse(scene, tmp_path / "map")
    assert (a["n_edges"], a["near"], a["floating"]) == (2, 1, 1)
    assert a["_res"][0] < 0.01 and a["_res"][1] == pytest.approx(z / 2, abs=0.05)
    # the floating edge's plane is half the depth in front of the surface, half the depth from the camera
    assert a["floating_stats"]["interior_off_m"] == pytest.approx(-z / 2, abs=0.05)
    assert a["floating_stats"]["distance_m"] == pytest.approx(z / 2, abs=0.02)
    assert a["near_stats"]["distance_m"] == pytest.approx(z, abs=0.02)
    png = bench.picture(a, tmp_path / "p.png")
    assert png.exists()
