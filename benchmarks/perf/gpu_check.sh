#!/usr/bin/env bash
# The fused plane renderer's GPU checks, as one prepared script of at most ~5 minutes for a machine with CUDA (run
# from the repository root after `make install TORCH="torch==2.13.0" PIP_EXTRA="--extra-index-url
# https://download.pytorch.org/whl/cu126"`; warp-lang is a dependency):
#   1. the renderer tests on CUDA (the fused kernels against the torch twin; one step under
#      torch.cuda.set_sync_debug_mode, at most one sync; the first-hit kernel and the line term on the device, a whole
#      training step with the line term under set_sync_debug_mode; the kernels under a side torch.cuda.Stream);
#   2. per training step of each renderer (the torch one it replaced, read from git; today's torch; Warp): kernel
#      launches (profiler), host syncs (set_sync_debug_mode("warn")), ms (median of 20 by CUDA events), at
#      640x480 x 10,000 and 320x240 x 2,000 planes, lambda 1500 and 300;
#   3. mapping the RedKitchen mini with `fast`, and with `fast --full-resolution`, each under MAP_TIMEOUT seconds.
# Every figure goes to $OUT/summary.txt with the card that gave it; step 2 also writes
# benchmarks/results/perf-raster-profile-cuda.json. CHECK_DEVICE=cpu runs steps 1-2 on the CPU (ops instead of
# launches, 320x240 only) and skips the mapping unless MAP=1: a dry run of the script on a machine without a GPU.
set -euo pipefail
OUT=${OUT:-outputs/gpu}
PY=${PY:-.venv/bin/python}
DEVICE=${CHECK_DEVICE:-cuda}
MAP_TIMEOUT=${MAP_TIMEOUT:-100}
DATA=${DATA:-../shared/data/7scenes-redkitchen-mini}
export LIPMAP_REQUIRE_WARP=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
# a GPU machine may get a copy of a working tree with uncommitted changes: keep its figures, marked as such
export LIPMAP_BENCH_ALLOW_DIRTY=${LIPMAP_BENCH_ALLOW_DIRTY:-1}
mkdir -p "$OUT"
SUMMARY="$OUT/summary.txt"
CARD=$($PY - "$DEVICE" <<'EOF'
import sys, torch
if sys.argv[1] == "cuda":
    assert torch.cuda.is_available(), "no CUDA device (CHECK_DEVICE=cpu for a dry run)"
    print(torch.cuda.get_device_name(0), "| torch", torch.__version__, "| CUDA", torch.version.cuda)
else:
    print("cpu | torch", torch.__version__)
EOF
)
COMMIT=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
echo "card: $CARD | commit $COMMIT | $(date -u '+%F %H:%M UTC')" | tee "$SUMMARY"

echo "== 1. renderer tests on $DEVICE" | tee -a "$SUMMARY"
t0=$SECONDS
$PY -m pytest tests/test_raster_fused.py tests/test_planes_render.py tests/test_raycast_fused.py \
    tests/test_line_term_device.py tests/test_warp_stream.py -q -p no:cacheprovider 2>&1 | tail -3 \
    | tee -a "$SUMMARY"
echo "tests: $((SECONDS - t0)) s (includes compiling the Warp kernels for $DEVICE) [$CARD]" | tee -a "$SUMMARY"

echo "== 2. launches, syncs and ms per training step" | tee -a "$SUMMARY"
QUICK=""
[ "$DEVICE" = cpu ] && QUICK="--quick"
$PY benchmarks/perf/profile_raster.py --device "$DEVICE" $QUICK 2>&1 | grep '^{' | tee -a "$SUMMARY"

if [ "$DEVICE" = cuda ] || [ "${MAP:-0}" = 1 ]; then
    echo "== 3. mapping the RedKitchen mini (MAP_TIMEOUT=$MAP_TIMEOUT s each)" | tee -a "$SUMMARY"
    for variant in fast full-resolution; do
        extra=""
        [ "$variant" = full-resolution ] && extra="--full-resolution"
        rm -rf "$OUT/map-$variant"
        t0=$SECONDS
        if timeout "$MAP_TIMEOUT" $PY -m localization.cli map --dataset 7scenes --root "$DATA" --scene redkitchen \
            --out "$OUT/map-$variant" --method lipmap --preset fast $extra > "$OUT/map-$variant.log" 2>&1; then
            status="done"
        else
            status="stopped at the time limit or failed (see $OUT/map-$variant.log)"
        fi
        echo "map fast ${extra:-(coarse to fine)}: $((SECONDS - t0)) s wall, $status [$CARD]" | tee -a "$SUMMARY"
        if [ -f "$OUT/map-$variant/linemap.h5" ]; then
            $PY - "$OUT/map-$variant/linemap.h5" <<'EOF' | tee -a "$SUMMARY"
import sys
from lipmap.linemap import LineMap
m = LineMap.load(sys.argv[1])
t = m.metadata.get("timings", {})
print(f"  lines {len(m.lines)}, stage seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in t.items() if k.endswith("_s")))
EOF
            $PY -m localization.cli map-eval --linemap "$OUT/map-$variant/linemap.h5" --dataset 7scenes --root "$DATA" \
                --scene redkitchen 2>&1 | tail -4 | tee -a "$SUMMARY"
        fi
    done
fi
echo "summary: $SUMMARY"
