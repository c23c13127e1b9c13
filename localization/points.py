"""2D-3D point matches for query images: a built-in SIFT pipeline with hloc-shaped steps.

Steps (each writes one artifact in hloc's layout and skips work already in it unless ``overwrite``):

    extract_sift(views, features_h5)                  -> features.h5   (pycolmap SIFT)
    pairs_from_poses(mapping_views, pairs_txt)        -> pairs file    (covisible mapping pairs)
    match_features(pairs, features_h5, matches_h5)    -> matches.h5    (mutual NN + Lowe ratio)
    triangulate_map(mapping_views, ..., sfm_dir)      -> sfm/          (COLMAP model, KNOWN poses)
    point_matches_for_query(query, retrieved, ...)    -> PointMatches  (hloc localize_sfm's 2D-3D)

``build_point_map`` chains the mapping steps; ``match_queries`` extracts, retrieves and matches the
queries. Because the files are hloc's, any step can be replaced by hloc's own output.

Pixel convention: keypoints in memory are COLMAP's (pixel centre at +0.5, what pycolmap's SIFT
returns - pinned by a test); the files hold hloc's (integer centres) and :mod:`.hloc_io` converts.
"""
from __future__ import annotations

import contextlib
import itertools
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np
from tqdm import tqdm

from lipmap import logger
from lipmap.artifacts import STAMP_ATTR, Stamp, reuse, views_key, write_stamp
from lipmap.errors import InputError
from lipmap.imageio import commit_batches
from lipmap.presets import resolve

from . import hloc_io
from .hloc_io import ModelIndex, h5_update, list_h5_names

# ----------------------------------------------------------------------------------------------
# configs and presets
# ----------------------------------------------------------------------------------------------


@dataclass
class SiftConfig:
    """pycolmap SIFT options (COLMAP defaults except the keypoint budget)."""

    max_keypoints: int = 4096  # COLMAP keeps the coarsest-scale features when over budget
    first_octave: int = -1  # -1 = upsample once (COLMAP default): more small-scale features, ~2x slower
    peak_threshold: float = 0.02 / 3
    edge_threshold: float = 10.0
    max_num_orientations: int = 2
    upright: bool = False
    num_threads: int = -1

    @property
    def name(self) -> str:
        return f"sift-n{self.max_keypoints}" + ("" if self.first_octave == -1 else f"-o{self.first_octave}")


@dataclass
class MatchConfig:
    """Descriptor matching: mutual nearest neighbour + Lowe's ratio test (hloc's NN-ratio)."""

    ratio: float = 0.8  # on Euclidean distances, as hloc and COLMAP
    mutual: bool = True
    max_distance: Optional[float] = None  # Euclidean, unit descriptors (COLMAP uses 0.7); None = off

    @property
    def name(self) -> str:
        return f"nn{'-mutual' if self.mutual else ''}-ratio{self.ratio:g}"


@dataclass
class PairsConfig:
    """Mapping pairs from known poses: frustum overlap (sampled at nominal depths) + viewing angle."""

    num_neighbors: int = 10
    max_angle_deg: float = 60.0
    min_overlap: float = 0.2
    depths: tuple = (1.0, 2.0, 3.5)  # metres; indoor scenes. Scale with the scene for others.
    grid: tuple = (8, 6)


@dataclass
class TriangulationConfig:
    """Geometric verification with the known poses, then COLMAP's triangulator (poses held fixed)."""

    max_epipolar_error: float = 4.0  # px, Sampson distance w.r.t. the known relative pose
    min_inliers: int = 15  # a pair with fewer verified matches is dropped
    min_angle_deg: float = 1.5  # COLMAP default triangulation angle
    max_reproj_error: float = 4.0  # px, COLMAP's complete/merge thresholds
    ignore_two_view_tracks: bool = True
    seed: int = 0
    num_threads: int = -1


@dataclass
class PointsConfig:
    """The whole built-in point pipeline; ``name`` records the settings in artifact names."""

    sift: SiftConfig = field(default_factory=SiftConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)


confs = {
    "sift-n4096": PointsConfig(),
    "sift-n2048": PointsConfig(sift=SiftConfig(max_keypoints=2048)),
    # fast: no upsampling; for tests and quick runs
    "sift-n1024-fast": PointsConfig(sift=SiftConfig(max_keypoints=1024, first_octave=0)),
}


def get_conf(conf=None) -> PointsConfig:
    """A :class:`PointsConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "point pipeline", default="sift-n4096")


# ----------------------------------------------------------------------------------------------
# SIFT extraction
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# pairs between mapping images from their known poses
# ----------------------------------------------------------------------------------------------


def frustum_overlap(view_a, view_b, conf: Optional[PairsConfig] = None) -> float:
    """Fraction of a grid of ``view_a``'s pixels, at nominal depths, that ``view_b`` sees in its image."""
    return float(_overlap_matrix([view_a, view_b], conf or PairsConfig())[0, 1])


