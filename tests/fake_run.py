"""A tiny finished ``lipmap-loc eval`` run on disk (results, journal, line map, images), for the report tests."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import h5py
import numpy as np

from lipmap.linemap import LineMap
from lipmap.poses import invert_T, make_T
from lipmap.testing import rect
from localization.config import LocalizationConfig
from localization.report_run import KEYS

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


def make_fake_run(tmp_path: Path) -> dict:
    """A 7-Scenes-layout dataset root (scene chess: 1 mapping + 2 query images) and an eval OUT tree
    with chess (complete) and room-x (results only, not in the dataset root nor the paper).

    chess's map is a ``lipmap`` map of 4 lines: two plane edges (the planes' edge -> line table says so)
    and two on-plane lines, with 2 planes.

    Returns:
        ``{"root", "out", "est"}``: dataset root, eval OUT, the journal's estimated poses.
    """
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
    edge_line = np.array([[0, 1, -1, -1], [-1, -1, -1, -1]])
    LineMap(lines, tracks, planes={"corners": corners, "edge_line": edge_line},
            metadata={"method": "lipmap"}).save(chess / "linemap.h5")
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
                       "n_line_inliers": 7, "n_line_matches": 9} for k in KEYS} for q in (Q0, Q1)}
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
