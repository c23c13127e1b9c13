"""SIFT features of images into an hloc ``features.h5`` (pycolmap), in worker processes on a CPU.

Keypoints in memory are COLMAP's (pixel centre at +0.5, what pycolmap's SIFT returns - pinned by a test); the file
holds hloc's (integer centres) and :mod:`localization.hloc_io` converts.
"""
from __future__ import annotations

import contextlib
import itertools
from dataclasses import asdict
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from tqdm import tqdm

from lipmap import logger
from lipmap.artifacts import STAMP_ATTR, Stamp, reuse
from lipmap.errors import InputError
from lipmap.imageio import commit_batches

from .. import hloc_io
from ..hloc_io import h5_update, list_h5_names
from .config import SiftConfig


@contextlib.contextmanager
def colmap_quiet():
    """Silence COLMAP's glog INFO/WARNING lines unless the lipmap logger is at DEBUG level."""
    import logging

    import pycolmap

    old = pycolmap.logging.minloglevel
    if logger.getEffectiveLevel() > logging.DEBUG:
        pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def sift_device(device: str = "auto") -> str:
    """Where pycolmap's SIFT runs: "cuda" for ``auto`` when pycolmap was built with CUDA and sees a
    GPU, else "cpu". GPU SIFT finds (slightly) different features, so the device is recorded in the
    features file's stamp when it is not the CPU."""
    import pycolmap

    if device not in ("auto", "cpu", "cuda"):
        raise InputError(f"unknown SIFT device {device!r}; choose auto, cpu or cuda")
    if device == "auto":
        n_gpu = getattr(pycolmap, "get_num_cuda_devices", lambda: 1)
        device = "cuda" if getattr(pycolmap, "has_cuda", False) and n_gpu() > 0 else "cpu"
    if device == "cuda" and not getattr(pycolmap, "has_cuda", False):
        raise InputError("SIFT on cuda needs a pycolmap built with CUDA (pycolmap.has_cuda is False)")
    return device


def _sift_extractor(conf: SiftConfig, device: str = "cpu"):
    import pycolmap

    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = conf.num_threads
    opts.sift.max_num_features = conf.max_keypoints
    opts.sift.first_octave = conf.first_octave
    opts.sift.peak_threshold = conf.peak_threshold
    opts.sift.edge_threshold = conf.edge_threshold
    opts.sift.max_num_orientations = conf.max_num_orientations
    opts.sift.upright = conf.upright
    # pycolmap.Sift(...) still works in 4.2.1 but is deprecated in favour of FeatureExtractor.
    with colmap_quiet():
        return pycolmap.FeatureExtractor.create(opts, getattr(pycolmap.Device, device))


def sift_features(gray: np.ndarray, conf: SiftConfig, extractor=None) -> dict:
    """SIFT on one grayscale image.

    Args:
        gray: (H, W) uint8 image.

    Returns:
        dict with **keypoints** (N, 2) float64 COLMAP pixel convention, **descriptors** (N, 128)
        float32 unit-norm RootSIFT (COLMAP's L1_ROOT, uint8 / 512 renormalised), **scales** (N,),
        **oris** (N,) radians.
    """
    import pycolmap

    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise InputError(f"SIFT needs a (H, W) uint8 image, got {gray.shape} {gray.dtype}")
    extractor = extractor or _sift_extractor(conf)
    kps, desc = extractor.extract_from_uint8_array(np.ascontiguousarray(gray))
    kp = pycolmap.keypoints_to_matrix(kps).astype(np.float64).reshape(-1, 4)
    d = np.asarray(desc.data, dtype=np.float32).reshape(len(kp), 128)  # -1 fails when nothing was found
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return {"keypoints": kp[:, :2], "descriptors": d, "scales": kp[:, 2], "oris": kp[:, 3]}


_WORKER_EXTRACTOR = None  # one SIFT extractor per worker process (see _extract_in_worker)


def _load_and_extract(view, conf: SiftConfig, extractor) -> tuple:
    gray = view.load_color(gray=True)
    return (gray.shape[1], gray.shape[0]), sift_features(gray, conf, extractor)


def _init_worker(conf: SiftConfig, quiet_level: int):
    global _WORKER_EXTRACTOR
    logger.setLevel(quiet_level)
    _WORKER_EXTRACTOR = _sift_extractor(conf, "cpu")


def _extract_in_worker(view, conf: SiftConfig) -> tuple:
    return _load_and_extract(view, conf, _WORKER_EXTRACTOR)


