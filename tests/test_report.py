"""localization.report: a report made from a tiny fake run (results, journal, line map, images)."""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from lipmap.linemap import LineMap
from lipmap.poses import invert_T, make_T
from lipmap.testing import rect
from localization import report as rp
from localization.pipeline import LocalizationConfig

W, H, F = 96, 72, 70.0
Q0, Q1 = "seq-02/frame-000000.color.png", "seq-02/frame-000001.color.png"


def _write_frame(seq_dir: Path, i: int, cam_from_world: np.ndarray, value: int):
    seq_dir.mkdir(parents=True, exist_ok=True)
    img = np.full((H, W, 3), value, np.uint8)
    img[H // 3 : 2 * H // 3, W // 3 : 2 * W // 3] = 255 - value  # something to see
    cv2.imwrite(str(seq_dir / f"frame-{i:06d}.color.png"), img)
    np.savetxt(seq_dir / f"frame-{i:06d}.pose.txt", invert_T(cam_from_world))


def _summary(acc_pt, acc_pl, n=2):
    def s(acc, t):
        return {"median_t_cm": t, "median_R_deg": 0.5, "acc_5cm_5deg": acc, "n_queries": n, "n_failed": 0}

    return {"point": s(acc_pt, 4.0), "point+line": s(acc_pl, 2.0)}


@pytest.fixture()
def fake_run(tmp_path):
    """A 7-Scenes-layout dataset root (scene chess: 1 mapping + 2 query images) and an eval OUT tree
    with chess (complete) and room-x (results only, not in the dataset root nor the paper)."""
    root, out = tmp_path / "data", tmp_path / "out"
    sd = root / "chess"
    sd.mkdir(parents=True)
    (sd / "TrainSplit.txt").write_text("sequence1\n")
    (sd / "TestSplit.txt").write_text("sequence2\n")
    (sd / "scene.json").write_text(json.dumps({"intrinsics": [F, F, W / 2, H / 2], "width": W, "height": H,
                                               "depth_registered": True}))
    gt = {Q0: make_T(np.eye(3), [0.0, 0.0, 0.0]), Q1: make_T(np.eye(3), [0.1, 0.0, 0.0])}
    _write_frame(sd / "seq-01", 0, make_T(np.eye(3), [0.05, 0.0, 0.0]), 90)
    _write_frame(sd / "seq-02", 0, gt[Q0], 110)
    _write_frame(sd / "seq-02", 1, gt[Q1], 130)

    ds = out / "7scenes"
    chess = ds / "chess"
    chess.mkdir(parents=True)
    panel = rect([0, 0, 3.0], 1.0, 0.75)
    lines = np.stack([panel, np.roll(panel, -1, axis=0)], 1)
    corners = np.stack([panel, rect([0, 0, 5.0], 4.0, 3.0)])
    tracks = [[("seq-01/frame-000000.color.png", i, np.zeros(4))] for i in range(4)]
    LineMap(lines, tracks, planes={"corners": corners}, metadata={"method": "lipmap"}).save(chess / "linemap.h5")
    with h5py.File(chess / "lines2d_query.h5", "w") as f:
        for q in (Q0, Q1):
            f.create_group(q).create_dataset("lines", data=np.array([[10, 10, 60, 10]], np.float32))
    conf = LocalizationConfig()
    config = json.loads(json.dumps(asdict(conf), default=str))
    # q0: lines help (5 cm -> 0.5 cm); q1: lines hurt (3 cm -> 4 cm)
    est = {Q0: {"point": gt[Q0] @ make_T(np.eye(3), [0.05, 0, 0]), "point+line": gt[Q0] @ make_T(np.eye(3), [0.005, 0, 0])},
           Q1: {"point": gt[Q1] @ make_T(np.eye(3), [0.03, 0, 0]), "point+line": gt[Q1] @ make_T(np.eye(3), [0.04, 0, 0])}}
    errs = {Q0: {"point": 5.0, "point+line": 0.5}, Q1: {"point": 3.0, "point+line": 4.0}}
    with open(chess / f"queries-{conf.digest()}.jsonl", "w") as f:
        for q in (Q0, Q1):
            f.write(json.dumps({"name": q, **{k: {"success": True, "cam_from_world": est[q][k].tolist()} for k in est[q]}}) + "\n")
    (chess / "queries-0000000000.jsonl").write_text(json.dumps({"name": Q0, "point": {"success": False}}) + "\n")
    queries = {q: {k: {"t_cm": errs[q][k], "R_deg": 0.1, "success": True, "n_inliers": 50, "n_matches": 60,
                       "n_line_inliers": 7, "n_line_matches": 9} for k in rp.KEYS} for q in (Q0, Q1)}
    res = {"scene": "chess", "dataset": "7scenes", "pose_source": "posetxt", "n_map_lines": 4, "config": config,
           "journal": f"queries-{conf.digest()}.jsonl", "map": {"path": "linemap.h5", "method": "lipmap"},
           "summary": _summary(50.0, 100.0), "queries": queries, "errors": {}}
    (chess / "results.json").write_text(json.dumps(res))
    roomx = ds / "room-x"
    roomx.mkdir()
    (roomx / "results.json").write_text(json.dumps({"scene": "room-x", "config": config, "summary": _summary(30.0, 40.0),
                                                    "queries": {Q0: {"point": {"t_cm": None, "R_deg": None},
                                                                     "point+line": {"t_cm": 2.0, "R_deg": 0.3}}}}))
    (ds / "results.json").write_text(json.dumps({"dataset": "7scenes", "pose_source": "posetxt",
                                                 "scenes": {"chess": _summary(50.0, 100.0), "room-x": _summary(30.0, 40.0)}}))
    (ds / "summary.md").write_text("# Localization summary (7scenes)\n\n| table |\n")
    return {"root": root, "out": out, "est": est}


def test_journal_named_in_results(fake_run):
    run = rp.load_scene_run(fake_run["out"] / "7scenes" / "chess")
    assert run.journal.name == f"queries-{LocalizationConfig().digest()}.jsonl"
    np.testing.assert_allclose(run.poses[Q0]["point+line"], fake_run["est"][Q0]["point+line"])
    assert rp.select_examples(run, 3) == [("improved", 1, Q0), ("worst", 1, Q1)]


def test_write_report(fake_run):
    out, root = fake_run["out"], fake_run["root"]
    path = rp.write_report(out, "7scenes", root=root)
    rep = out / "7scenes" / "report"
    assert path == rep / "report.md"
    expected = ["accuracy_5cm5deg.png", "cdf_chess.png", "cdf_room-x.png", "query_chess_improved1.png",
                "query_chess_worst1.png", "linemap_chess.png", "planes_chess.png"]
    for name in expected:
        img = cv2.imread(str(rep / name))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 400, name
    text = path.read_text()
    for section in ("# Localization report (7scenes)", "## Accuracy at 5 cm / 5°", "## Error distributions",
                    "### chess", "### room-x", "## Query examples", "## Line maps", "## Notes"):
        assert section in text, section
    for name in expected:
        assert f"]({name})" in text, name
    assert f"| largest improvement #1 | `{Q0}` | 5.0 cm / 0.10° | 0.5 cm / 0.10° | 7 |" in text
    assert "Not in the paper's table (no paper bars): room-x." in text
    assert "room-x: cannot load the scene" in text  # no images for it: said, not silently dropped
    # summary.md gets one plots block, refreshed (not duplicated) by a second run
    rp._refresh_summary_links(out / "7scenes" / "summary.md", rep, rep / "accuracy_5cm5deg.png",
                              {"chess": rep / "cdf_chess.png"})
    summary = (out / "7scenes" / "summary.md").read_text()
    assert summary.startswith("# Localization summary (7scenes)\n\n| table |")
    assert summary.count(rp.BEGIN) == 1 and summary.count(rp.END) == 1
    assert "](report/accuracy_5cm5deg.png)" in summary and "](report/cdf_chess.png)" in summary


def test_report_without_dataset_root_and_cli(fake_run):
    out = fake_run["out"]
    ap = argparse.ArgumentParser()
    rp.add_report_parser(ap.add_subparsers(dest="command"))
    args = ap.parse_args(["report", str(out)])  # dataset detected, no root
    path = args.func(args)
    text = path.read_text()
    assert "chess: dataset root unknown (pass `--root`)" in text
    rep = path.parent
    assert (rep / "linemap_chess.png").exists()  # the overview needs no images
    assert not list(rep.glob("query_*.png"))
    with pytest.raises(rp.InputError):
        rp.write_report(out / "nothing-here", None)
