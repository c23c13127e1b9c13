"""How mapping and localization cost grow with the frames: the large synthetic scene at 100, 400 and 1,500
mapping views and 100 / 500 queries, at default settings.

    python -m localization.cli synth --preset large --seed 0 --out DATA      # 5 rooms, 1,500 + 500 frames, 640x480
    python benchmarks/perf/bench_scale.py --root DATA --scene room-s0 --work WORK
        [--views 100 400 1500] [--queries 100 500] [--loc-views 100] [--tag TAG]

Each measurement runs in a fresh process (so its peak RSS is its own): ``map_scene`` (method lipmap, preset
fast) on V views spread evenly over the mapping frames (the same rooms, seen more densely), then
``localize_scene`` (the ``eval`` defaults) on N queries spread evenly over the query frames, against the map
of ``--loc-views`` views. Stages come from the pipelines' checkpoints and timings; ``peak_rss_mb`` is the
process's high-water mark at the end of the stage. Writes one JSON line per stage
``{"views", "queries", "stage", "seconds", "peak_rss_mb", "device"}`` to
``benchmarks/results/perf-scale.jsonl`` and the rows with their provenance and the growth ratios to
``benchmarks/results/perf-scale.json``. A rerun reuses the work folder's artifacts: delete it to time again.
``--estimate-from benchmarks/results/perf-scale.jsonl`` only redoes the full-size estimate from those measured
rows, with the keyframe rate of today's keyframe rule (``--root``/``--work`` are then unused); with several files,
a later file's rows replace an earlier one's of the same views, queries and stage (a tagged partial rerun).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def device() -> str:
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def evenly(views: list, n: int) -> list:
    """``n`` views spread evenly over ``views`` (all of them when n >= len)."""
    if n >= len(views):
        return list(views)
    return [views[i] for i in np.unique(np.linspace(0, len(views) - 1, n).round().astype(int))]


class Clock:
    """The pipelines' checkpoint: time and peak RSS at each event."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.events = []

    def __call__(self, event: str):
        self.events.append((event, time.perf_counter() - self.t0, peak_rss_mb()))

    def at(self, event: str, last: bool = False):
        hits = [e for e in self.events if e[0] == event]
        return (hits[-1] if last else hits[0]) if hits else None


def _scene(args):
    from lipmap.datasets import load_scene

    return load_scene("synthetic", args.root, args.scene)


def worker_map(args) -> list:
    """Map ``args.n`` views; one row per stage."""
    from lipmap.evaluation import evaluate_linemap, load_ground_truth, scene_ground_truth
    from lipmap.linemap import LineMap
    from lipmap.mapping.pipeline import map_scene
    from lipmap.planes.io import load_planes_meta

    scene = _scene(args)
    scene = replace(scene, mapping=evenly(scene.mapping, args.n))
    out = args.work / f"map-{args.n}"
    clock = Clock()
    path = map_scene(scene, out, args.preset, "lipmap", checkpoint=clock)
    lm = LineMap.load(path)
    if not clock.events:
        raise SystemExit(f"{out} holds a finished map: delete it to time the mapping again")
    hist = load_planes_meta(out / "planes.h5").get("history", {})
    t_lines, t_planes, t_map = (clock.at(e) for e in ("lines2d", "planes", "linemap"))
    init = float(hist.get("init_seconds", 0.0))
    stages = [("lines2d", t_lines[1], t_lines[2]), ("plane_init_tsdf", init, t_planes[2]),
              ("plane_optimization", t_planes[1] - t_lines[1] - init, t_planes[2]),
              ("extraction_tracks_renders", t_map[1] - t_planes[1], t_map[2]), ("mapping_total", t_map[1], t_map[2])]
    gt = load_ground_truth(scene_ground_truth(scene))
    f5 = evaluate_linemap(lm, gt)["M1"]["line"]["f@0.05"]
    kf = lm.metadata.get("keyframes", {})
    rows = [{"views": args.n, "queries": 0, "stage": s, "seconds": round(sec, 2), "peak_rss_mb": round(rss, 1),
             "device": device()} for s, sec, rss in stages]
    rows[-1].update({"n_keyframes": kf.get("n_keyframes"), "n_lines": len(lm), "f@5cm": round(f5, 4),
                     "n_planes": lm.metadata.get("n_planes"), "max_planes": max(hist.get("planes") or [0]),
                     "prune_split_rounds": len(hist.get("planes") or []), "splits": int(sum(hist.get("split") or []))})
    return rows