def default_workers() -> int:
    """Worker processes for CPU SIFT: the cores this process may use."""
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _sift_stream(todo: Sequence, conf: SiftConfig, workers: int, device: str):
    """(view, image size, features) for each of ``todo``, in order.

    pycolmap's ``extract_from_uint8_array`` holds the GIL (its binding releases nothing, and two
    threads ran at 0.95 CPU-seconds per second), so CPU SIFT runs in ``workers`` processes, each
    with its own extractor, that also read the images; at most ``2 * workers`` images are in flight
    so memory stays bounded. On the GPU (or with one worker) one extractor runs here while a thread
    reads the next images (the decoders release the GIL).
    """
    from collections import deque
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    ahead = 2 * max(1, workers)
    if device == "cpu" and workers > 1:
        import multiprocessing as mp

        # spawn, not fork: the parent may hold torch / OpenMP threads
        pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                   initargs=(conf, logger.getEffectiveLevel()))

        def submit(v):
            return pool.submit(_extract_in_worker, v, conf)
    else:
        extractor = _sift_extractor(conf, device)
        pool = ThreadPoolExecutor(1)

        def submit(v):
            return pool.submit(v.load_color, gray=True)

    with pool:
        it = iter(todo)
        pending = deque((v, submit(v)) for _, v in zip(range(ahead), it))  # range first: zip must not consume a view it drops
        while pending:
            v, fut = pending.popleft()
            nxt = next(it, None)
            if nxt is not None:
                pending.append((nxt, submit(nxt)))
            if isinstance(pool, ThreadPoolExecutor):
                gray = fut.result()
                yield v, (gray.shape[1], gray.shape[0]), sift_features(gray, conf, extractor)
            else:
                size, f = fut.result()
                yield v, size, f


def extract_sift(views: Sequence, out_h5, conf: Optional[SiftConfig] = None, overwrite: bool = False, chunk: int = 16,
                 workers: Optional[int] = None, device: str = "auto") -> Path:
    """Extract SIFT for every view into an hloc ``features.h5``; images already there are skipped.

    Args:
        views: objects with ``.name`` and ``.load_color(gray=True)`` (:class:`lipmap.scene.View`);
            picklable when more than ``chunk`` images go to worker processes.
        out_h5: the features file (created or extended).
        conf: :class:`SiftConfig`.
        workers: CPU SIFT processes (default: the usable cores); 1 = in this process. A run of
            ``chunk`` images or fewer always stays in this process.
        device: "auto" (cuda when pycolmap has it and sees a GPU), "cpu" or "cuda" (:func:`sift_device`).

    Written per image, in the order of ``views`` and identical whatever ``workers``: ``keypoints``
    (N, 2) float32 hloc convention (COLMAP - 0.5),
    ``descriptors`` (128, N) float16 (lossless: COLMAP quantises SIFT to uint8 / 512), ``scores``
    (N,) = the SIFT scale (pycolmap 4 exposes no detector response; larger scales are the ones
    COLMAP keeps first), ``scales``, ``oris``, ``image_size`` [w, h]; attrs ``uncertainty`` = 1 px.
    """
    conf = conf or SiftConfig()
    device = sift_device(device)
    out_h5 = Path(out_h5)
    stamp = Stamp("features", {"sift": asdict(conf)} if device == "cpu" else {"sift": asdict(conf), "device": device})
    fresh = not reuse(out_h5, stamp, overwrite, "SIFT features")
    done = set() if fresh else set(list_h5_names(out_h5))
    todo = [v for v in views if v.name not in done]
    if len(todo) < len(views):
        logger.info("Skipping %d images already in %s.", len(views) - len(todo), out_h5.name)
    if not todo:
        return out_h5
    workers = default_workers() if workers is None else max(1, int(workers))
    workers = min(workers, len(todo)) if len(todo) > chunk else 1
    logger.info("Extracting SIFT (%s, %s%s) for %d images.", conf.name, device,
                f", {workers} processes" if device == "cpu" and workers > 1 else "", len(todo))
    stream = _sift_stream(todo, conf, workers, device)
    try:
        bar = tqdm(total=len(todo), desc="sift", unit="img", disable=len(todo) <= chunk)
        for start, end in commit_batches(len(todo), len(done), chunk):
            with h5_update(out_h5, fresh=fresh) as fd:
                fd.attrs[STAMP_ATTR] = stamp.to_json()
                for v, size, f in itertools.islice(stream, end - start):
                    bar.update(1)
                    hloc_io.write_features(
                        fd,
                        v.name,
                        f["keypoints"],
                        f["descriptors"].astype(np.float16),
                        scores=f["scales"],
                        image_size=size,
                        uncertainty=1.0,
                        extra={"scales": f["scales"].astype(np.float32), "oris": f["oris"].astype(np.float32)},
                    )
            fresh = False
        bar.close()
    finally:
        stream.close()  # shuts the workers down, also on an error
    return out_h5
