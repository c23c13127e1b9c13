"""How long ``lipmap-loc map`` takes on one scene: the median of several runs, each a fresh process into an empty
folder, per stage, under each thread environment asked for.

    python benchmarks/perf/bench_mapping.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--runs 3] [--method lipmap] [--preset fast] \
        [--env default --env OMP_WAIT_POLICY=PASSIVE] [--tag TAG]

Each ``--env`` is ``default`` (the caller's environment) or ``KEY=VALUE[,KEY=VALUE]`` set on top of it for the
child processes: torch's OpenMP threads behave very differently with ``OMP_WAIT_POLICY=PASSIVE`` (sleeping
between parallel regions: faster beside another busy process, slower alone), so a mapping time means little
without the environment it ran in. Stage times come from the map's own ``timings``; the load average before each
run is recorded, since a run beside another job is not a measurement of the code. Writes
``benchmarks/results/perf-mapping-<dataset>-<scene>[-TAG].json``.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402

HEADER = ["scene", "method / preset", "environment", "runs", "total s (median, min-max)", "2D lines s", "planes s",
          "extraction s", "peak RSS MB", "load before (1 min)"]


def parse_env(spec: str) -> dict:
    """``default`` -> {}; ``K=V,K2=V2`` -> {K: V, K2: V2}."""
    if spec == "default":
        return {}
    out = {}
    for item in spec.split(","):
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--env {spec!r}: expected 'default' or KEY=VALUE[,KEY=VALUE]")
        out[key] = value
    return out


def map_timings(linemap_h5: Path) -> dict:
    """The ``timings`` a mapping run recorded in its ``linemap.h5``."""
    from lipmap.linemap import LineMap

    return dict(LineMap.load(linemap_h5).metadata.get("timings", {}))


def run_once(args, env: dict, folder: Path) -> dict:
    """One mapping run in a fresh process into the empty ``folder``: its stage times, wall time and peak RSS."""
    shutil.rmtree(folder, ignore_errors=True)
    cmd = [sys.executable, "-m", "localization.cli", "map", "--dataset", args.dataset, "--root", str(args.root),
           "--scene", args.scene, "--out", str(folder), "--method", args.method, "--preset", args.preset]
    load = os.getloadavg()[0]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    err = proc.stderr.read()  # the progress bars; read before waiting, so a full pipe cannot block the child
    _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage: its peak RSS
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"mapping failed ({proc.returncode}): {' '.join(cmd)}\n{err[-3000:]}")
    return {"wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0, "load_before": load,
            **map_timings(folder / "linemap.h5")}


def summary_row(args, env_spec: str, runs: list) -> list:
    def med(key):
        return float(np.median([r.get(key, np.nan) for r in runs]))

    total = [r["total_s"] for r in runs]
    return [args.scene, f"{args.method} `{args.preset}`", f"`{env_spec}`", len(runs),
            f"{med('total_s'):.0f} ({min(total):.0f}-{max(total):.0f})", f"{med('lines2d_s'):.0f}",
            f"{med('optimize_s'):.0f}", f"{med('extract_s'):.0f}", f"{med('peak_rss_mb'):.0f}",
            " / ".join(f"{r['load_before']:.1f}" for r in runs)]


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--method", default="lipmap", choices=["lipmap", "lift"])
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--env", action="append", default=None, help="'default' or KEY=VALUE[,KEY=VALUE] (repeatable)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    envs = args.env or ["default"]
    rows, measured = [], {}
    for spec in envs:
        env = parse_env(spec)
        runs = []
        for i in range(args.runs):
            r = run_once(args, env, args.out / f"run-{len(measured)}-{i}")
            runs.append(r)
            print(f"{spec} run {i + 1}/{args.runs}: {r['total_s']:.0f} s (planes {r.get('optimize_s', float('nan')):.0f} s, "
                  f"load before {r['load_before']:.1f})", flush=True)
        measured[spec] = runs
        rows.append(summary_row(args, spec, runs))
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    name = f"perf-mapping-{args.dataset}-{args.scene}" + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"scene": args.scene, "dataset": args.dataset, "method": args.method, "preset": args.preset,
                         "runs": measured, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
