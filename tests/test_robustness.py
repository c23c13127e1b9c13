"""Bad input, interruption and recovery on the MINI synthetic scene of test_pipeline.

Each bad input is checked where a user meets it: through ``python -m localization.cli`` (exit code 2,
one line ``lipmap-loc: error: <file>: <problem>`` on stderr, no traceback) when it stops the run, or
in results.json when it only costs one query. docs/bad-inputs.md lists the messages.
"""
import json
import logging
import os
import re
import shutil
import subprocess
import sys
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from lipmap import InputError, logger
from lipmap.artifacts import read_stamp
from lipmap.datasets import load_scene
from lipmap.datasets.synthetic import generate_scene
from lipmap.datasets.validate import check_scene
from lipmap.linemap import LineMap
from lipmap.lines2d import detect_lines_image, load_lines
from localization.linequery import LineQueryConfig
from localization.config import LineRescueConfig
from localization.pipeline import run_eval

from test_pipeline import CONF, MINI, _numbers

REPO = Path(__file__).resolve().parents[1]
SCENE = "room-s1"
NOT_RIGID = "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"


def Q(i: int) -> str:
    return f"seq-02/frame-{i:06d}.color.png"


@pytest.fixture(scope="module")
def mini_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("mini")
    generate_scene(root, seed=1, preset=MINI)
    return root


@pytest.fixture(scope="module")
def ref(mini_root, tmp_path_factory) -> dict:
    """An uninterrupted run on the intact scene: its output folder and its results."""
    out = tmp_path_factory.mktemp("ref")
    path = run_eval("synthetic", mini_root, [SCENE], out, CONF)
    return {"out": out, "all": json.loads(path.read_text()),
            "scene": json.loads((path.parent / SCENE / "results.json").read_text())}


def _copy_data(mini_root, tmp_path) -> Path:
    shutil.copytree(mini_root, tmp_path / "data")
    return tmp_path / "data"


def _copy_out(ref, tmp_path) -> Path:
    """The reference run's artifacts (line map, SIFT, SfM model, query lines) without its journal."""
    out = tmp_path / "out"
    shutil.copytree(ref["out"], out, ignore=shutil.ignore_patterns("queries-*.jsonl", "results*"))
    return out


def _scene_results(out: Path) -> dict:
    return json.loads((out / "synthetic" / SCENE / "results.json").read_text())


def _errors_of(q: dict) -> tuple:
    return q["t_cm"], q["R_deg"]


@contextmanager
def lipmap_log(caplog):
    """The lipmap logger does not propagate to the root logger; hand its records to caplog."""
    logger.addHandler(caplog.handler)
    try:
        with caplog.at_level(logging.WARNING, logger="lipmap"):
            yield caplog
    finally:
        logger.removeHandler(caplog.handler)


# ----------------------------------------------------------------------------------------------
# bad mapping input: the run stops with one line naming the file (CLI)
# ----------------------------------------------------------------------------------------------
def _cli(args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "localization.cli", *args], capture_output=True, text=True,
                          cwd=REPO, env={**os.environ, **(env or {})}, timeout=timeout)


def _one_line_error(p) -> str:
    assert p.returncode == 2, p.stderr[-3000:]
    assert "Traceback" not in p.stderr
    errors = [line for line in p.stderr.splitlines() if line.startswith("lipmap-loc: error: ")]
    assert len(errors) == 1 and p.stderr.rstrip().endswith(errors[0]), p.stderr[-3000:]
    return errors[0]