def _view_samples(views, conf: PairsConfig) -> list:
    """Each view's grid of pixel rays at the nominal depths, in the world frame: (S, 3) per view."""
    from lipmap.poses import invert_T

    gx, gy = conf.grid
    samples = []
    for v in views:
        cam = v.camera
        u = (np.arange(gx) + 0.5) / gx * cam.width
        w = (np.arange(gy) + 0.5) / gy * cam.height
        uu, ww = np.meshgrid(u, w)
        rays = np.stack([(uu - cam.cx) / cam.fx, (ww - cam.cy) / cam.fy, np.ones_like(uu)], -1).reshape(-1, 3)
        pts_cam = np.concatenate([rays * d for d in conf.depths])
        T = invert_T(v.cam_from_world)
        samples.append(pts_cam @ T[:3, :3].T + T[:3, 3])
    return samples


def _overlap_from(samples_i: np.ndarray, view_j) -> np.ndarray:
    """Fraction of each set of samples (..., S, 3) that ``view_j`` sees inside its image: (...,)."""
    from lipmap.geometry import project_points

    uv, z = project_points(samples_i, view_j.cam_from_world, view_j.camera)
    cam = view_j.camera
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height)
    return inside.mean(-1)


def _overlap_matrix(views, conf: PairsConfig) -> np.ndarray:
    """Dense (N, N) frustum overlap, ov[i, j] = fraction of i's samples j sees; the reference for
    :func:`pairs_from_poses`' pruned search (O(N^2) projections)."""
    samples = _view_samples(views, conf)
    n = len(views)
    ov = np.eye(n)
    for j, vj in enumerate(views):
        for i in range(n):
            if i == j:
                continue
            ov[i, j] = _overlap_from(samples[i], vj)
    return ov


def _frustum_bounds(views, samples):
    """Per view: centre (3,), optical axis (3,), half-angle of the cone around the axis that holds
    the image (its widest corner) and the farthest sample from the centre."""
    centres = np.stack([_centre(v) for v in views])
    axes = np.stack([v.cam_from_world[2, :3] for v in views])
    half = []
    for v in views:
        cam = v.camera
        x = np.array([0.0, cam.width]) - cam.cx
        y = np.array([0.0, cam.height]) - cam.cy
        r = np.hypot(x[:, None] / cam.fx, y[None, :] / cam.fy).max()
        half.append(np.arctan(r))
    reach = np.array([np.linalg.norm(s - c, axis=1).max() for s, c in zip(samples, centres)])
    return centres, axes, np.array(half), reach


def _centre(view) -> np.ndarray:
    T = view.cam_from_world
    return -T[:3, :3].T @ T[:3, 3]


def _ball_meets_cone(mid, radius, apex, axis, half) -> np.ndarray:
    """Whether balls (mid, radius) can meet the infinite cones (apex, unit axis, half-angle); arrays
    of pairs. Conservative (1e-6 rad slack): a False is certain."""
    w = mid - apex
    dist = np.linalg.norm(w, axis=1)
    cosb = np.einsum("ij,ij->i", w, axis) / np.maximum(dist, 1e-12)
    beta = np.arccos(np.clip(cosb, -1, 1))
    spread = np.arcsin(np.clip(radius / np.maximum(dist, 1e-12), 0, 1))
    return (dist <= radius) | (beta <= half + spread + 1e-6)


def _candidate_pairs(views, samples, conf: PairsConfig, block: int = 512):
    """Pairs (i < j) that may pass the exact test, in blocks of i: an iterator of (I, J) arrays.

    A pair is kept by the exact test only if each view sees some of the other's samples (overlap
    >= min_overlap > 0 both ways) and their axes are within ``max_angle_deg``. A sample s_j of
    view j inside view i's image lies in i's cone (half-angle t_i to the widest image corner), and
    s_j is within R_j (the farthest sample, ~ the largest depth) of j's centre; likewise for i.
    With d = c_j - c_i and L = |d| this gives d.a_i >= (L - R_j) cos t_i - R_j and
    -d.a_j >= (L - R_i) cos t_j - R_i; their sum is at most L |a_i - a_j| <= 2 L sin(max_angle / 2),
    so  L <= 2 R / (cos t - sin(max_angle / 2))  with R the largest reach and t the widest cone.
    Candidates are the centres within that radius (a cKDTree), then the axis angle, then whether
    each view's sample ball can meet the other's cone at all. When the radius is unbounded
    (wide cones, large angles) or min_overlap <= 0 every pair of each block is a candidate.
    """
    from scipy.spatial import cKDTree

    n = len(views)
    centres, axes, half, reach = _frustum_bounds(views, samples)
    mids = np.stack([s.mean(0) for s in samples])
    balls = np.array([np.linalg.norm(s - m, axis=1).max() for s, m in zip(samples, mids)])
    denom = np.cos(half.max()) - np.sin(np.radians(min(conf.max_angle_deg, 180.0)) / 2)
    prune = conf.min_overlap > 0
    radius = 2 * reach.max() / denom * (1 + 1e-9) + 1e-9 if prune and denom > 0 else np.inf
    tree = cKDTree(centres) if np.isfinite(radius) else None
    cos_max = np.cos(np.radians(conf.max_angle_deg)) - 1e-9
    for start in range(0, n, block):
        rows = np.arange(start, min(n, start + block))
        if tree is None:
            I, J = np.triu_indices(n, 1)
            keep = (I >= start) & (I < rows[-1] + 1)
            I, J = I[keep], J[keep]
        else:
            near = tree.query_ball_point(centres[rows], radius)
            I = np.repeat(rows, [len(x) for x in near])
            J = np.concatenate([np.asarray(x, np.int64) for x in near]) if len(I) else np.zeros(0, np.int64)
            keep = J > I
            I, J = I[keep], J[keep]
        keep = np.einsum("ij,ij->i", axes[I], axes[J]) >= cos_max
        I, J = I[keep], J[keep]
        if prune:
            keep = _ball_meets_cone(mids[I], balls[I], centres[J], axes[J], half[J])
            keep &= _ball_meets_cone(mids[J], balls[J], centres[I], axes[I], half[I])
            I, J = I[keep], J[keep]
        yield I, J


