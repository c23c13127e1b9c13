"""How the Warp kernels run: Warp loaded on first use, zero-copy views of torch tensors, launches on torch's stream,
and CPU launches split over threads.

Shared by the rasterizer (:mod:`lipmap.planes.raster_warp`) and the first-hit kernel
(:mod:`lipmap.planes.raycast_warp`); the kernels themselves live there.
"""
from __future__ import annotations

import contextlib
import functools
import os

import torch


@functools.lru_cache(maxsize=None)
def load():
    """The initialised ``warp`` module, or None without warp-lang (``import lipmap`` must work without it)."""
    try:
        import warp as wp
    except ImportError:
        return None
    # Warp's greeting and its "module loaded" lines are INFO; this level is process-wide
    wp.config.log_level = wp.LOG_WARNING
    # Warp probes for a CUDA driver on init and prints a warning when there is none; a CPU-only machine is fine
    with _quiet_stderr(not torch.cuda.is_available()):
        wp.init()
    return wp


@contextlib.contextmanager
def _quiet_stderr(active: bool):
    if not active:
        yield
        return
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def device_name(t: torch.Tensor) -> str:
    """Warp's name of the device ``t`` lives on."""
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


def stream(t: torch.Tensor):
    """The Warp stream of torch's current stream on ``t``'s device (None on the CPU, which has no streams).

    The kernels read tensors torch wrote and torch reads what they write, with no synchronisation between: both
    must queue on one stream. Warp would otherwise launch on a stream of its own, which a caller running torch on a
    side stream (``torch.cuda.stream(s)``) would race.
    """
    if t.device.type != "cuda":
        return None
    return _warp_stream(torch.cuda.current_stream(t.device))


@functools.lru_cache(maxsize=64)
def _warp_stream(torch_stream):
    # one Warp wrapper per torch stream (torch draws its streams from a fixed pool): wrapping registers the stream
    # with Warp, which a training step would otherwise pay at every launch
    return load().stream_from_torch(torch_stream)


def wrap(wp, t: torch.Tensor, dtype=None):
    """A Warp view of a contiguous torch tensor (no copy)."""
    return wp.from_torch(t.contiguous(), dtype=dtype, requires_grad=False)


def view(wp, t: torch.Tensor, dtype=None):
    """A Warp array descriptor of a contiguous torch tensor whose storage outlives the launch: no copy and no Python
    array object (a step passes about 80 arrays; ``wp.array`` wrappers cost about 1 ms of it on a CPU)."""
    if not t.is_contiguous():
        raise ValueError("a Warp view needs a contiguous tensor")  # a copy would be freed before the kernel runs
    return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)


def n_chunks(t: torch.Tensor) -> int:
    """Launches per kernel: Warp runs a CPU launch on one thread, so the CPU work is split over torch's threads."""
    return 1 if t.device.type == "cuda" else max(1, torch.get_num_threads())


@functools.lru_cache(maxsize=None)
def _pool(n: int):
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(max_workers=n, thread_name_prefix="lipmap-raster")


def launch_chunks(wp, kernel, dim_per_chunk: int, device: str, n: int, args_of, threads: int | None = None,
                  stream=None):
    """Launch ``kernel`` as ``n`` interleaved chunks, ``args_of(chunk)`` giving each one's arguments, on ``threads``
    threads (default ``n``), on ``stream`` (CUDA; see :func:`stream`).

    CPU chunks run on the calling thread and ``threads - 1`` pool threads (a CPU launch releases the GIL), each
    taking the next chunk not yet taken; their arguments are packed here, on the calling thread.
    """
    if dim_per_chunk == 0:
        return
    cmds = [wp.launch(kernel, dim=dim_per_chunk, device=device, inputs=args_of(h), record_cmd=True) for h in range(n)]
    threads = min(n, threads or n)
    todo = iter(cmds)  # next() on a list iterator is atomic under the GIL: each chunk runs once

    def drain():
        for cmd in todo:
            cmd.launch(stream)

    helpers = [_pool(threads - 1).submit(drain) for _ in range(threads - 1)] if threads > 1 else []
    drain()
    for f in helpers:
        f.result()
