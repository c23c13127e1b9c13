"""Where one GPU training step of the plane renderer spends its time: torch profiler tables (CPU and CUDA).

    python benchmarks/perf/profile_raster.py > benchmarks/results/perf-raster-profile-<gpu>.txt

Planes and camera as ``bench_raster.py`` (the RedKitchen init, grown 2.5x); 3 warm-up steps, then 5 profiled
forward + backward steps at 640x480 x 10,000 and 320x240 x 2,000 planes, lambda 1500. Read: ``cudaLaunchKernel``
calls / 5 = kernel launches per step; ``aten::nonzero`` calls / 5 = host-device synchronizations per step;
``Self CUDA time total`` / 5 = the GPU's own work per step, against the step's wall time in ``perf-raster.json``.
"""
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks" / "perf"))
sys.path.insert(0, str(REPO / "benchmarks"))
import bench_raster as br  # noqa: E402

if not torch.cuda.is_available():
    raise SystemExit("profile_raster.py profiles the CUDA renderer: no CUDA device here")
for res, K in (("640x480", 10000), ("320x240", 2000)):
    step, _ = br.training_step(res, K, "cuda", 1500.0)
    for _ in range(3):
        step()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(5):
            step()
        torch.cuda.synchronize()
    print("=====", res, K)
    print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=25, max_name_column_width=50))
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=12, max_name_column_width=50))