def _truncate(path: Path):
    b = path.read_bytes()
    path.write_bytes(b[: len(b) // 2])


def _truncated_jpeg(frame: Path):
    png = frame / "frame-000003.color.png"
    jpg = frame / "frame-000003.color.jpg"
    cv2.imwrite(str(jpg), cv2.imread(str(png)))
    png.unlink()
    _truncate(jpg)


def _write(rel: str, content):
    def mutate(scene: Path):
        p = scene / rel
        if isinstance(content, np.ndarray):
            cv2.imwrite(str(p), content)
        elif content is None:
            p.unlink()
        else:
            p.write_text(content)

    return mutate


FRAME = "seq-01/frame-000003"
BAD_FRAME = f"bad mapping frame {FRAME}.color.png: "
SKIP = r" \(use --skip-bad-frames to skip it\)$"
MAPPING_CASES = {
    # name: (change to the scene folder, file named in the message, problem (regex))
    "truncated-png": (lambda s: _truncate(s / f"{FRAME}.color.png"), f"{FRAME}.color.png",
                      BAD_FRAME + "{path}: image cannot be decoded \\(corrupt or not an image\\)" + SKIP),
    "truncated-jpeg": (lambda s: _truncated_jpeg(s / "seq-01"), f"{FRAME}.color.jpg",
                       BAD_FRAME + "{path}: image is truncated \\(JPEG ends before its end-of-image marker\\)" + SKIP),
    "missing-colour": (_write(f"{FRAME}.color.png", None), f"{FRAME}.color.png",
                       "{path}: colour image is missing \\(frame has a pose file; looked for .color.png and .color.jpg\\)$"),
    "missing-depth": (_write(f"{FRAME}.depth.png", None), f"{FRAME}.depth.png",
                      BAD_FRAME + "{path}: depth map is missing \\(mapping needs depth\\)" + SKIP),
    "nan-pose": (_write(f"{FRAME}.pose.txt", "nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"), f"{FRAME}.pose.txt",
                 "{path}: pose contains NaN or infinite values$"),
    "inf-pose": (_write(f"{FRAME}.pose.txt", "1 0 0 inf\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"), f"{FRAME}.pose.txt",
                 "{path}: pose contains NaN or infinite values$"),
    "non-rigid-pose": (_write(f"{FRAME}.pose.txt", NOT_RIGID), f"{FRAME}.pose.txt",
                       "{path}: pose is not rigid: rotation block deviates from orthonormal by 3 \\(det 2\\)$"),
    "depth-wrong-size": (_write(f"{FRAME}.depth.png", np.full((90, 120), 1000, np.uint16)), f"{FRAME}.depth.png",
                         BAD_FRAME + "{path}: depth map has size 120x90, expected 240x180" + SKIP),
    "depth-8-bit": (_write(f"{FRAME}.depth.png", np.full((180, 240), 100, np.uint8)), f"{FRAME}.depth.png",
                    BAD_FRAME + "{path}: depth map must be 16-bit \\(uint16 millimetres\\), got uint8" + SKIP),
    "depth-all-invalid": (_write(f"{FRAME}.depth.png", np.zeros((180, 240), np.uint16)), f"{FRAME}.depth.png",
                          BAD_FRAME + "{path}: depth map has no valid pixel \\(all 0 or 65535\\)" + SKIP),
    "depth-all-65535": (_write(f"{FRAME}.depth.png", np.full((180, 240), 65535, np.uint16)), f"{FRAME}.depth.png",
                        BAD_FRAME + "{path}: depth map has no valid pixel \\(all 0 or 65535\\)" + SKIP),
    "duplicate-names-across-splits": (_write("TestSplit.txt", "sequence2\nsequence1\n"), "TestSplit.txt",
                                      "{path}: sequence1 is in both TrainSplit.txt and TestSplit.txt "
                                      "\\(mapping and query frames would have the same names\\)$"),
    "duplicate-names-in-split": (_write("TrainSplit.txt", "sequence1\nsequence1\n"), "TrainSplit.txt",
                                 "{path}: line 2: sequence1 is listed twice \\(its frames would have duplicate names\\)$"),
}


@pytest.mark.parametrize("case", list(MAPPING_CASES))
def test_cli_bad_mapping_input_stops_with_one_line(mini_root, tmp_path, case):
    mutate, rel, problem = MAPPING_CASES[case]
    root = _copy_data(mini_root, tmp_path)
    mutate(root / SCENE)
    p = _cli(["eval", "--dataset", "synthetic", "--root", str(root), "--scenes", SCENE, "--method", "lift",
              "--points", "sift-n2048", "--out", str(tmp_path / "out")])
    msg = _one_line_error(p)
    path = re.escape(str(root / SCENE / rel))
    assert re.fullmatch("lipmap-loc: error: " + problem.format(path=path), msg), msg
    assert not list((tmp_path / "out" / "synthetic" / SCENE).glob("map-*/linemap.h5"))  # found before any work


def test_skip_bad_frames_skips_each_with_a_warning(mini_root, tmp_path, caplog):
    root = _copy_data(mini_root, tmp_path)
    seq = root / SCENE / "seq-01"
    (seq / "frame-000003.pose.txt").write_text(NOT_RIGID)
    (seq / "frame-000009.color.png").unlink()
    cv2.imwrite(str(seq / "frame-000005.depth.png"), np.zeros((180, 240), np.uint16))
    cv2.imwrite(str(seq / "frame-000007.depth.png"), np.full((90, 120), 1000, np.uint16))
    with pytest.raises(InputError, match="frame-000003.pose.txt: pose is not rigid"):
        load_scene("synthetic", root, SCENE)
    with lipmap_log(caplog):
        scene = load_scene("synthetic", root, SCENE, skip_bad_frames=True)  # the reader drops pose / image problems
        scene, bad_queries = check_scene(scene, skip_bad_frames=True)  # the check drops depth problems
    assert len(scene.mapping) == 12 and len(scene.query) == 6 and not bad_queries
    kept = {v.name for v in scene.mapping}
    assert not kept & {f"seq-01/frame-{i:06d}.color.png" for i in (3, 5, 7, 9)}
    skipped = scene.meta["skipped_frames"]
    for frag in ("frame-000003.pose.txt: pose is not rigid", "frame-000009.color.png: colour image is missing",
                 "frame-000005.depth.png: depth map has no valid pixel", "frame-000007.depth.png: depth map has size 120x90"):
        assert sum(frag in s for s in skipped) == 1, (frag, skipped)
        assert any(frag in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records), frag


# ----------------------------------------------------------------------------------------------
# bad queries: reported as failed (or skipped for invalid ground truth); the others are kept
# ----------------------------------------------------------------------------------------------
def test_bad_queries_fail_alone(mini_root, ref, tmp_path):
    root = _copy_data(mini_root, tmp_path)
    seq = root / SCENE / "seq-02"
    # a uniform image: no lines, no SIFT features, so fewer than 4 point matches
    cv2.imwrite(str(seq / "frame-000001.color.png"), np.full((180, 240, 3), 128, np.uint8))
    (seq / "frame-000003.color.png").unlink()  # a missing query image
    (seq / "frame-000004.pose.txt").write_text(NOT_RIGID)  # invalid ground truth
    out = tmp_path / "out"
    run_eval("synthetic", root, [SCENE], out, CONF)
    res = _scene_results(out)
    assert res["errors"] == {Q(3): f"{seq / 'frame-000003.color.png'}: image file is missing"}
    assert set(res["skipped_invalid_gt"]) == {Q(4)}
    assert re.fullmatch(r".*frame-000004\.pose\.txt: pose is not rigid: .*", res["skipped_invalid_gt"][Q(4)])
    uniform = res["queries"][Q(1)]
    assert uniform["point"]["success"] is False and uniform["point"]["reason"] == "0 matches < 4"
    assert uniform["point+line"]["reason"] == "no point-only pose, and the line rescue found none"
    (qlines,) = (out / "synthetic" / SCENE).glob("lines2d_query-*.h5")
    assert load_lines(qlines, Q(1)).shape == (0, 4)
    s = res["summary"]["point"]
    assert s["n_queries"] == 5 and s["n_failed"] == 2
    for i in (0, 2, 5):  # untouched queries: the very numbers of the intact run
        for key in ("point", "point+line"):
            assert _errors_of(res["queries"][Q(i)][key]) == _errors_of(ref["scene"]["queries"][Q(i)][key])


def test_uniform_image_has_no_lines():
    lines, scores = detect_lines_image(np.full((180, 240), 128, np.uint8))
    assert lines.shape == (0, 4) and len(scores) == 0


def test_query_without_lines_keeps_its_point_pose(mini_root, ref, tmp_path):
    out = _copy_out(ref, tmp_path)
    (qlines,) = (out / "synthetic" / SCENE).glob("lines2d_query-*.h5")
    with h5py.File(qlines, "a") as f:
        g = f[Q(0)]
        for k in ("lines", "scores"):
            del g[k]
        g.create_dataset("lines", data=np.zeros((0, 4), np.float32))
        g.create_dataset("scores", data=np.zeros(0, np.float32))
    run_eval("synthetic", mini_root, [SCENE], out, CONF)
    q = _scene_results(out)["queries"]
    assert q[Q(0)]["point+line"]["success"] and not q[Q(0)]["point+line"]["used_lines"]
    assert q[Q(0)]["point+line"]["n_query_lines"] == 0 and q[Q(0)]["point+line"]["n_line_matches"] == 0
    assert _errors_of(q[Q(0)]["point+line"]) == _errors_of(q[Q(0)]["point"]) == _errors_of(ref["scene"]["queries"][Q(0)]["point"])
    for i in range(1, 6):
        assert _errors_of(q[Q(i)]["point+line"]) == _errors_of(ref["scene"]["queries"][Q(i)]["point+line"])


def test_empty_line_map_falls_back_to_point_poses(mini_root, ref, tmp_path, caplog):
    out = _copy_out(ref, tmp_path)
    (path,) = (out / "synthetic" / SCENE).glob("map-*/linemap.h5")
    LineMap(np.zeros((0, 2, 3)), metadata={"method": "lift"}).save(path, stamp=read_stamp(path))  # same settings, no lines
    with lipmap_log(caplog):
        run_eval("synthetic", mini_root, [SCENE], out, CONF)
    assert any("linemap.h5: the line map has no lines; point+line poses will be the point-only poses" in r.getMessage()
               for r in caplog.records)
    res = _scene_results(out)
    assert res["n_map_lines"] == 0 and not res["errors"]
    for name, q in res["queries"].items():
        assert q["point+line"]["success"] and not q["point+line"]["used_lines"], name
        assert _errors_of(q["point+line"]) == _errors_of(q["point"]) == _errors_of(ref["scene"]["queries"][name]["point"])
    s = res["summary"]
    assert {k: v for k, v in s["point+line"].items() if k in s["point"] and "ms" not in k} == \
        {k: v for k, v in s["point"].items() if "ms" not in k}


def test_fewer_than_4_point_matches_fail_every_query_cleanly(mini_root, ref, tmp_path):
    out = _copy_out(ref, tmp_path)
    run_eval("synthetic", mini_root, [SCENE], out, replace(CONF, max_point_matches=3,
                                                           line_rescue=LineRescueConfig(weak_inliers=0)))
    res = _scene_results(out)
    assert res["summary"]["point"]["n_failed"] == res["summary"]["point+line"]["n_failed"] == 6
    for q in res["queries"].values():
        assert q["point"]["n_matches"] == 3 and q["point"]["reason"] == "3 matches < 4"


def test_lines_rescue_queries_with_3_point_matches(mini_root, ref, tmp_path):
    """With the rescue (the default), the P3P poses of the one triple are verified by the map's lines."""
    out = _copy_out(ref, tmp_path)
    run_eval("synthetic", mini_root, [SCENE], out, replace(CONF, max_point_matches=3))
    res = _scene_results(out)
    assert res["summary"]["point"]["n_failed"] == 6
    assert res["summary"]["point+line"]["n_failed"] <= 1
    t = []
    for q in res["queries"].values():
        assert q["point"]["reason"] == "3 matches < 4"
        pl = q["point+line"]
        if pl["success"]:
            assert pl["rescued"] and pl["t_cm"] < 10.0
            t.append(pl["t_cm"])
        else:
            assert pl["reason"]
    # (measured: 0.5-4.8 cm, median 2.6 cm; with the narrowing rounds refining the rescued pose, 1.1-6.0 cm)
    assert sum(x < 5.0 for x in t) >= 5 and np.median(t) < 4.0


def test_raycast_query_on_a_map_without_planes_stops_once(mini_root, ref, tmp_path):
    out = _copy_out(ref, tmp_path)
    with pytest.raises(InputError, match=r"linemap\.h5: the raycast line query needs a line map with planes; "
                                         r"this one was made by 'lift' and has none \(use --line-query projection"):
        run_eval("synthetic", mini_root, [SCENE], out,
                 replace(CONF, line_query=LineQueryConfig(method="raycast")))


# ----------------------------------------------------------------------------------------------
# hloc inputs
# ----------------------------------------------------------------------------------------------
def test_bad_hloc_files_fail_their_queries_only(mini_root, ref, tmp_path):
    (src,) = (ref["out"] / "synthetic" / SCENE).glob("points-*")
    hloc = tmp_path / "hloc" / SCENE
    hloc.mkdir(parents=True)
    shutil.copytree(next(src.glob("sfm_*")), hloc / "sfm")
    shutil.copy(src / "feats-sift-n2048.h5", hloc / "features.h5")
    shutil.copy(next(src.glob("*_pairs-query-*.h5")), hloc / "matches.h5")
    pairs = hloc / "pairs-query.txt"
    text = next(src.glob("pairs-query-*.txt")).read_text()
    text = text.replace(f"{Q(4)} seq-01/", f"{Q(4)} seq-01/frame-000099.color.png\n{Q(4)} seq-01/", 1)
    pairs.write_text(text)
    with h5py.File(hloc / "features.h5", "a") as f:
        del f[Q(1)]  # the pairs file names an image missing from features.h5
        del f[Q(2)]["keypoints"]
        kp = f[Q(3)]["keypoints"][()]
        del f[Q(3)]["keypoints"]
        f[Q(3)].create_dataset("keypoints", data=np.full(kp.shape, b"x", dtype="S1"))
    out = _copy_out(ref, tmp_path)
    shutil.rmtree(next((out / "synthetic" / SCENE).glob("points-*")))
    run_eval("synthetic", mini_root, [SCENE], out, CONF, hloc_dir=tmp_path / "hloc")
    res = _scene_results(out)
    feats = hloc / "features.h5"
    assert res["errors"] == {
        Q(1): f"{feats}: query {Q(1)!r} (from pairs {pairs}) has no group {Q(1)!r} in the features file",
        Q(2): f"{feats}: image {Q(2)!r}: missing dataset 'keypoints'",
        Q(3): f"{feats}: {Q(3)}/keypoints must have a numeric dtype, got |S1",
        Q(4): f"{pairs}: image 'seq-01/frame-000099.color.png' (paired with {Q(4)!r}) is not in the SfM model {hloc / 'sfm'}",
    }
    for i in (0, 5):  # same files as the built-in run: the same numbers
        for key in ("point", "point+line"):
            assert _errors_of(res["queries"][Q(i)][key]) == _errors_of(ref["scene"]["queries"][Q(i)][key])


def test_pairs_naming_images_missing_from_features(ref, tmp_path):
    from localization.points import match_features

    (src,) = (ref["out"] / "synthetic" / SCENE).glob("points-*")
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{Q(0)} seq-01/frame-000000.color.png\n{Q(0)} seq-01/frame-000099.color.png\n")
    with pytest.raises(InputError) as e:
        match_features(pairs, src / "feats-sift-n2048.h5", tmp_path / "matches.h5")
    assert str(e.value) == (f"{pairs}: pair 2 ({Q(0)} seq-01/frame-000099.color.png): image "
                            f"'seq-01/frame-000099.color.png' has no group in the features file {src / 'feats-sift-n2048.h5'}")
    assert not (tmp_path / "matches.h5").exists()


# ----------------------------------------------------------------------------------------------
# interruption during mapping
# ----------------------------------------------------------------------------------------------
def test_sigkill_during_mapping_then_resume_gives_same_results(mini_root, ref, tmp_path):
    out = tmp_path / "run"
    script = ("import sys; sys.path.insert(0, 'tests'); from test_pipeline import CONF; from lipmap.testing import kill_at; "
              "from localization.pipeline import run_eval; "
              "run_eval('synthetic', sys.argv[1], ['room-s1'], sys.argv[2], CONF, checkpoint=kill_at('mapped'))")
    killed = subprocess.run([sys.executable, "-c", script, str(mini_root), str(out)], capture_output=True, text=True,
                            cwd=REPO, timeout=300)
    assert killed.returncode == -9, killed.stderr[-2000:]  # SIGKILL right after linemap.h5 was written
    scene_dir = out / "synthetic" / SCENE
    (linemap,) = scene_dir.glob("map-*/linemap.h5")
    assert not list(scene_dir.glob("points-*")) and not (scene_dir / "results.json").exists()
    assert not list(scene_dir.rglob(".*.tmp*"))  # atomic writes leave no half-written files behind
    mtime = linemap.stat().st_mtime_ns
    path = run_eval("synthetic", mini_root, [SCENE], out, CONF)
    assert linemap.stat().st_mtime_ns == mtime  # resumed from the line map, not rebuilt
    assert _numbers(json.loads(path.read_text())) == _numbers(ref["all"])
