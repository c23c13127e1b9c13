"""The held-out-viewpoint split of the RedKitchen mini (benchmarks/7scenes/make_heldout_split.py)."""

import numpy as np

from lipmap.datasets import load_scene

from conftest import benchmark_module


def _module():
    return benchmark_module("7scenes/make_heldout_split.py")


def test_heldout_split_maps_the_first_stretch_and_queries_the_second(redkitchen_root, tmp_path):
    dst = _module().make_split(redkitchen_root, tmp_path)
    assert dst.name == "redkitchen-heldout"
    for source in ("posetxt", "sfm"):
        scene = load_scene("7scenes", tmp_path, dst.name, pose_source=source)
        frames = lambda views: sorted(int(v.name.split("-")[-1].split(".")[0]) for v in views)  # noqa: E731
        assert frames(scene.mapping) == list(range(0, 250, 5)) and frames(scene.query) == list(range(250, 500, 5))
    # queries are far from every mapping view: tens of cm (the mini's own queries are ~3.5 cm from one)
    centres = np.array([v.center for v in scene.mapping])
    d = [np.linalg.norm(centres - q.center, axis=1).min() for q in scene.query]
    assert np.median(d) > 0.1
