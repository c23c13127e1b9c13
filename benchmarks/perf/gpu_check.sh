#!/usr/bin/env bash
# The GPU checks of issue #16, as one prepared script for a machine with CUDA (run from the repository root,
# after `make install TORCH="torch==2.13.0" PIP_EXTRA="--extra-index-url https://download.pytorch.org/whl/cu126"`):
#   1. the renderer at 640x480 x 10,000 planes (target: <= 5 ms per forward + backward),
#   2. bench_scale at 1,500 mapping views of the large synthetic scene (generated here with all cores),
#   3. the mapping of the RedKitchen mini (fast preset) and its map-eval.
# Each step's output goes to $OUT (default outputs/gpu); the figures land in benchmarks/results/.
set -euo pipefail
OUT=${OUT:-outputs/gpu}
PY=${PY:-.venv/bin/python}
mkdir -p "$OUT"
$PY -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; print(torch.cuda.get_device_name(0))"
$PY benchmarks/perf/bench_raster.py --devices cuda 2>&1 | tee "$OUT/raster.log"
$PY -m localization.cli synth --preset large --seed 0 --out "$OUT/data" --workers "$(nproc)" 2>&1 | tail -2
$PY benchmarks/perf/bench_scale.py --root "$OUT/data" --scene room-s0 --work "$OUT/scale" --views 100 1500 --queries 100 500 \
    2>&1 | tee "$OUT/scale.log"
$PY -m localization.cli map --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini --scene redkitchen \
    --out "$OUT/redkitchen" --method lipmap --preset fast 2>&1 | tail -3
$PY -m localization.cli map-eval --linemap "$OUT/redkitchen/linemap.h5" --dataset 7scenes \
    --root ../shared/data/7scenes-redkitchen-mini --scene redkitchen 2>&1 | tail -8
