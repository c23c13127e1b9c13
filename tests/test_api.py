"""The per-query API, through public names only: a map built once, then one query at a time."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lipmap.datasets import load_scene
from lipmap.datasets.synthetic import generate_scene
from lipmap.lines2d import load_lines
from lipmap.mapping.pipeline import map_scene
from localization import LocalizationConfig, Localizer, QueryResult
from localization.hloc_io import read_pairs
from localization.pipeline import run_eval
from localization.points import point_matches_from_hloc

from test_pipeline import CONF, MINI

SCENE = "room-s1"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict:
    """The map built once with map_scene, then the benchmark over it (run_eval with that map)."""
    root = tmp_path_factory.mktemp("data")
    generate_scene(root, seed=1, preset=MINI)
    scene = load_scene("synthetic", root, SCENE)
    linemap = map_scene(scene, tmp_path_factory.mktemp("map"), "fast", "lift")
    out = tmp_path_factory.mktemp("out")
    path = run_eval("synthetic", root, [SCENE], out, CONF, linemap=linemap)
    scene_dir = path.parent / SCENE
    (points,) = scene_dir.glob("points-*")
    (qlines,) = scene_dir.glob("lines2d_query-*.h5")
    return {"scene": scene, "linemap": linemap, "results": json.loads((scene_dir / "results.json").read_text()),
            "points": points, "qlines": qlines, "out": out}


def _matches(run, name):
    pts = run["points"]
    (sfm,) = pts.glob("sfm_*")
    (feats,) = [p for p in pts.glob("feats-*.h5") if "_" not in p.stem]
    (pairs,) = pts.glob("pairs-query-*.txt")
    (matches,) = pts.glob(f"*_{pairs.stem}.h5")
    return point_matches_from_hloc(name, sfm, feats, matches, read_pairs(pairs))


def test_run_eval_uses_the_map_it_is_given(run):
    res = run["results"]
    assert res["map"]["given"] is True
    assert Path(res["map"]["path"]).resolve() == Path(run["linemap"]).resolve()
    assert not list((run["out"] / "synthetic" / SCENE).glob("map-*"))  # nothing mapped twice


def test_localizer_gives_the_benchmark_poses(run):
    loc = Localizer.from_linemap(run["linemap"], CONF)
    for view in run["scene"].query:
        pm = _matches(run, view.name)
        res = loc.localize(view.camera, pm.p2d, pm.p3d, lines2d=load_lines(run["qlines"], view.name), name=view.name)
        assert isinstance(res, QueryResult)
        ref = run["results"]["queries"][view.name]
        for key, pose in (("point", res.point), ("point+line", res.point_line)):
            assert pose.success
            err_t = np.linalg.norm((np.linalg.inv(pose.cam_from_world) - np.linalg.inv(view.cam_from_world))[:3, 3])
            assert abs(100 * err_t - ref[key]["t_cm"]) < 1e-3  # the same call as the benchmark's: the same pose
        assert res.point.n_inliers == ref["point"]["n_inliers"]
        assert len(res.line_matches) == ref["point+line"]["n_line_matches"]
        assert res.line_matches.inliers.sum() == ref["point+line"]["n_line_inliers"]
        assert res.line_matches.lines2d.shape == (len(res.line_matches), 2, 2)
        assert res.line_matches.lines3d.shape == (len(res.line_matches), 2, 3)
        assert res.point_line.inliers.shape == (len(pm),)
        assert set(res.timings) >= {"point", "line_stage", "total"} and res.timings["total"] > 0


def test_localizer_from_an_image_and_with_few_points(run):
    loc = Localizer.from_linemap(run["linemap"], LocalizationConfig(points="sift-n2048", map_method="lift"))
    view = run["scene"].query[0]
    pm = _matches(run, view.name)
    res = loc.localize(view.camera.to_dict(), pm.p2d, pm.p3d, image=view.color_path)
    assert len(res.lines2d) > 10 and res.timings["detect_lines"] > 0
    dt = np.linalg.norm(np.linalg.inv(res.point_line.cam_from_world)[:3, 3] - np.linalg.inv(view.cam_from_world)[:3, 3])
    assert dt < 0.05
    few = loc.localize(view.camera, pm.p2d[:3], pm.p3d[:3], lines2d=res.lines2d)  # a failure is a result
    assert not few.point.success and few.point.cam_from_world is None and few.point.reason