def worker_loc(args) -> list:
    """Localize ``args.n`` queries against the map of ``args.loc_views`` views; one row per stage."""
    from localization.config import LocalizationConfig
    from localization.pipeline import localize_scene

    import shutil

    from lipmap.mapping.pipeline import map_variant_dir

    scene = _scene(args)
    scene = replace(scene, mapping=evenly(scene.mapping, args.loc_views), query=evenly(scene.query, args.n))
    conf = LocalizationConfig(mapping=args.preset)
    # the map of these views was timed by the mapping run: the localization run starts from a copy (same stamp)
    made, variant = args.work / f"map-{args.loc_views}", map_variant_dir(args.work / "loc", scene, args.preset, conf.map_method)
    if (made / "linemap.h5").exists() and not variant.exists():
        shutil.copytree(made, variant)
    clock = Clock()
    res = localize_scene(scene, args.work / "loc", conf, checkpoint=clock)
    queries = [e for e in clock.events if e[0] == "query"]
    if len(queries) < 2:
        raise SystemExit(f"{args.work / 'loc'} holds a finished journal for these queries: delete it to time again")
    # the per-query loop: first to last journal entry, scaled by N / (N - 1) for the first query's own time
    loop = (queries[-1][1] - queries[0][1]) * len(queries) / (len(queries) - 1)
    t = res["timings"]
    mapped = clock.at("mapped")
    stages = [("map_reused" if mapped[1] < 5 else "map", mapped[1], mapped[2]),
              ("point_map", t.get("point_map_s", 0.0), queries[0][2]),
              ("query_points", t.get("query_points_s", 0.0), queries[0][2]),
              ("localize_loop", loop, queries[-1][2])]
    per_query = (t.get("query_points_s", 0.0) + loop) / args.n
    rows = [{"views": args.loc_views, "queries": args.n, "stage": s, "seconds": round(sec, 2),
             "peak_rss_mb": round(rss, 1), "device": device()} for s, sec, rss in stages]
    rows.append({"views": args.loc_views, "queries": args.n, "stage": "per_query", "seconds": round(per_query, 4),
                 "peak_rss_mb": round(queries[-1][2], 1), "device": device(),
                 "median_t_cm_point_line": res["summary"]["point+line"].get("median_t_cm")})
    return rows


def _run_worker(args, kind: str, n: int) -> list:
    cmd = [sys.executable, __file__, "--root", str(args.root), "--scene", args.scene, "--work", str(args.work),
           "--loc-views", str(args.loc_views), "--preset", args.preset, "--worker", kind, "--n", str(n)]
    print("$", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"worker {kind} {n} failed ({proc.returncode})")
    rows = json.loads(proc.stdout.strip().splitlines()[-1])
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


def _summary(rows: list) -> dict:
    total = {r["views"]: r for r in rows if r["stage"] == "mapping_total"}
    per_q = {r["queries"]: r for r in rows if r["stage"] == "per_query"}
    out = {}
    if len(total) >= 2:
        lo, hi = min(total), max(total)
        out["mapping"] = {"views": [lo, hi], "time_ratio": round(total[hi]["seconds"] / total[lo]["seconds"], 3),
                          "peak_rss_ratio": round(total[hi]["peak_rss_mb"] / total[lo]["peak_rss_mb"], 3),
                          "peak_rss_mb_max": max(r["peak_rss_mb"] for r in total.values())}
    if len(per_q) >= 2:
        lo, hi = min(per_q), max(per_q)
        out["localization"] = {"queries": [lo, hi], "per_query_ratio": round(per_q[hi]["seconds"] / per_q[lo]["seconds"], 3)}
    return out