def _top_per_row(rows, cols, vals, k):
    """Keep each row's k best (value descending, then column) of sparse (row, col, value) triples."""
    order = np.lexsort((cols, -vals, rows))
    rows, cols, vals = rows[order], cols[order], vals[order]
    first = np.searchsorted(rows, rows, side="left")
    keep = np.arange(len(rows)) - first < k
    return rows[keep], cols[keep], vals[keep]


def pairs_from_poses(views: Sequence, out_path=None, conf: Optional[PairsConfig] = None) -> list[tuple[str, str]]:
    """Covisible pairs of posed images: for each image its ``num_neighbors`` best partners by
    symmetric frustum overlap (min of both directions), among those within ``max_angle_deg`` of
    viewing direction and with overlap >= ``min_overlap``. Each unordered pair is listed once, in
    the order of ``views``. Written as an hloc pairs file when ``out_path`` is given.

    The exact overlap is computed only for candidate pairs that can pass it (:func:`_candidate_pairs`:
    nearby centres, close axes, frusta that can meet), so the cost is ~N x the neighbours within
    reach rather than N^2, and memory stays ~N x num_neighbors; the pairs equal those of the dense
    test over every pair (:func:`_overlap_matrix`)."""
    conf = conf or PairsConfig()
    n = len(views)
    samples = _view_samples(views, conf)
    stack = np.stack(samples) if n else np.zeros((0, 0, 3))
    dirs = np.stack([v.cam_from_world[2, :3] for v in views]) if n else np.zeros((0, 3))
    k = conf.num_neighbors
    rows = np.zeros(0, np.int64)
    cols = np.zeros(0, np.int64)
    vals = np.zeros(0)
    n_cand = 0
    for I, J in _candidate_pairs(views, samples, conf) if n > 1 else ():
        n_cand += len(I)
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", dirs[I], dirs[J]), -1, 1)))
        I, J = I[ang <= conf.max_angle_deg], J[ang <= conf.max_angle_deg]
        ov_ij = np.empty(len(I))
        ov_ji = np.empty(len(I))
        for j in np.unique(J):  # i's samples seen by j
            sel = J == j
            ov_ij[sel] = _overlap_from(stack[I[sel]], views[j])
        for i in np.unique(I):  # j's samples seen by i
            sel = I == i
            ov_ji[sel] = _overlap_from(stack[J[sel]], views[i])
        sym = np.minimum(ov_ij, ov_ji)
        ok = sym >= conf.min_overlap
        I, J, sym = I[ok], J[ok], sym[ok]
        rows, cols, vals = np.concatenate([rows, I, J]), np.concatenate([cols, J, I]), np.concatenate([vals, sym, sym])
        rows, cols, vals = _top_per_row(rows, cols, vals, k)
    rows, cols, _ = _top_per_row(rows, cols, vals, k)
    chosen = set(zip(np.minimum(rows, cols).tolist(), np.maximum(rows, cols).tolist()))
    pairs = [(views[i].name, views[j].name) for i, j in sorted(chosen)]
    logger.info("%d covisible pairs among %d posed images (%d candidate pairs tested).", len(pairs), n, n_cand)
    if out_path is not None:
        hloc_io.write_pairs(out_path, pairs)
    return pairs


def _pairs_from_poses_dense(views: Sequence, conf: Optional[PairsConfig] = None) -> list[tuple[str, str]]:
    """The former all-pairs :func:`pairs_from_poses` (O(N^2) projections): the reference in tests
    and benchmarks."""
    conf = conf or PairsConfig()
    n = len(views)
    ov = _overlap_matrix(views, conf)
    sym = np.minimum(ov, ov.T)
    dirs = np.stack([v.cam_from_world[2, :3] for v in views])  # optical axes in the world frame
    ang = np.degrees(np.arccos(np.clip(dirs @ dirs.T, -1, 1)))
    ok = (sym >= conf.min_overlap) & (ang <= conf.max_angle_deg) & ~np.eye(n, dtype=bool)
    chosen = set()
    for i in range(n):
        cand = np.flatnonzero(ok[i])
        # stable order: overlap descending, then index
        cand = cand[np.lexsort((cand, -sym[i, cand]))][: conf.num_neighbors]
        for j in cand:
            chosen.add((min(i, j), max(i, j)))
    return [(views[i].name, views[j].name) for i, j in sorted(chosen)]


# ----------------------------------------------------------------------------------------------
# matching
# ----------------------------------------------------------------------------------------------


