"""How mapping and localization cost grow with the frames: the large synthetic scene at 100, 400 and 1,500
mapping views and 100 / 500 queries, at default settings.

    python -m localization.cli synth --preset large --seed 0 --out DATA      # 5 rooms, 1,500 + 500 frames, 640x480
    python benchmarks/perf/bench_scale.py --root DATA --scene room-s0 --work /tmp/scale
        [--views 100 400 1500] [--queries 100 500] [--loc-views 100]

Each measurement runs in a fresh process (so its peak RSS is its own): ``map_scene`` (method lipmap, preset
fast) on V views spread evenly over the mapping frames (the same rooms, seen more densely), then
``localize_scene`` (the ``eval`` defaults) on N queries spread evenly over the query frames, against the map
of ``--loc-views`` views. Stages come from the pipelines' checkpoints and timings; ``peak_rss_mb`` is the
process's high-water mark at the end of the stage. Writes one JSON line per stage
``{"views", "queries", "stage", "seconds", "peak_rss_mb", "device"}`` to
``benchmarks/results/perf-scale.jsonl`` and the rows with their provenance and the growth ratios to
``benchmarks/results/perf-scale.json``. A rerun reuses the work folder's artifacts: delete it to time again.
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
    rows[-1].update({"n_keyframes": kf.get("n_keyframes"), "n_lines": len(lm), "f@5cm": round(f5, 4)})
    return rows


def worker_loc(args) -> list:
    """Localize ``args.n`` queries against the map of ``args.loc_views`` views; one row per stage."""
    from localization.pipeline import LocalizationConfig, localize_scene

    scene = _scene(args)
    scene = replace(scene, mapping=evenly(scene.mapping, args.loc_views), query=evenly(scene.query, args.n))
    clock = Clock()
    res = localize_scene(scene, args.work / "loc", LocalizationConfig(mapping=args.preset), checkpoint=clock)
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--scene", default="room-s0")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--views", type=int, nargs="*", default=[100, 400, 1500])
    ap.add_argument("--queries", type=int, nargs="*", default=[100, 500])
    ap.add_argument("--loc-views", type=int, default=100)
    ap.add_argument("--preset", default="fast", help="mapping preset (the default is eval's; 'quick' for a smoke run)")
    ap.add_argument("--no-write", action="store_true", help="print only (smoke runs)")
    ap.add_argument("--worker", choices=["map", "loc"], help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        import logging

        logging.getLogger("lipmap").setLevel(logging.WARNING)
        rows = worker_map(args) if args.worker == "map" else worker_loc(args)
        print(json.dumps(rows))
        return
    rows = [r for n in args.views for r in _run_worker(args, "map", n)]
    rows += [r for n in args.queries for r in _run_worker(args, "loc", n)]
    summary = _summary(rows)
    print(json.dumps(summary, indent=1))
    if args.no_write:
        return
    (results.RESULTS / "perf-scale.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    results.write("perf-scale", {"scene": f"{args.root.name}/{args.scene}", "rows": rows, "summary": summary})


if __name__ == "__main__":
    main()
