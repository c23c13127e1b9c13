"""Retrieval without downloaded weights: VLAD / BoW descriptors, top-k pairs, recall on real frames."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from lipmap.errors import InputError
from lipmap.poses import make_T
from localization import hloc_io
from localization.points.retrieval import (
    RetrievalConfig,
    global_descriptor,
    pairs_from_retrieval,
    pose_distance,
    retrieval_recall,
    top_k,
    train_codebook,
)


def _features(tmp_path, n_db=6, n_words=8, seed=0):
    """Each db image draws descriptors from its own subset of word centres; query i = noisy db i."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(n_words * 3, 32))
    db, q = {}, {}
    for i in range(n_db):
        words = rng.choice(len(centers), 5, replace=False)
        base = centers[rng.choice(words, 200)]
        db[f"db/{i:02d}.png"] = base + rng.normal(0, 0.1, base.shape)
        q[f"q/{i:02d}.png"] = base[:150] + rng.normal(0, 0.1, (150, 32))
    path = tmp_path / "feats.h5"
    with h5py.File(path, "w") as fd:
        for name, d in {**db, **q}.items():
            hloc_io.write_features(fd, name, rng.uniform(0, 100, (len(d), 2)), d)
    return path, sorted(db), sorted(q)


class TestGlobalDescriptor:
    @pytest.mark.parametrize("method", ["vlad", "bow"])
    def test_shapes_and_norm(self, tmp_path, method):
        feats, db, _ = _features(tmp_path)
        conf = RetrievalConfig(method=method, num_words=8)
        cb = train_codebook(feats, db, conf)
        assert cb["centers"].shape == (8, 32)
        d = hloc_io.read_features(feats, db[0])["descriptors"]
        g = global_descriptor(d, cb, conf)
        assert g.shape == ((8 * 32,) if method == "vlad" else (8,))
        assert abs(np.linalg.norm(g) - 1) < 1e-5
        np.testing.assert_array_equal(g, global_descriptor(d, cb, conf))
        assert np.all(global_descriptor(d[:0], cb, conf) == 0)

    def test_codebook_seeded(self, tmp_path):
        feats, db, _ = _features(tmp_path)
        a = train_codebook(feats, db, RetrievalConfig(num_words=8, seed=3))["centers"]
        b = train_codebook(feats, db, RetrievalConfig(num_words=8, seed=3))["centers"]
        np.testing.assert_array_equal(a, b)

    def test_too_few_descriptors(self, tmp_path):
        feats, db, _ = _features(tmp_path)
        with pytest.raises(InputError, match="visual words"):
            train_codebook(feats, db[:1], RetrievalConfig(num_words=500))


def test_top_k_order_and_ties():
    q = np.array([[1.0, 0.0]])
    d = np.array([[0.0, 1.0], [1.0, 0.0], [1.0, 0.0], [0.6, 0.8]])
    assert top_k(q, d, 3).tolist() == [[1, 2, 3]]
    assert top_k(q, d, 10).shape == (1, 4)


@pytest.mark.parametrize("method", ["vlad", "bow"])
def test_pairs_from_retrieval(tmp_path, method):
    feats, db, q = _features(tmp_path)
    conf = RetrievalConfig(method=method, num_words=8, num_retrieved=3)
    out = pairs_from_retrieval(q, db, feats, tmp_path / "pairs.txt", conf)
    pairs = hloc_io.read_pairs(out)
    ranked = hloc_io.pairs_by_query(pairs)
    assert len(pairs) == 3 * len(q) and set(ranked) == set(q)
    for name in q:  # the source image comes first
        assert ranked[name][0] == name.replace("q/", "db/")
        assert all(r in db for r in ranked[name])
    # cached: not recomputed; overwrite recomputes the same (seeded)
    mtime = out.stat().st_mtime_ns
    pairs_from_retrieval(q, db, feats, out, conf)
    assert out.stat().st_mtime_ns == mtime
    text = out.read_text()
    pairs_from_retrieval(q, db, feats, out, conf, overwrite=True)
    assert out.read_text() == text
    tag = f"{conf.name}_{feats.stem}"
    assert (tmp_path / f"global-{tag}.h5").exists() and (tmp_path / f"codebook-{tag}.npz").exists()
    # other queries: not the cached pairs
    pairs_from_retrieval(q[:2], db, feats, out, conf)
    assert set(hloc_io.pairs_by_query(hloc_io.read_pairs(out))) == set(q[:2])


def test_retrieval_missing_image(tmp_path):
    feats, db, q = _features(tmp_path)
    with pytest.raises(InputError) as e:
        pairs_from_retrieval(q + ["q/missing.png"], db, feats, tmp_path / "pairs.txt", RetrievalConfig(num_words=8))
    assert "q/missing.png" in str(e.value) and str(feats) in str(e.value)


def test_retrieval_recall_counts():
    def T(x, yaw=0.0):
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        return make_T(R, -R @ np.array([x, 0, 0]))

    db = {"a": T(0.0), "b": T(1.0), "c": T(2.0)}
    qs = {"q1": T(0.1), "q2": T(1.9)}
    pairs = [("q1", "b"), ("q1", "a"), ("q2", "a"), ("q2", "b")]
    r = retrieval_recall(pairs, qs, db, ks=(1, 2))
    assert r["per_query"] == {"q1": 2, "q2": None}
    assert r["recall@1"] == 0.0 and r["recall@2"] == 0.5
    assert pose_distance(T(0), T(0.05)) == pytest.approx(0.05)
    assert pose_distance(T(0), T(0, np.radians(2))) == pytest.approx(0.02)


def test_redkitchen_recall(redkitchen_root, tmp_path):
    """VLAD over SIFT on real frames: the pose-nearest mapping frame is among the top 5."""
    from lipmap.datasets import load_scene
    from localization.points import SiftConfig, extract_sift

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    mapping = scene.mapping[::2]
    queries = scene.query[::10]
    feats = extract_sift(mapping + queries, tmp_path / "feats.h5", SiftConfig(max_keypoints=1024, first_octave=0))
    conf = RetrievalConfig(num_words=32, num_retrieved=5)
    pairs = pairs_from_retrieval([v.name for v in queries], [v.name for v in mapping], feats, tmp_path / "p.txt", conf)
    r = retrieval_recall(pairs, {v.name: v.cam_from_world for v in queries}, {v.name: v.cam_from_world for v in mapping})
    assert r["recall@5"] >= 0.8, r
