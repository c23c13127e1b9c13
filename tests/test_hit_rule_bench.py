"""benchmarks/hit_rule.py: the two hit rules agree where centre order and hit order agree, and the script counts
the pixels where a slanted plane crossing a wall makes them differ."""

import numpy as np

from conftest import benchmark_module
from lipmap.datasets import load_scene
from lipmap.datasets.synthetic import SynthConfig, generate_scene
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.primitives import Planes
from lipmap.planes.targets import TargetStore

MINI = SynthConfig("mini", 240, 180, 196.875, 196.875, 120.0, 90.0, n_mapping=2, n_query=1, texels_per_m=200.0)


def _planes_in_view(v, centres, normals, radius):
    """Planes given in ``v``'s camera frame, moved to the world frame."""
    R, t = v.cam_from_world[:3, :3], v.cam_from_world[:3, 3]
    c = (np.asarray(centres, float) - t) @ R
    n = np.asarray(normals, float) @ R
    return Planes.from_normals(c, n, [radius] * len(c))


def test_the_rules_differ_only_where_a_nearer_centre_hides_a_nearer_hit(tmp_path):
    generate_scene(tmp_path / "data", seed=1, preset=MINI)
    scene = load_scene("synthetic", tmp_path / "data", "room-s1")
    bench = benchmark_module("hit_rule.py")
    conf = PlaneOptConfig.preset("paper")
    targets = TargetStore(scene.mapping, conf)
    v = targets[0].view
    a = np.radians(50)
    crossing = _planes_in_view(v, [[0, 0, 2.0], [0, 0, 2.1]], [[np.sin(a), 0, -np.cos(a)], [0, 0, -1.0]], 0.5)
    stacked = _planes_in_view(v, [[0, 0, 2.0], [0, 0, 2.1]], [[0, 0, -1.0], [0, 0, -1.0]], 0.5)
    r = bench.compare(crossing, conf, targets, [0], 1500.0)
    # right of x = 0.084 m the slanted plane lies behind the wall: about a third of the slanted plane's pixels
    assert r["rendered_pixels"] > 1000
    assert 0.1 < r["first_plane_differs"] < 0.6 and r["depth_over_1cm"] > 0.05
    assert r["plane_loss_nearest"] != r["plane_loss_reference"]
    s = bench.compare(stacked, conf, targets, [0], 1500.0)
    assert s["rendered_pixels"] > 1000 and s["first_plane_differs"] == 0 and s["depth_over_1cm"] == 0
    assert s["plane_loss_nearest"] == s["plane_loss_reference"]