# 7-Scenes frames per scene (mapping = TrainSplit sequences, queries = TestSplit), 1,000 per sequence
SEVEN_SCENES = {"chess": (4000, 2000), "fire": (2000, 2000), "heads": (1000, 1000), "office": (6000, 4000),
                "pumpkin": (4000, 2000), "redkitchen": (7000, 5000), "stairs": (2000, 1000)}
FULL_RATE_STEP = 10  # the RedKitchen mini keeps every 10th frame of the 30 Hz sequence


def keyframe_rate(root) -> float:
    """Keyframes per frame of a 30 Hz 7-Scenes sequence with the default settings: the RedKitchen mini's poses
    (every 10th frame) interpolated back to every frame (linear centres, slerped rotations)."""
    from scipy.spatial.transform import Rotation, Slerp

    from lipmap.datasets import load_scene
    from lipmap.mapping.keyframes import select_keyframes
    from lipmap.poses import invert_T, make_T

    views = load_scene("7scenes", root, "redkitchen").mapping
    T_wc = np.stack([invert_T(v.cam_from_world) for v in views])
    t_in = np.arange(len(views)) * FULL_RATE_STEP
    t_out = np.arange(t_in[-1] + 1)
    rot = Slerp(t_in, Rotation.from_matrix(T_wc[:, :3, :3]))(t_out).as_matrix()
    ctr = np.stack([np.interp(t_out, t_in, T_wc[:, i, 3]) for i in range(3)], 1)
    dense = [replace(views[0], name=f"seq-01/frame-{i:06d}.color.png", cam_from_world=invert_T(make_T(rot[i], ctr[i])))
             for i in range(len(t_out))]
    return len(select_keyframes(dense)) / len(dense)


def measured_rows(paths: list) -> list:
    """The rows of ``perf-scale*.jsonl`` files; a later file's row replaces an earlier one's of the same views,
    queries and stage."""
    rows = {}
    for path in paths:
        for line in Path(path).read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                rows[(r["views"], r["queries"], r["stage"])] = r
    return list(rows.values())


def estimate(rows: list, kf_rate: float) -> dict:
    """The full 7-Scenes reproduction on this machine, from the measured stages: line mapping as a fixed part plus
    a part per keyframe (least squares over the mapping runs), the point map per mapping image, and the query side
    per query (both from the localization runs)."""
    total = sorted((r["n_keyframes"], r["seconds"]) for r in rows if r["stage"] == "mapping_total")
    if len(total) < 2:
        return {}
    k, sec = np.array(total, dtype=float).T
    per_kf, fixed = np.polyfit(k, sec, 1)
    loc = [r for r in rows if r["queries"]]
    point_map = next(r for r in loc if r["stage"] == "point_map")
    per_map_image = point_map["seconds"] / point_map["views"]
    per_query = max(r["seconds"] for r in loc if r["stage"] == "per_query")
    scenes = {}
    for name, (n_map, n_query) in SEVEN_SCENES.items():
        kf = kf_rate * n_map
        scenes[name] = {"keyframes": round(kf), "line_map_h": (fixed + per_kf * kf) / 3600,
                        "point_map_h": per_map_image * n_map / 3600, "queries_h": per_query * n_query / 3600}
    tot = {key: sum(s[key] for s in scenes.values()) for key in ("line_map_h", "point_map_h", "queries_h")}
    return {"keyframes_per_frame": round(kf_rate, 4), "line_map_fixed_s": round(fixed, 1),
            "line_map_per_keyframe_s": round(per_kf, 3), "point_map_per_image_s": round(per_map_image, 3),
            "per_query_s": round(per_query, 3), "scenes": scenes, "total_h": {k: round(v, 2) for k, v in tot.items()},
            "all_h": round(sum(tot.values()), 2)}


