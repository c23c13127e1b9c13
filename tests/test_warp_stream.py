"""The Warp kernels queue on torch's current CUDA stream: run under a side stream (``torch.cuda.stream(s)``), the fused
raster and the first-hit kernel read their inputs only once torch has written them on that stream, and give what
they give on the default stream. CUDA only (a CPU has no streams); benchmarks/perf/gpu_check.sh runs it."""
from __future__ import annotations

import pytest
import torch

from lipmap.mapping.assign import first_hit
from lipmap.planes import rasterize_planes
from lipmap.planes import raster_warp
from test_raster_fused import INTR, H, W, random_planes
from test_raycast_fused import random_planes as random_rects
from test_raycast_fused import rays

needs_cuda_warp = pytest.mark.skipif(
    not torch.cuda.is_available() or raster_warp.unsupported(torch.device("cuda"), torch.float32, 5) is not None,
    reason="CUDA and warp-lang needed")

# ~0.1 s of GPU spinning queued on the side stream before the inputs are written: a kernel launched on any other
# stream would run first and read memory torch has not filled yet
_SPIN_CYCLES = 200_000_000


def _render_and_grads(tensors):
    P = [t.clone().requires_grad_() for t in tensors]
    out = rasterize_planes(*P, torch.eye(4, device=P[0].device), INTR, W, H, 300.0, backend="warp")
    grads = torch.autograd.grad((out.depth * out.depth).sum() + out.normal.abs().sum() + out.alpha.sum(), P)
    return out, grads


@needs_cuda_warp
def test_the_fused_raster_runs_on_a_side_stream():
    planes = [t.cuda() for t in random_planes(200, seed=4).tensors()]
    want, want_g = _render_and_grads(planes)
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        torch.cuda._sleep(_SPIN_CYCLES)
        late = [t * 1.0 for t in planes]  # written on the side stream after the spin
        got, got_g = _render_and_grads(late)
        got = [got.depth.detach(), got.normal.detach(), got.alpha.detach(), got.hits]
    torch.cuda.synchronize()
    assert want.n_pairs > 0
    for a, b in zip(got, [want.depth.detach(), want.normal.detach(), want.alpha.detach(), want.hits]):
        assert torch.equal(a, b)  # one program per pixel: the same inputs give the same bits
    for a, b in zip(got_g, want_g):
        # the reverse pass sums per-plane gradients with atomics, in whatever order the threads arrive
        assert b.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max()))


@needs_cuda_warp
def test_the_first_hit_kernel_runs_on_a_side_stream():
    corners = random_rects(40, 0).corners().cuda()
    o, d = (x.cuda() for x in rays())
    want = first_hit(corners, o, d, backend="warp")
    torch.cuda.synchronize()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        torch.cuda._sleep(_SPIN_CYCLES)
        got = first_hit(corners * 1.0, o * 1.0, d * 1.0, backend="warp")
    torch.cuda.synchronize()
    assert (want >= 0).any() and torch.equal(got, want)
