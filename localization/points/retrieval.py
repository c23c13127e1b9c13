"""Image retrieval without downloaded weights: VLAD or bag of visual words over local descriptors.

A codebook is trained (seeded k-means) on the mapping images' descriptors from an hloc
``features.h5``; each image gets a global descriptor (stored in hloc's global-features layout: one
group per image with ``global_descriptor``); each query is paired with its top-k mapping images by
cosine similarity and the result is written as an hloc pairs file. A user-supplied pairs file
(e.g. from hloc's NetVLAD retrieval) can be used instead: see :func:`localization.hloc_io.read_pairs`.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from tqdm import tqdm

from lipmap import logger
from lipmap.artifacts import Stamp, reuse, write_stamp
from lipmap.errors import InputError
from lipmap.presets import resolve
from lipmap.imageio import atomic_path

from .. import hloc_io
from ..hloc_io import h5_update, list_h5_names


@dataclass
class RetrievalConfig:
    method: str = "vlad"  # vlad | bow
    num_words: int = 64  # VLAD: 64 x 128 = 8192-d; BoW wants more words (e.g. 1024)
    num_retrieved: int = 10
    max_train_descriptors: int = 100_000  # random subset of the mapping descriptors for k-means
    power_norm: float = 0.5  # VLAD: signed power normalisation before intra-normalisation (1 = off)
    seed: int = 0

    @property
    def name(self) -> str:
        return f"{self.method}{self.num_words}"

    def __post_init__(self):
        if self.method not in ("vlad", "bow"):
            raise InputError(f"unknown retrieval method {self.method!r}; choose vlad or bow")


confs = {
    "vlad64": RetrievalConfig(),
    "bow1024": RetrievalConfig(method="bow", num_words=1024),
}


def get_conf(conf=None) -> RetrievalConfig:
    """A :class:`RetrievalConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "retrieval", default="vlad64")


def _descriptors(features_h5, name: str) -> np.ndarray:
    d = hloc_io.read_features(features_h5, name)["descriptors"]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def train_codebook(features_h5, names: Sequence[str], conf: Optional[RetrievalConfig] = None) -> dict:
    """k-means visual words over a seeded random subset of the descriptors of ``names``.

    Returns:
        dict with **centers** (K, D) float32 and, for BoW, **idf** (K,) from the same images.
    """
    from sklearn.cluster import MiniBatchKMeans

    conf = conf or RetrievalConfig()
    rng = np.random.default_rng(conf.seed)
    per_image = max(1, conf.max_train_descriptors // max(1, len(names)))
    chunks = []
    for n in names:
        d = _descriptors(features_h5, n)
        if len(d) > per_image:
            d = d[np.sort(rng.choice(len(d), per_image, replace=False))]
        chunks.append(d)
    X = np.concatenate(chunks).astype(np.float32)
    if len(X) < conf.num_words:
        raise InputError(
            f"only {len(X)} descriptors in {len(names)} mapping images for {conf.num_words} visual words", features_h5
        )
    km = MiniBatchKMeans(n_clusters=conf.num_words, random_state=conf.seed, batch_size=4096, n_init=3, max_iter=100)
    km.fit(X)
    out = {"centers": km.cluster_centers_.astype(np.float32)}
    if conf.method == "bow":
        df = np.zeros(conf.num_words)
        for n in names:
            df[np.unique(_assign(_descriptors(features_h5, n), out["centers"]))] += 1
        out["idf"] = np.log((1 + len(names)) / (1 + df)).astype(np.float32)
    logger.info("Trained a %d-word codebook on %d descriptors of %d images.", conf.num_words, len(X), len(names))
    return out


def _assign(desc: np.ndarray, centers: np.ndarray) -> np.ndarray:
    d2 = (desc**2).sum(1)[:, None] - 2 * desc @ centers.T + (centers**2).sum(1)[None]
    return d2.argmin(1)


def global_descriptor(desc: np.ndarray, codebook: dict, conf: Optional[RetrievalConfig] = None) -> np.ndarray:
    """One unit-norm global descriptor from local descriptors.

    Args:
        desc: (N, D) local descriptors; codebook: from :func:`train_codebook`.

    Returns:
        (K * D,) for VLAD (residuals summed per word, power- and intra-normalised, then L2), or
        (K,) for BoW (tf-idf, L2).
    """
    conf = conf or RetrievalConfig()
    centers = codebook["centers"]
    K, D = centers.shape
    if len(desc) == 0:
        return np.zeros(K * D if conf.method == "vlad" else K, np.float32)
    a = _assign(desc.astype(np.float32), centers)
    if conf.method == "bow":
        g = np.bincount(a, minlength=K).astype(np.float32) / len(desc) * codebook["idf"]
    else:
        v = np.zeros((K, D), np.float32)
        np.add.at(v, a, desc - centers[a])
        v = np.sign(v) * np.abs(v) ** conf.power_norm
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)  # intra-normalisation
        g = v.reshape(-1)
    return (g / max(np.linalg.norm(g), 1e-12)).astype(np.float32)


def _names_digest(names: Sequence[str]) -> str:
    return hashlib.sha1("\n".join(sorted(names)).encode()).hexdigest()[:12]


def load_or_train_codebook(features_h5, db_names: Sequence[str], path, conf: RetrievalConfig, overwrite: bool = False) -> dict:
    """The codebook cached at ``path`` (.npz) if it was trained on the same images and settings."""
    path = Path(path)
    key = f"{conf.name}-seed{conf.seed}-n{conf.max_train_descriptors}-{_names_digest(db_names)}"
    if path.exists() and not overwrite:
        with np.load(path) as z:
            if str(z["key"]) == key:
                return {k: z[k] for k in z.files if k != "key"}
        logger.info("Codebook %s was trained on other images or settings: retraining.", path.name)
    cb = train_codebook(features_h5, db_names, conf)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, key=np.array(key), **cb)
    return cb


def extract_global(features_h5, names: Sequence[str], out_h5, codebook: dict, conf: RetrievalConfig, overwrite: bool = False) -> Path:
    """Global descriptors of ``names`` into ``out_h5`` (hloc layout: ``<name>/global_descriptor``)."""
    out_h5 = Path(out_h5)
    done = set() if overwrite or not out_h5.exists() else set(list_h5_names(out_h5))
    todo = [n for n in names if n not in done]
    if not todo:
        return out_h5
    with h5_update(out_h5, fresh=overwrite) as fd:
        fd.attrs["conf"] = conf.name
        for n in tqdm(todo, desc="global", disable=len(todo) < 50):
            g = global_descriptor(_descriptors(features_h5, n), codebook, conf)
            if n in fd:
                del fd[n]
            fd.create_group(n).create_dataset("global_descriptor", data=g)
    return out_h5


def read_global(path, names: Sequence[str]) -> np.ndarray:
    """(len(names), G) global descriptors from an hloc global-features file (ours or NetVLAD's)."""
    with hloc_io.open_h5(path) as fd:
        out = []
        for n in names:
            if n not in fd or "global_descriptor" not in fd[n]:
                raise InputError(f"image {n!r} has no global_descriptor", path)
            out.append(np.asarray(fd[n]["global_descriptor"][()], dtype=np.float32).reshape(-1))
    return np.stack(out)


def top_k(query_desc: np.ndarray, db_desc: np.ndarray, k: int, block: int = 256) -> np.ndarray:
    """(Q, min(k, N)) indices of the most similar database descriptors, best first (ties: lower index).

    Queries go ``block`` at a time (memory ~ block x N similarities) and each row is only partly
    sorted: every score >= the row's k-th best (ties included) is ranked, the rest never.
    """
    n = db_desc.shape[0]
    k = min(k, n)
    out = np.zeros((len(query_desc), k), np.int64)
    if k == 0:
        return out
    for start in range(0, len(query_desc), block):
        sim = query_desc[start : start + block] @ db_desc.T
        kth = np.partition(sim, n - k, axis=1)[:, n - k]  # the k-th largest of each row
        rows, cols = np.nonzero(sim >= kth[:, None])
        vals = sim[rows, cols]
        order = np.lexsort((cols, -vals, rows))
        rows, cols = rows[order], cols[order]
        rank = np.arange(len(rows)) - np.searchsorted(rows, rows, side="left")
        keep = rank < k
        out[start + rows[keep], rank[keep]] = cols[keep]
    return out


def _top_k_full_sort(query_desc: np.ndarray, db_desc: np.ndarray, k: int) -> np.ndarray:
    """The former :func:`top_k` (a full Q x N sort): the reference in tests and benchmarks."""
    sim = query_desc @ db_desc.T
    order = np.lexsort((np.broadcast_to(np.arange(sim.shape[1]), sim.shape), -sim), axis=1)
    return order[:, : min(k, sim.shape[1])]


def pairs_from_retrieval(
    query_names: Sequence[str],
    db_names: Sequence[str],
    features_h5,
    out_pairs,
    conf: Optional[RetrievalConfig] = None,
    global_h5=None,
    overwrite: bool = False,
    block: int = 256,
) -> Path:
    """Pair each query with its ``num_retrieved`` most similar database images; hloc pairs file.

    The codebook is trained on ``db_names`` only (cached beside ``out_pairs``); global descriptors
    go to ``global_h5`` (default ``global-<method><K>.h5`` beside ``out_pairs``).
    """
    conf = conf or RetrievalConfig()
    out_pairs = Path(out_pairs)
    stamp = Stamp("pairs-retrieval", {"retrieval": asdict(conf), "features": Path(features_h5).name,
                                      "queries": _names_digest(query_names), "db": _names_digest(db_names)})
    if reuse(out_pairs, stamp, overwrite, "retrieval", replace_stale=True):
        return out_pairs
    if not db_names:
        raise InputError("retrieval needs at least one database image", features_h5)
    hloc_io.check_pairs_in_features([(q, q) for q in query_names] + [(d, d) for d in db_names], features_h5)
    # the words depend on the local features: name the cached codebook / descriptors after them
    tag = f"{conf.name}_{Path(features_h5).stem}"
    global_h5 = Path(global_h5) if global_h5 else out_pairs.parent / f"global-{tag}.h5"
    codebook = load_or_train_codebook(features_h5, db_names, out_pairs.parent / f"codebook-{tag}.npz", conf, overwrite)
    # a new codebook invalidates stored global descriptors
    extract_global(features_h5, list(db_names) + list(query_names), global_h5, codebook, conf, overwrite=True)
    dd = read_global(global_h5, db_names)
    pairs, per_query = [], 0
    for start in range(0, len(query_names), block):  # queries in blocks: memory ~ database + block x N
        qn = list(query_names[start : start + block])
        idx = top_k(read_global(global_h5, qn), dd, conf.num_retrieved, block)
        pairs += [(q, db_names[j]) for q, row in zip(qn, idx) for j in row]
        per_query = idx.shape[1]
    hloc_io.write_pairs(out_pairs, pairs)
    write_stamp(out_pairs, stamp)
    logger.info("Retrieved %d database images for each of %d queries.", per_query, len(query_names))
    return out_pairs


def pose_distance(cam_from_world_a: np.ndarray, cam_from_world_b: np.ndarray, m_per_deg: float = 0.01) -> float:
    """Camera-centre distance (m) + ``m_per_deg`` x rotation angle (deg): 1 deg counts as 1 cm."""
    from lipmap.poses import pose_errors

    dt, dr = pose_errors(cam_from_world_a, cam_from_world_b)
    return dt + m_per_deg * dr


def retrieval_recall(pairs, query_poses: dict, db_poses: dict, ks: Sequence[int] = (1, 5, 10)) -> dict:
    """How often the pose-nearest database image (:func:`pose_distance`) is among the top-k retrieved.

    Args:
        pairs: pairs file or list of (query, db) in rank order; query_poses / db_poses: name -> 4x4.

    Returns:
        {"recall@k": fraction of queries, ...} and ``per_query`` {name: rank of the nearest (1-based)
        or None}.
    """
    pairs = hloc_io.read_pairs(pairs) if isinstance(pairs, (str, Path)) else list(pairs)
    ranked = hloc_io.pairs_by_query(pairs)
    db_names = list(db_poses)
    per_query = {}
    for q, T in query_poses.items():
        dists = [pose_distance(T, db_poses[n]) for n in db_names]
        nearest = db_names[int(np.argmin(dists))]
        got = ranked.get(q, [])
        per_query[q] = got.index(nearest) + 1 if nearest in got else None
    out = {f"recall@{k}": float(np.mean([r is not None and r <= k for r in per_query.values()])) for k in ks}
    out["per_query"] = per_query
    return out