def _tables(rows: list, est: dict) -> tuple:
    header = ["views", "queries", "stage", "seconds", "peak RSS (MB)", "keyframes", "lines", "F@5cm"]
    rounds = any("prune_split_rounds" in r for r in rows)
    if rounds:
        header += ["planes (most during the run)", "prune/split rounds", "splits"]

    def row(r):
        out = [r["views"], r["queries"] or "", r["stage"], r["seconds"], r["peak_rss_mb"], r.get("n_keyframes", ""),
               r.get("n_lines", ""), r.get("f@5cm", "")]
        if rounds:
            planes = f"{r['n_planes']} ({r['max_planes']})" if r.get("n_planes") is not None else ""
            out += [planes, r.get("prune_split_rounds", ""), r.get("splits", "")]
        return out

    table = {"header": header, "rows": [row(r) for r in rows]}
    if not est:
        return table, None
    eh = ["scene", "mapping frames", "keyframes", "line map (h)", "point map (h)", "queries (h)"]
    erows = [[n, SEVEN_SCENES[n][0], s["keyframes"], f"{s['line_map_h']:.2f}", f"{s['point_map_h']:.2f}",
              f"{s['queries_h']:.2f}"] for n, s in est["scenes"].items()]
    t = est["total_h"]
    erows.append(["**all 7 scenes**", sum(v[0] for v in SEVEN_SCENES.values()), sum(s["keyframes"] for s in est["scenes"].values()),
                  f"{t['line_map_h']:.1f}", f"{t['point_map_h']:.1f}", f"{t['queries_h']:.1f} (total {est['all_h']:.1f} h)"])
    return table, {"header": eh, "rows": erows}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path)
    ap.add_argument("--scene", default="room-s0")
    ap.add_argument("--work", type=Path)
    ap.add_argument("--views", type=int, nargs="*", default=[100, 400, 1500])
    ap.add_argument("--queries", type=int, nargs="*", default=[100, 500])
    ap.add_argument("--loc-views", type=int, default=100)
    ap.add_argument("--preset", default="fast", help="mapping preset (the default is eval's; 'quick' for a smoke run)")
    ap.add_argument("--no-write", action="store_true", help="print only (smoke runs)")
    ap.add_argument("--tag", default="", help="write perf-scale-TAG.json(l) instead, without the full-size estimate: "
                                              "a partial rerun (say --views 1500 --queries) beside the full table")
    ap.add_argument("--sevenscenes-root", type=Path, default=REPO.parent / "shared/data/7scenes-redkitchen-mini",
                    help="the RedKitchen mini, whose poses give the keyframe rate of the full-size estimate")
    ap.add_argument("--estimate-from", type=Path, nargs="+", default=None, metavar="JSONL",
                    help="only redo the full-size estimate from measured rows (perf-scale.jsonl) with today's keyframe rule")
    ap.add_argument("--worker", choices=["map", "loc"], help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if not args.estimate_from and (args.root is None or args.work is None):
        ap.error("--root and --work are required (unless --estimate-from)")
    if args.worker:
        import logging

        logging.getLogger("lipmap").setLevel(logging.WARNING)
        rows = worker_map(args) if args.worker == "map" else worker_loc(args)
        print(json.dumps(rows))
        return
    if args.estimate_from:
        rows = measured_rows(args.estimate_from)
        est = estimate(rows, keyframe_rate(args.sevenscenes_root))
        print(json.dumps(est, indent=1))
        if not args.no_write:
            results.write("perf-scale-estimate", {"estimate": est, "table": _tables(rows, est)[1],
                                                  "measured_rows": [str(p) for p in args.estimate_from]})
        return
    rows = [r for n in args.views for r in _run_worker(args, "map", n)]
    rows += [r for n in args.queries for r in _run_worker(args, "loc", n)]
    summary = _summary(rows)
    est = estimate(rows, keyframe_rate(args.sevenscenes_root)) if args.sevenscenes_root.exists() and not args.tag else {}
    table, est_table = _tables(rows, est)
    print(json.dumps({**summary, "estimate": est}, indent=1))
    if args.no_write:
        return
    name = f"perf-scale-{args.tag}" if args.tag else "perf-scale"
    (results.RESULTS / f"{name}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    results.write(name, {"scene": f"{args.root.name}/{args.scene}", "rows": rows, "summary": summary, "table": table})
    if est_table:
        results.write("perf-scale-estimate", {"estimate": est, "table": est_table})


if __name__ == "__main__":
    main()
