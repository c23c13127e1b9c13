"""ms per iteration of the joint line-plane optimization (render, plane loss, line term, backward, Adam), by part.

    python benchmarks/perf/bench_training_step.py --out OUT [--iterations 200] [--backends warp,torch]

The RedKitchen mini (``../shared/data/7scenes-redkitchen-mini``) with the ``fast`` mapping preset: its keyframes,
its LSD lines (detected into OUT), its initial planes. Each backend (``LIPMAP_RENDER_BACKEND``, which picks the
renderer and the line term's first-hit caster) runs in a fresh process: ``--warmup`` iterations at the working
resolution (the planes grow from their small initial radii, kernels load), then ``--iterations`` timed ones there
(320x240) and as many at the camera's resolution (640x480, the preset's fine phase), from the warmed planes. Parts
come from cProfile over the timed iterations (cumulative seconds per iteration; the profiler's own overhead is in
the total too, so compare rows with each other). The total column is timed without the profiler. Syncs: the
operations of one iteration that would wait for a GPU (counted on the CPU, as ``tests/test_raster_fused.py`` does;
on a CPU the line term compacts its rows, one of them, which it does not on a GPU), and all the torch operations
it dispatches (Warp's launches not included). ``--tag`` names the run in the
table's first column: run on a checkout of an older commit (with this script copied in), it gives the "before" rows.

Writes ``benchmarks/results/perf-training-step-redkitchen[-TAG].json``.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tests"))
import results  # noqa: E402

DATA = (REPO / ".." / "shared" / "data" / "7scenes-redkitchen-mini").resolve()
HEADER = ["run", "renderer", "resolution", "ms per iteration", "render (forward)", "line term", "of it: first hits",
          "backward + Adam", "plane loss", "syncs per iteration", "torch operations per iteration"]
# (column, the file and function whose cumulative time it is)
PARTS = [("render (forward)", ("train.py", "render_target")), ("line term", ("supervision.py", "__call__")),
         ("of it: first hits", ("supervision.py", "_first_hits")), ("backward + Adam", ("optimizer.py", "_apply_step")),
         ("plane loss", ("losses.py", "plane_loss"))]


def measure(args) -> list[dict]:
    """In this process: the rows of one backend."""
    import torch

    from lipmap.datasets import load_scene
    from lipmap.mapping.joint import _plane_settings, line_supervision
    from lipmap.mapping.keyframes import keyframe_views
    from lipmap.mapping.pipeline import _lines_by_view, detect_or_import_lines, get_conf
    from lipmap.planes import train
    from lipmap.planes.init import init_planes
    from lipmap.planes.optimizer import _make_optimizer
    from lipmap.planes.targets import TargetStore
    from lipmap.planes.train import optimize_planes
    from test_raster_fused import CountDispatch

    torch.set_num_threads(args.threads)
    scene = load_scene("7scenes", args.root, "redkitchen")
    conf = get_conf("fast")
    scene = replace(scene, mapping=keyframe_views(scene.mapping, conf.keyframes))
    lines_h5 = detect_or_import_lines(scene.mapping, args.out, conf, None, False)
    lbv = _lines_by_view(lines_h5, scene.mapping)
    pconf, _ = _plane_settings(conf)
    pconf = replace(pconf, fine_iterations=0, progress=False, split=False)
    sup = line_supervision(lbv, conf)
    planes = init_planes(scene.mapping, pconf.init)
    coarse = TargetStore(scene.mapping, pconf)
    planes, _ = optimize_planes(coarse, planes, replace(pconf, iterations=args.warmup), extra_loss=sup)
    fine_conf = replace(pconf, target_width=10 ** 6)  # downscale 1: the camera's resolution
    rows = []
    for label, conf_i, targets in (("320x240", pconf, coarse), ("640x480", fine_conf, TargetStore(scene.mapping, fine_conf))):
        run = replace(conf_i, iterations=args.iterations)
        optimize_planes(targets, planes, replace(conf_i, iterations=len(targets)), extra_loss=sup)  # targets cached
        t = time.perf_counter()
        optimize_planes(targets, planes, run, extra_loss=sup)
        total = (time.perf_counter() - t) / args.iterations
        prof = cProfile.Profile()
        prof.enable()
        optimize_planes(targets, planes, run, extra_loss=sup)
        prof.disable()
        stats = pstats.Stats(prof).stats
        cum = {}
        for (file, _, fn), (_, _, _, ct, _) in stats.items():
            if "lipmap" in file:
                key = (Path(file).name, fn)
                cum[key] = cum.get(key, 0.0) + ct
        # one iteration's syncs
        params = [p.clone(memory_format=torch.contiguous_format).requires_grad_() for p in planes.tensors()]
        sched = train.Schedule.of(run, len(targets))
        opt = _make_optimizer(params, run)
        st = train._EpochStats.zeros(len(params[0]), params[0].device)
        train._train_view(params, opt, targets[0], 0, sched, sup, st)
        with CountDispatch() as n:
            train._train_view(params, opt, targets[1], 1, sched, sup, st)
        row = {"run": args.tag or "this commit", "renderer": os.environ.get("LIPMAP_RENDER_BACKEND", "auto"),
               "resolution": label,
               "ms per iteration": round(1000 * total, 1), "syncs per iteration": n.syncs,
               "torch operations per iteration": n.ops}
        for col, key in PARTS:
            row[col] = round(1000 * cum.get(key, 0.0) / args.iterations, 1)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, required=True, help="where the 2D lines are detected")
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--backends", default="warp,torch")
    ap.add_argument("--tag", default="")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.child:
        measure(args)
        return
    results.require_clean()
    rows = []
    for backend in args.backends.split(","):
        cmd = [sys.executable, __file__, "--child", "--root", str(args.root), "--out", str(args.out),
               "--iterations", str(args.iterations), "--warmup", str(args.warmup), "--threads", str(args.threads),
               "--tag", args.tag]
        out = subprocess.run(cmd, env={**os.environ, "LIPMAP_RENDER_BACKEND": backend}, capture_output=True, text=True)
        if out.returncode:
            raise SystemExit(f"{backend}: {out.stderr[-3000:]}")
        rows += [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    name = "perf-training-step-redkitchen" + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"threads": args.threads, "iterations": args.iterations, "warmup": args.warmup,
                         "table": {"header": HEADER, "rows": [[r[h] for h in HEADER] for r in rows]}})


if __name__ == "__main__":
    main()
