"""Memory under load: localize many synthetic queries in ONE process and watch the resident memory.

    python benchmarks/perf/bench_memory.py                    # 16 mapping + 1000 queries, 160x120
    python benchmarks/perf/bench_memory.py --quick            # 200 queries (smoke test)
    python benchmarks/perf/bench_memory.py --workdir WORK   # keep the scene and artifacts; a rerun
                                                              # reuses them and redoes only the queries

A synthetic scene (``lipmap.datasets.synthetic``) is generated with few mapping frames and many
query frames, then ``localization.pipeline.localize_scene`` runs once: line map (``lift``), SIFT
point map, query SIFT + retrieval + matching, query lines, then the per-query loop. Inside the loop
the pipeline's checkpoint callback (``checkpoint("query")``, called after each journal write) records
the resident set size. At the first query the peak counter (``VmHWM``) is reset through
``/proc/self/clear_refs``, so ``peak_rss_mb`` is the peak of the localization loop only, not of
the preparation (query SIFT for all images); ``process_peak_rss_mb`` is the peak since the start
(the larger of the preparation's peak, read before the reset, and the loop's).

Printed, one JSON line each: ``{"queries": N, "rss_mb", "peak_rss_mb", ...}`` after query 1, 100
and the last one, then a summary with the slope of the RSS over queries 100..N (MB per 1000
queries, least squares) and the timings. Memory is flat when the slope is ~0 beyond the journal's
own records (about 1 KB per query kept in the results dict).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def hwm_mb() -> float | None:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return None


def reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-query", type=int, default=1000)
    ap.add_argument("--n-mapping", type=int, default=16)
    ap.add_argument("--size", default="160x120", help="image WxH (intrinsics scale with it)")
    ap.add_argument("--points", default="sift-n2048")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=None, help="scene + artifacts here (default: a temp folder)")
    ap.add_argument("--quick", action="store_true", help="200 queries")
    args = ap.parse_args(argv)
    if args.quick:
        args.n_query = 200

    import torch

    torch.set_num_threads(min(2, os.cpu_count() or 1))
    from lipmap import logger
    from lipmap.datasets import load_scene
    from lipmap.datasets.synthetic import SynthConfig, generate_scene
    from localization.config import LocalizationConfig
    from localization.pipeline import localize_scene

    w, h = (int(v) for v in args.size.split("x"))
    f = 0.8203125 * w  # the 7-Scenes field of view (525 / 640)
    # supersample=1: a quarter of the rays of the default; image quality does not matter here
    cfg = SynthConfig(f"mem{args.n_query}", w, h, f, f, w / 2, h / 2, n_mapping=args.n_mapping, n_query=args.n_query,
                      texels_per_m=200.0 * w / 240, supersample=1)
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_memory_")
        args.workdir = Path(tmp.name)
    logger.setLevel("WARNING")
    t0 = time.time()
    scene_dir = generate_scene(args.workdir / "data", seed=args.seed, preset=cfg)
    t_gen = time.time() - t0
    scene = load_scene("synthetic", args.workdir / "data", scene_dir.name)
    conf = LocalizationConfig(points=args.points, map_method="lift", num_retrieved=5, seed=0)
    for old in (args.workdir / "out").glob("queries-*.jsonl"):  # a kept workdir: reuse artifacts, redo every query
        old.unlink()

    samples: list[tuple[int, float]] = []
    marks = {1, 100, args.n_query}
    lines = []
    state = {"t_loop": None}
    def hook(name: str):
        if name == "query":
            n = len(samples) + 1
            if n == 1:
                state["prepare_peak"] = hwm_mb() or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                state["hwm_reset"] = reset_hwm()
                state["t_loop"] = time.time()
            r = rss_mb()
            samples.append((n, r))
            if n in marks:
                loop_peak = hwm_mb() if state["hwm_reset"] else float("nan")
                rec = {"queries": n, "rss_mb": round(r, 1), "peak_rss_mb": round(loop_peak, 1),
                       "process_peak_rss_mb": round(max(state["prepare_peak"], hwm_mb() or 0), 1),
                       "loop_s": round(time.time() - state["t_loop"], 2)}
                lines.append(rec)
                print(json.dumps(rec), flush=True)

    rss_start = rss_mb()
    t1 = time.time()
    res = localize_scene(scene, args.workdir / "out", conf, checkpoint=hook)
    t_total = time.time() - t1
    if len(samples) < args.n_query:
        print(json.dumps({"warning": f"only {len(samples)} queries were localized in this process "
                                     "(a journal from an earlier run was resumed); use a fresh --workdir"}))
    import numpy as np

    tail = np.array([s for s in samples if s[0] >= 100]) if len(samples) >= 200 else np.array(samples)
    slope = float(np.polyfit(tail[:, 0], tail[:, 1], 1)[0]) * 1000 if len(tail) > 2 else float("nan")
    s = res["summary"]
    summary = {
        "summary": True,
        "image_size": [w, h], "n_mapping": args.n_mapping, "n_query": args.n_query,
        "queries_localized_here": len(samples),
        "rss_before_run_mb": round(rss_start, 1),
        "rss_loop_start_mb": round(samples[0][1], 1) if samples else None,
        "rss_growth_100_to_last_mb": round(samples[-1][1] - samples[99][1], 1) if len(samples) >= 100 else None,
        "rss_slope_mb_per_1000_queries": round(slope, 2),
        "hwm_reset": state.get("hwm_reset"),
        "generate_s": round(t_gen, 1), "prepare_s": round((state["t_loop"] or time.time()) - t1, 1),
        "loop_s": round(time.time() - state["t_loop"], 1) if state["t_loop"] else None, "total_s": round(t_total, 1),
        "point_failed": s["point"]["n_failed"], "point_median_t_cm": s["point"]["median_t_cm"],
        "point_line_median_t_cm": s["point+line"]["median_t_cm"],
        "machine": f"{platform.machine()} {os.cpu_count()} cpu, torch threads {torch.get_num_threads()}",
    }
    print(json.dumps(summary), flush=True)
    header = ["queries localized in one process", "resident MB", "peak MB (loop)", "loop s"]
    rows = [[r["queries"], r["rss_mb"], r["peak_rss_mb"], r["loop_s"]] for r in lines]
    rows.append([f"slope: {summary['rss_slope_mb_per_1000_queries']} MB per 1000 queries", "", "", summary["loop_s"]])
    results.write("perf-memory" + ("-quick" if args.quick else ""), {"samples": lines, "summary": summary,
                                                                      "table": {"header": header, "rows": rows}})
    if tmp is not None:
        tmp.cleanup()
    return lines, summary


if __name__ == "__main__":
    main()
