"""One training step of each plane renderer, counted and timed: kernel launches, host syncs, ms per step.

    python benchmarks/perf/profile_raster.py --device cuda            # the GPU check (gpu_check.sh runs it)
    python benchmarks/perf/profile_raster.py --device cpu --quick     # the same on CPU (ops instead of launches)

Planes and camera as ``bench_raster.py`` (the RedKitchen init grown 2.5x, or the box room), at 640x480 x 10,000 and
320x240 x 2,000 planes (``--quick``: the latter only), lambda 1500 and 300, each renderer of ``--backends``
(``baseline`` is the torch renderer the fused one replaced, read from git; see ``bench_raster.py``). Per
configuration, after 3 warm-up steps:

- launches per step: CUDA, kernel launches in the torch profiler's trace (``cudaLaunchKernel`` and the driver's
  ``cuLaunchKernel``, which Warp uses) over 5 steps / 5; CPU, torch operations dispatched (a
  ``TorchDispatchMode``), Warp's launches not included;
- syncs per step: CUDA, the warnings of ``torch.cuda.set_sync_debug_mode("warn")`` over one step (every
  synchronizing call warns); CPU, the operations that would wait for a device (``nonzero``, ``.item()``, boolean
  indexing, ...);
- ms per step: the median of ``--repeat`` (20) steps, by CUDA events on CUDA, ``perf_counter`` on CPU.

Prints one JSON line per configuration, each with the device's name, and writes
``benchmarks/results/perf-raster-profile-<device>[-TAG].json`` (the card is in its provenance).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks" / "perf"))
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tests"))
import bench_raster as br  # noqa: E402
import results  # noqa: E402

_LAUNCHES = {"cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx"}


def count_cuda(step) -> tuple[float, int]:
    """(kernel launches per step over 5 profiled steps, synchronizing calls in one step)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            step()
        torch.cuda.synchronize()
    launches = sum(e.count for e in prof.key_averages() if e.key in _LAUNCHES) / 5
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            step()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    syncs = sum("synchroniz" in str(w.message) for w in caught)
    return launches, syncs


def count_cpu(step) -> tuple[int, int]:
    """(torch operations dispatched, of which host syncs on a device) in one step."""
    from test_raster_fused import CountDispatch

    with CountDispatch() as n:
        step()
    return n.ops, n.syncs


def time_steps(step, device: str, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        if device == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            step()
            b.record()
            torch.cuda.synchronize()
            out.append(a.elapsed_time(b))
        else:
            t = time.perf_counter()
            step()
            out.append(1000 * (time.perf_counter() - t))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--backends", default="baseline,torch,warp")
    ap.add_argument("--baseline-rev", default=br.BASELINE_REV)
    ap.add_argument("--quick", action="store_true", help="320x240 x 2,000 planes only")
    ap.add_argument("--box", action="store_true", help="the random box room even where the real data is")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2, help="torch threads on CPU")
    ap.add_argument("--tag", default=None)
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("profile_raster.py --device cuda: no CUDA device here")
    torch.set_num_threads(args.threads)
    name = torch.cuda.get_device_name(0) if args.device == "cuda" else f"cpu, {args.threads} threads"
    configs = [("320x240", 2000)] if args.quick else [("640x480", 10000), ("320x240", 2000)]
    records = []
    for res, K in configs:
        for lam in (1500.0, 300.0):
            for backend in args.backends.split(","):
                step, source = br.training_step(res, K, args.device, lam, box=args.box, backend=backend,
                                                baseline_rev=args.baseline_rev)
                for _ in range(3):
                    step()
                if args.device == "cuda":
                    torch.cuda.synchronize()
                    launches, syncs = count_cuda(step)
                else:
                    launches, syncs = count_cpu(step)
                ms = time_steps(step, args.device, args.repeat)
                rec = {"resolution": res, "planes": K, "lambda": lam, "renderer": backend, "device": name,
                       "launches_per_step": launches, "syncs_per_step": syncs,
                       "ms_per_step_median": round(statistics.median(ms), 2), "ms_min": round(min(ms), 2),
                       "steps": len(ms), "source": source}
                print(json.dumps(rec), flush=True)
                records.append(rec)
    what = "kernel launches" if args.device == "cuda" else "torch ops"
    header = ["resolution", "planes", "lambda", "renderer", "device", f"{what} per step", "host syncs per step",
              f"ms per step (median of {args.repeat})"]
    rows = [[r["resolution"], r["planes"], f"{r['lambda']:g}", r["renderer"], r["device"], r["launches_per_step"],
             r["syncs_per_step"], r["ms_per_step_median"]] for r in records]
    tag = f"-{args.tag}" if args.tag else ""
    results.write(f"perf-raster-profile-{args.device}{tag}",
                  {"records": records, "table": {"header": header, "rows": rows}})


if __name__ == "__main__":
    main()