def mutual_nn_ratio(desc0: np.ndarray, desc1: np.ndarray, conf: Optional[MatchConfig] = None):
    """Match two sets of unit descriptors.

    Args:
        desc0: (N0, D), desc1: (N1, D) unit-norm.

    Returns:
        **matches0** (N0,) int32 index into desc1 or -1, **scores0** (N0,) float32 cosine
        similarity of the match (0 where unmatched). Deterministic (no randomness involved).
    """
    import torch

    conf = conf or MatchConfig()
    n0, n1 = len(desc0), len(desc1)
    matches0 = np.full(n0, -1, np.int32)
    scores0 = np.zeros(n0, np.float32)
    if n0 == 0 or n1 < 2:
        return matches0, scores0
    d0 = torch.from_numpy(np.ascontiguousarray(desc0, dtype=np.float32))
    d1 = torch.from_numpy(np.ascontiguousarray(desc1, dtype=np.float32))
    sim = d0 @ d1.T
    top, idx = sim.topk(2, dim=1)
    dist = (2.0 - 2.0 * top).clamp(min=0)  # squared Euclidean of unit vectors
    keep = dist[:, 0] <= (conf.ratio**2) * dist[:, 1]
    if conf.max_distance is not None:
        keep &= dist[:, 0] <= conf.max_distance**2
    nn0 = idx[:, 0]
    if conf.mutual:
        nn1 = sim.argmax(dim=0)
        keep &= nn1[nn0] == torch.arange(n0)
    keep = keep.numpy()
    matches0[keep] = nn0.numpy()[keep]
    scores0[keep] = top[:, 0].numpy()[keep]
    return matches0, scores0


class _DescriptorCache:
    """Unit descriptors by image name, least recently used dropped first; at most ``max_items``
    images and ``max_bytes``. ``reads`` counts the file reads."""

    def __init__(self, features_h5, max_items: int = 256, max_bytes: int = 1 << 30):
        from collections import OrderedDict

        self.path = Path(features_h5)
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.items: "OrderedDict[str, np.ndarray]" = OrderedDict()
        self.nbytes = 0
        self.reads = 0

    def __call__(self, name: str) -> np.ndarray:
        if name in self.items:
            self.items.move_to_end(name)
            return self.items[name]
        d = hloc_io.read_features(self.path, name)["descriptors"]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        self.reads += 1
        while self.items and (len(self.items) >= self.max_items or self.nbytes + d.nbytes > self.max_bytes):
            self.nbytes -= self.items.popitem(last=False)[1].nbytes
        self.items[name] = d
        self.nbytes += d.nbytes
        return d


def _match_schedule(pairs: Sequence, block: int = 64) -> list:
    """``pairs`` reordered so that a cache of ``2 * block`` images reads each image at most once per
    block pair it is in: images are numbered in name order (a sequence's frames stay together),
    grouped in blocks of ``block``, and the pairs sorted by (block of the lower number, block of
    the higher, lower, higher). An image is then read at most min(its pairs, 2 x blocks) times,
    once for pairs between nearby frames, whatever order the pairs came in."""
    idx = {n: i for i, n in enumerate(sorted({n for p in pairs for n in p}))}

    def key(p):
        i, j = sorted((idx[p[0]], idx[p[1]]))
        return i // block, j // block, i, j

    return sorted(pairs, key=key)


def match_features(pairs, features_h5, out_h5, conf: Optional[MatchConfig] = None, overwrite: bool = False, chunk: int = 64,
                   block: int = 64, max_cache_bytes: int = 1 << 30) -> Path:
    """Match the descriptors of image pairs into an hloc ``matches.h5``.

    Args:
        pairs: a pairs file or a list of (name0, name1); a pair already in ``out_h5`` (either order,
            either naming) or repeated reversed in the list is matched once.
        features_h5: features of every paired image.
        block, max_cache_bytes: the pairs are matched in :func:`_match_schedule`'s order with up
            to ``2 * block`` images' descriptors (and at most ``max_cache_bytes``) in memory. torch's
            matmul already uses every core, so pairs are matched one after the other.

    Each pair is stored as ``names_to_pair(name0, name1)`` with ``matches0`` int32 indexed by
    name0's keypoints (-1 = unmatched) and ``matching_scores0`` float32 (cosine similarity).
    """
    import h5py

    conf = conf or MatchConfig()
    pairs_path = Path(pairs) if isinstance(pairs, (str, Path)) else None
    pairs = hloc_io.read_pairs(pairs_path) if pairs_path is not None else [tuple(p) for p in pairs]
    hloc_io.check_pairs_in_features(pairs, features_h5, pairs_path)
    out_h5 = Path(out_h5)
    stamp = Stamp("matches", {"match": asdict(conf)})
    fresh = not reuse(out_h5, stamp, overwrite, "matches")
    seen, todo = set(), []
    existing = None if fresh else h5py.File(str(out_h5), "r")
    try:
        for a, b in pairs:
            if (a, b) in seen or (b, a) in seen or a == b:
                continue
            seen.add((a, b))
            if existing is not None and hloc_io.pair_in_file(existing, a, b):
                continue
            todo.append((a, b))
    finally:
        if existing is not None:
            existing.close()
    if len(todo) < len(seen):
        logger.info("Skipping %d pairs already in %s.", len(seen) - len(todo), out_h5.name)
    if not todo:
        return out_h5
    logger.info("Matching %d pairs (%s).", len(todo), conf.name)
    todo = _match_schedule(todo, block)
    desc = _DescriptorCache(features_h5, max_items=2 * block, max_bytes=max_cache_bytes)
    bar = tqdm(total=len(todo), desc="match", unit="pair", disable=len(todo) <= chunk)
    for start, end in commit_batches(len(todo), len(seen) - len(todo), chunk):
        with h5_update(out_h5, fresh=fresh) as fd:
            fd.attrs[STAMP_ATTR] = stamp.to_json()
            for a, b in todo[start:end]:
                m0, s0 = mutual_nn_ratio(desc(a), desc(b), conf)
                hloc_io.write_matches(fd, a, b, m0, s0)
                bar.update(1)
        fresh = False
    bar.close()
    return out_h5


