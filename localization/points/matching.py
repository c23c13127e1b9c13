"""Descriptor matching of image pairs into an hloc ``matches.h5``: mutual nearest neighbour and Lowe's ratio."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from tqdm import tqdm

from lipmap import logger
from lipmap.artifacts import STAMP_ATTR, Stamp, reuse
from lipmap.imageio import commit_batches

from .. import hloc_io
from ..hloc_io import h5_update
from .config import MatchConfig


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