# ----------------------------------------------------------------------------------------------
# triangulation with known poses
# ----------------------------------------------------------------------------------------------


def sampson_distance(x0: np.ndarray, x1: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Sampson distance in pixels of correspondences (N, 2) <-> (N, 2) under x1^T F x0 = 0."""
    h0 = np.concatenate([x0, np.ones((len(x0), 1))], 1)
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    Fx0 = h0 @ F.T
    Ftx1 = h1 @ F
    num = np.sum(h1 * Fx0, 1) ** 2
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-18))


def fundamental_from_poses(cam0_from_world, cam1_from_world, K0: np.ndarray, K1: np.ndarray) -> np.ndarray:
    """F with x1^T F x0 = 0 from two known poses and intrinsics (pixel conventions must agree)."""
    from lipmap.poses import invert_T

    T = cam1_from_world @ invert_T(cam0_from_world)  # cam1_from_cam0
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K1).T @ (tx @ R) @ np.linalg.inv(K0)


def triangulate_map(
    mapping_views: Sequence,
    features_h5,
    pairs,
    matches_h5,
    sfm_dir,
    conf: Optional[TriangulationConfig] = None,
    overwrite: bool = False,
) -> Path:
    """Triangulate matched SIFT features with the KNOWN mapping poses into a COLMAP model.

    Builds a pycolmap.Reconstruction holding the known cameras and poses (COLMAP 4: one trivial
    rig per camera, one trivial frame per image), a COLMAP database with the keypoints and the
    matches that pass the epipolar check against the known relative pose, and runs
    ``pycolmap.triangulate_points`` (COLMAP's point_triangulator: poses and intrinsics stay fixed,
    bundle adjustment refines the points only). This is what hloc's ``triangulation.py`` does,
    with the geometric verification done from the known poses instead of RANSAC.

    Args:
        mapping_views: posed :class:`lipmap.scene.View` objects (names as in the h5 files).
        features_h5, matches_h5: hloc files; pairs: pairs file or list of (name0, name1).
        sfm_dir: output folder (cameras/images/points3D/rigs/frames .bin, plus database.db).

    Returns:
        ``sfm_dir``; skipped when it already holds a model, unless ``overwrite``.
    """
    conf = conf or TriangulationConfig()
    sfm_dir = Path(sfm_dir)
    if not overwrite and (sfm_dir / "points3D.bin").exists() and (sfm_dir / "images.bin").exists():
        logger.info("Skipping triangulation: %s exists.", sfm_dir)
        return sfm_dir
    unique_pairs = _unique_pairs(_checked_pairs(mapping_views, pairs))
    _triangulate_atomically(sfm_dir, mapping_views, features_h5, unique_pairs, matches_h5, conf)
    return sfm_dir


def _checked_pairs(mapping_views: Sequence, pairs) -> list:
    """The pairs as tuples (read from a pairs file or given); InputError if they name an unknown or unposed view."""
    pairs_path = Path(pairs) if isinstance(pairs, (str, Path)) else None
    pairs = hloc_io.read_pairs(pairs_path) if pairs_path is not None else [tuple(p) for p in pairs]
    by_name = {v.name: v for v in mapping_views}
    for a, b in pairs:
        for n in (a, b):
            if n not in by_name:
                raise InputError(f"paired image {n!r} is not one of the mapping views", pairs_path)
    for v in mapping_views:
        if v.cam_from_world is None:
            raise InputError(f"mapping view {v.name} has no pose; triangulation needs known poses")
    return pairs


def _unique_pairs(pairs: list) -> list:
    """The pairs in order without self-pairs and repeats in either order."""
    seen, unique_pairs = set(), []
    for a, b in pairs:  # a pair listed twice (or reversed) would violate the database's unique key
        if a != b and (a, b) not in seen and (b, a) not in seen:
            seen.add((a, b))
            unique_pairs.append((a, b))
    return unique_pairs


def _triangulate_atomically(sfm_dir: Path, mapping_views: Sequence, features_h5, pairs: list, matches_h5,
                            conf: TriangulationConfig):
    """Triangulate in a temporary folder renamed to ``sfm_dir`` at the end (never a partial model); log the model."""
    import shutil

    tmp = sfm_dir.parent / f".{sfm_dir.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    t0 = time.time()
    try:
        rec = _triangulate_into(tmp, mapping_views, features_h5, pairs, matches_h5, conf)
        if sfm_dir.exists():
            shutil.rmtree(sfm_dir)
        tmp.rename(sfm_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info(
        "Triangulated %d points (mean track %.2f, mean reprojection error %.2f px) in %.1f s.",
        rec.num_points3D(),
        rec.compute_mean_track_length() if rec.num_points3D() else 0.0,
        rec.compute_mean_reprojection_error() if rec.num_points3D() else 0.0,
        time.time() - t0,
    )


def _triangulation_options(conf: TriangulationConfig):
    """COLMAP's triangulator options from ``conf``, with the intrinsics held fixed."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.extract_colors = False  # COLMAP 4.2's point_triangulator reads colours anyway; .jpg vs .png names only warn
    opts.random_seed = conf.seed
    opts.num_threads = conf.num_threads
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    tri = opts.triangulation
    tri.min_angle = conf.min_angle_deg
    tri.complete_max_reproj_error = conf.max_reproj_error
    tri.merge_max_reproj_error = conf.max_reproj_error
    tri.ignore_two_view_tracks = conf.ignore_two_view_tracks
    tri.random_seed = conf.seed
    return opts


def _triangulate_into(tmp: Path, mapping_views: Sequence, features_h5, pairs: list, matches_h5,
                      conf: TriangulationConfig):
    """Write the database and the triangulated model's files into ``tmp``; returns the model."""
    import pycolmap

    rec = _reconstruction_and_database(mapping_views, features_h5, pairs, matches_h5, tmp / "database.db", conf)
    opts = _triangulation_options(conf)
    pycolmap.set_random_seed(conf.seed)
    model_dir = tmp / "model"
    model_dir.mkdir()
    with colmap_quiet():
        rec = pycolmap.triangulate_points(rec, tmp / "database.db", tmp, model_dir, clear_points=True, options=opts)
    # hloc's layout: the model files beside database.db
    for f in model_dir.iterdir():
        f.rename(tmp / f.name)
    model_dir.rmdir()
    return rec


def _reconstruction_and_database(mapping_views, features_h5, pairs, matches_h5, db_path, conf: TriangulationConfig):
    """The known-pose Reconstruction (no points) and a COLMAP database of keypoints + verified matches."""
    import pycolmap

    by_name = {v.name: v for v in mapping_views}
    rec = pycolmap.Reconstruction()
    cam_ids: dict = {}
    image_ids: dict[str, int] = {}
    kps: dict[str, np.ndarray] = {}
    db = pycolmap.Database.open(str(db_path))
    try:
        for v in mapping_views:
            if v.camera not in cam_ids:
                cam_ids[v.camera] = len(cam_ids) + 1
                cam = v.camera.to_pycolmap(camera_id=cam_ids[v.camera])
                rec.add_camera_with_trivial_rig(cam)
                db.write_camera(cam, use_camera_id=True)
            image_id = len(image_ids) + 1
            image_ids[v.name] = image_id
            R, t = v.cam_from_world[:3, :3], v.cam_from_world[:3, 3]
            image = pycolmap.Image(name=v.name, camera_id=cam_ids[v.camera], image_id=image_id)
            rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
            db.write_image(pycolmap.Image(name=v.name, camera_id=cam_ids[v.camera], image_id=image_id), use_image_id=True)
            kps[v.name] = hloc_io.read_keypoints(features_h5, v.name)  # COLMAP convention already
            db.write_keypoints(image_id, kps[v.name].astype(np.float32))

        n_raw = n_ver = n_pairs = 0
        with hloc_io.open_h5(matches_h5) as mfd:
            for a, b in tqdm(pairs, desc="verify", disable=len(pairs) < 500):
                matches, _ = hloc_io.read_matches_from(mfd, a, b, matches_h5)
                if len(matches) and (matches[:, 0].max() >= len(kps[a]) or matches[:, 1].max() >= len(kps[b])):
                    raise InputError(f"matches of ({a}, {b}) index beyond the keypoints in {features_h5}", matches_h5)
                va, vb = by_name[a], by_name[b]
                F = fundamental_from_poses(va.cam_from_world, vb.cam_from_world, va.camera.K, vb.camera.K)
                err = sampson_distance(kps[a][matches[:, 0]], kps[b][matches[:, 1]], F) if len(matches) else np.zeros(0)
                inl = matches[err <= conf.max_epipolar_error]
                n_raw += len(matches)
                if len(inl) < conf.min_inliers:
                    continue
                ia, ib = image_ids[a], image_ids[b]
                if ia > ib:  # COLMAP stores a pair with the smaller image id first
                    ia, ib, matches, inl, va, vb = ib, ia, matches[:, ::-1], inl[:, ::-1], vb, va
                db.write_matches(ia, ib, np.ascontiguousarray(matches, dtype=np.uint32))
                tvg = pycolmap.TwoViewGeometry()
                tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                tvg.inlier_matches = np.ascontiguousarray(inl, dtype=np.uint32)
                T = vb.cam_from_world @ np.linalg.inv(va.cam_from_world)
                tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
                db.write_two_view_geometry(ia, ib, tvg)
                n_ver += len(inl)
                n_pairs += 1
    finally:
        db.close()
    logger.info("Verified %d / %d matches with the known poses; %d / %d pairs kept.", n_ver, n_raw, n_pairs, len(pairs))
    return rec


def model_stats(sfm_dir_or_rec) -> dict:
    """Number of 3D points, mean track length, mean / median reprojection error (px) of a model."""
    rec = hloc_io.read_sfm(sfm_dir_or_rec) if isinstance(sfm_dir_or_rec, (str, Path)) else sfm_dir_or_rec
    errs = np.array([p.error for p in rec.points3D.values()])
    return {
        "num_points3D": int(rec.num_points3D()),
        "mean_track_length": float(rec.compute_mean_track_length()) if len(errs) else 0.0,
        "mean_reproj_error": float(errs.mean()) if len(errs) else float("nan"),
        "median_reproj_error": float(np.median(errs)) if len(errs) else float("nan"),
    }


# ----------------------------------------------------------------------------------------------
# 2D-3D matches of a query
# ----------------------------------------------------------------------------------------------


@dataclass
class PointMatches:
    """2D-3D point matches of one query; unpacks as ``p2d, p3d, point3D_ids``.

    Attributes:
        p2d: (N, 2) query keypoints, COLMAP pixel convention.
        p3d: (N, 3) world points.
        point3D_ids: (N,) ids in the reconstruction.
        keypoint_idx: (N,) index of each query keypoint in the features file.
    """

    p2d: np.ndarray
    p3d: np.ndarray
    point3D_ids: np.ndarray
    keypoint_idx: np.ndarray

    def __iter__(self):
        return iter((self.p2d, self.p3d, self.point3D_ids))

    def __len__(self) -> int:
        return len(self.p2d)

    def subset(self, idx: np.ndarray) -> "PointMatches":
        return PointMatches(self.p2d[idx], self.p3d[idx], self.point3D_ids[idx], self.keypoint_idx[idx])


def point_matches_for_query(query_name: str, retrieved: Iterable[str], features_h5, matches_h5, reconstruction) -> PointMatches:
    """2D-3D matches of one query from its matches to retrieved database images (hloc's localize_sfm).

    Each query keypoint gets the 3D points of the database keypoints it matched; a keypoint
    matched to several 3D points (through different database images) keeps one entry per
    distinct 3D point, and repeated (keypoint, 3D point) pairs are kept once.

    Args:
        reconstruction: a pycolmap.Reconstruction, a :class:`~localization.hloc_io.ModelIndex`
            (reuse it across queries) or an SfM folder.

    Returns:
        :class:`PointMatches`, sorted by (keypoint index, 3D point id).
    """
    if isinstance(reconstruction, ModelIndex):
        model = reconstruction
    elif isinstance(reconstruction, (str, Path)):
        model = ModelIndex(hloc_io.read_sfm(reconstruction), reconstruction)
    else:
        model = ModelIndex(reconstruction)
    kpq = hloc_io.read_keypoints(features_h5, query_name)
    rows = []
    with hloc_io.open_h5(matches_h5) as mfd:
        for db_name in dict.fromkeys(retrieved):  # unique, order kept
            ids = model.point3D_ids(db_name)
            m, _ = hloc_io.read_matches_from(mfd, query_name, db_name, matches_h5)
            if len(m) == 0:
                continue
            if m[:, 0].max() >= len(kpq) or m[:, 1].max() >= len(ids):
                raise InputError(
                    f"matches of ({query_name}, {db_name}) index keypoints beyond the query's {len(kpq)} features "
                    f"or the model image's {len(ids)} points2D (features and model from different runs?)",
                    matches_h5,
                )
            pid = ids[m[:, 1]]
            ok = pid >= 0
            rows.append(np.stack([m[ok, 0], pid[ok]], 1))
    if rows:
        rows = np.unique(np.concatenate(rows), axis=0)
    else:
        rows = np.zeros((0, 2), np.int64)
    return PointMatches(
        p2d=kpq[rows[:, 0]], p3d=model.xyz(rows[:, 1]), point3D_ids=rows[:, 1].astype(np.int64), keypoint_idx=rows[:, 0]
    )


def point_matches_from_hloc(query: str, sfm_dir, features_h5, matches_h5, pairs, model: Optional[ModelIndex] = None,
                            pairs_name=None):
    """2D-3D point matches of one query from hloc's outputs, the way hloc's ``localize_sfm`` builds them.

    Args:
        query: query image name (a group in ``features_h5``).
        sfm_dir: COLMAP model of the database images (ignored when ``model`` is given).
        features_h5, matches_h5: hloc files holding the query's keypoints and query-db matches.
        pairs: a pairs file path, or a list of (query, db) pairs / db names; those of ``query``
            are used, in order.
        model: a :class:`ModelIndex` reused across queries (read from ``sfm_dir`` if None).
        pairs_name: the file a pairs list was read from, named in error messages.

    Returns:
        :class:`PointMatches` - p2d (N, 2) COLMAP convention, p3d (N, 3),
        point3D_ids (N,); unpacks as ``p2d, p3d, ids``.
    """
    if model is None:
        model = ModelIndex(hloc_io.read_sfm(sfm_dir), sfm_dir)
    pairs_path = Path(pairs) if isinstance(pairs, (str, Path)) else None
    pair_list = hloc_io.read_pairs(pairs_path) if pairs_path is not None else [tuple(p) for p in pairs]
    pairs_path = pairs_path or pairs_name
    retrieved = hloc_io.pairs_by_query(pair_list).get(query, [])
    if not Path(features_h5).exists():
        raise InputError("features file is missing", features_h5)
    with hloc_io.open_h5(features_h5) as fd:
        if query not in fd:
            raise InputError(
                f"query {query!r} (from pairs {pairs_path or 'list'}) has no group {query!r} in the features file",
                features_h5,
            )
    for name in retrieved:
        if name not in model:
            raise InputError(
                f"image {name!r} (paired with {query!r}) is not in the SfM model {sfm_dir}", pairs_path or sfm_dir
            )
    if not retrieved:
        logger.warning("no database images paired with query %s", query)
    return point_matches_for_query(query, retrieved, features_h5, matches_h5, model)


# ----------------------------------------------------------------------------------------------
# chains
# ----------------------------------------------------------------------------------------------


def build_point_map(mapping_views: Sequence, out_dir, conf: Optional[PointsConfig] = None, overwrite: bool = False) -> dict:
    """Mapping side of the built-in pipeline: SIFT, covisible pairs, matches, triangulation.

    Returns:
        dict of artifact paths: ``features``, ``pairs``, ``matches``, ``sfm`` and per-step
        ``timings`` (seconds; 0 when a step was skipped).
    """
    conf = conf or PointsConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    features = out_dir / f"feats-{conf.sift.name}.h5"
    pairs = out_dir / f"pairs-db-covis{conf.pairs.num_neighbors}.txt"
    matches = out_dir / f"feats-{conf.sift.name}_{conf.match.name}_{pairs.stem}.h5"
    sfm = out_dir / f"sfm_{conf.sift.name}_{conf.match.name}"
    timings = {}
    t = time.time()
    extract_sift(mapping_views, features, conf.sift, overwrite)
    timings["extract"] = time.time() - t
    t = time.time()
    pairs_stamp = Stamp("pairs-covisible", {"pairs": asdict(conf.pairs), "views": views_key(mapping_views)})
    if not reuse(pairs, pairs_stamp, overwrite, "covisible pairs", replace_stale=True):
        pairs_from_poses(mapping_views, pairs, conf.pairs)
        write_stamp(pairs, pairs_stamp)
    timings["pairs"] = time.time() - t
    t = time.time()
    match_features(pairs, features, matches, conf.match, overwrite)
    timings["match"] = time.time() - t
    t = time.time()
    sfm_stamp = Stamp("sfm", {"triangulation": asdict(conf.triangulation), "sift": asdict(conf.sift),
                              "match": asdict(conf.match), "pairs": pairs_stamp.digest, "views": views_key(mapping_views)})
    if not reuse(sfm, sfm_stamp, overwrite, "triangulation", replace_stale=True):
        triangulate_map(mapping_views, features, pairs, matches, sfm, conf.triangulation, overwrite=True)
        write_stamp(sfm, sfm_stamp)
    timings["triangulate"] = time.time() - t
    return {"features": features, "pairs": pairs, "matches": matches, "sfm": sfm, "timings": timings}


def match_queries(
    query_views: Sequence,
    mapping_names: Sequence[str],
    features_h5,
    out_dir,
    conf: Optional[PointsConfig] = None,
    retrieval=None,
    pairs=None,
    overwrite: bool = False,
) -> dict:
    """Query side: SIFT on the queries (into the mapping ``features_h5``), retrieval (or a given
    pairs file), matching against the retrieved mapping images.

    Args:
        retrieval: :class:`localization.retrieval.RetrievalConfig` (default VLAD top-10) - unused
            when ``pairs`` is given.
        pairs: an existing query pairs file / list to use instead of retrieval.

    Returns:
        dict with ``pairs`` (path), ``matches`` (path), ``timings`` (seconds per step).
    """
    from .retrieval import RetrievalConfig, pairs_from_retrieval

    conf = conf or PointsConfig()
    out_dir = Path(out_dir)
    timings = {}
    t = time.time()
    extract_sift(query_views, features_h5, conf.sift, overwrite)
    timings["extract"] = time.time() - t
    t = time.time()
    if pairs is None:
        rconf = retrieval or RetrievalConfig()
        pairs = out_dir / f"pairs-query-{rconf.name}-top{rconf.num_retrieved}_{Path(features_h5).stem}.txt"
        pairs_from_retrieval([v.name for v in query_views], list(mapping_names), features_h5, pairs, rconf, overwrite=overwrite)
    timings["retrieval"] = time.time() - t
    pairs_name = Path(pairs).stem if isinstance(pairs, (str, Path)) else "pairs-query"
    matches = out_dir / f"feats-{conf.sift.name}_{conf.match.name}_{pairs_name}.h5"
    t = time.time()
    match_features(pairs, features_h5, matches, conf.match, overwrite)
    timings["match"] = time.time() - t
    return {"pairs": pairs, "matches": matches, "timings": timings}


__all__ = [
    "SiftConfig",
    "MatchConfig",
    "PairsConfig",
    "TriangulationConfig",
    "PointsConfig",
    "confs",
    "sift_features",
    "extract_sift",
    "frustum_overlap",
    "pairs_from_poses",
    "mutual_nn_ratio",
    "match_features",
    "sampson_distance",
    "fundamental_from_poses",
    "triangulate_map",
    "model_stats",
    "PointMatches",
    "point_matches_for_query",
    "point_matches_from_hloc",
    "build_point_map",
    "match_queries",
]
