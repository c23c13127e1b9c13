"""The point pipeline at scale: parallel SIFT, grouped matching, pruned pairs from poses and
bounded retrieval give today's outputs (the sequential / dense versions are the references)."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from lipmap.artifacts import STAMP_ATTR
from lipmap.errors import InputError
from lipmap.imageio import write_color
from lipmap.scene import Camera, View
from localization import hloc_io, points
from localization.points import features as pfeatures, matching as pmatching, pairs as ppairs
from localization.points import SiftConfig, extract_sift


def texture_views(tmp_path, n, size=(160, 120), seed=0):
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n):
        img = rng.integers(0, 256, (size[1] // 8, size[0] // 8, 1)).astype(np.uint8)
        img = np.kron(img, np.ones((8, 8, 3), np.uint8))  # blocky: plenty of SIFT corners
        path = tmp_path / f"im{i:03d}.png"
        write_color(path, img)
        cam = Camera(size[0], size[1], (150.0, 150.0, size[0] / 2, size[1] / 2))
        views.append(View(name=f"seq/im{i:03d}.png", camera=cam, cam_from_world=np.eye(4), color_path=path))
    return views


def h5_contents(path):
    out = {}
    with h5py.File(path, "r") as fd:
        fd.visititems(lambda k, d: out.__setitem__(k, d[()]) if isinstance(d, h5py.Dataset) else None)
        names = list(fd)
    return names, out


class TestParallelSift:
    def test_processes_equal_sequential(self, tmp_path):
        """Worker processes write the same datasets, byte for byte, in the same order as one process."""
        views = texture_views(tmp_path, 7)
        conf = SiftConfig(max_keypoints=300, first_octave=0)
        seq = extract_sift(views, tmp_path / "seq.h5", conf, chunk=2, workers=1, device="cpu")
        par = extract_sift(views, tmp_path / "par.h5", conf, chunk=2, workers=2, device="cpu")
        (n0, d0), (n1, d1) = h5_contents(seq), h5_contents(par)
        assert n0 == n1
        assert d0.keys() == d1.keys() and len(d0) >= 7 * 5
        for k in d0:
            np.testing.assert_array_equal(d0[k], d1[k], err_msg=k)
        with h5py.File(seq, "r") as a, h5py.File(par, "r") as b:
            assert list(a["seq"]) == list(b["seq"])  # creation order kept
            assert a.attrs[STAMP_ATTR] == b.attrs[STAMP_ATTR]
        for v in views:  # and both equal SIFT on each image alone (the former loop)
            f = points.sift_features(v.load_color(gray=True), conf)
            np.testing.assert_array_equal(d1[f"{v.name}/descriptors"], f["descriptors"].astype(np.float16).T)
            np.testing.assert_array_equal(d1[f"{v.name}/keypoints"], (f["keypoints"] - 0.5).astype(np.float32))

    def test_device_selection(self, monkeypatch):
        import pycolmap

        assert pfeatures.sift_device("cpu") == "cpu"
        monkeypatch.setattr(pycolmap, "has_cuda", False, raising=False)
        assert pfeatures.sift_device("auto") == "cpu"
        with pytest.raises(InputError):
            pfeatures.sift_device("cuda")
        with pytest.raises(InputError):
            pfeatures.sift_device("tpu")
        monkeypatch.setattr(pycolmap, "has_cuda", True, raising=False)
        monkeypatch.setattr(pycolmap, "get_num_cuda_devices", lambda: 1, raising=False)
        assert pfeatures.sift_device("auto") == "cuda"
        monkeypatch.setattr(pycolmap, "get_num_cuda_devices", lambda: 0, raising=False)
        assert pfeatures.sift_device("auto") == "cpu"

    def test_cuda_extractor_requested(self, tmp_path, monkeypatch):
        """On a CUDA pycolmap the extractor is created on Device.cuda and the stamp names the device."""
        made = []
        real = pfeatures._sift_extractor

        def fake(conf, device="cpu"):
            made.append(device)
            return real(conf, "cpu")

        monkeypatch.setattr(pfeatures, "_sift_extractor", fake)
        monkeypatch.setattr(pfeatures, "sift_device", lambda device="auto": "cuda")
        views = texture_views(tmp_path, 2)
        out = extract_sift(views, tmp_path / "f.h5", SiftConfig(max_keypoints=100, first_octave=0))
        assert made == ["cuda"]
        with h5py.File(out, "r") as fd:
            assert "cuda" in fd.attrs[STAMP_ATTR]


def trajectory_views(n, seed=0, length=60.0, cam=Camera(640, 480, (525.0, 525.0, 320.0, 240.0))):
    """Posed views only (no images): a walk along a winding corridor, looking around as it goes
    (yaw wanders, pitch a little), with returns past earlier places."""
    from scipy.spatial.transform import Rotation

    from lipmap.poses import make_T

    rng = np.random.default_rng(seed)
    s = np.linspace(0, 1, n)
    centres = np.stack([length * s, 3 * np.sin(6 * np.pi * s), 1.5 + 0.2 * np.sin(20 * s)], 1)
    centres += rng.normal(0, 0.05, centres.shape)
    yaw = np.cumsum(rng.normal(0, 0.25, n))
    pitch = rng.normal(0, 0.15, n)
    views = []
    for i in range(n):
        # camera looks along +z of its frame; world_from_cam rotation: yaw about world z, pitch about x
        R_wc = Rotation.from_euler("zx", [yaw[i], -np.pi / 2 + pitch[i]]).as_matrix()
        T_wc = make_T(R_wc, centres[i])
        views.append(View(name=f"seq/f{i:05d}.png", camera=cam, cam_from_world=np.linalg.inv(T_wc),
                          color_path=f"/nonexistent/f{i:05d}.png"))
    return views


class TestPairsFromPoses:
    @pytest.mark.parametrize("n,length,conf", [
        (320, 60.0, points.PairsConfig()),
        (150, 6.0, points.PairsConfig()),  # a small room: almost every pair is a candidate
        (120, 20.0, points.PairsConfig(num_neighbors=4, max_angle_deg=90, min_overlap=0.05, depths=(0.5, 6.0))),
        (60, 20.0, points.PairsConfig(min_overlap=0.0)),  # no overlap pruning possible
    ])
    def test_equals_dense(self, n, length, conf):
        views = trajectory_views(n, seed=n, length=length)
        got = points.pairs_from_poses(views, conf=conf)
        ref = ppairs._pairs_from_poses_dense(views, conf)
        assert len(ref) > n
        assert got == ref

    def test_candidates_bounded_on_a_long_walk(self):
        """On a 300 m walk the exact test runs on ~N x (views within reach), not N^2 pairs."""
        views = trajectory_views(1500, length=300.0)
        conf = points.PairsConfig()
        n_cand = sum(len(I) for I, _ in ppairs._candidate_pairs(views, ppairs._view_samples(views, conf), conf))
        assert n_cand < 1500 * 1499 / 2 / 10, n_cand
        # the candidates hold every pair the exact test keeps, on a window checked densely
        sub = views[:300]
        assert points.pairs_from_poses(sub, conf=conf) == ppairs._pairs_from_poses_dense(sub, conf)


class TestMatching:
    def test_grouped_matching_equals_per_pair(self, tmp_path, monkeypatch):
        """Scattered pairs (shuffled, both orientations) give each pair the matches of matching it
        alone, and with a small cache each image is read at most once per block pair."""
        views = texture_views(tmp_path, 12, seed=3)
        feats = extract_sift(views, tmp_path / "f.h5", SiftConfig(max_keypoints=200, first_octave=0), workers=1)
        rng = np.random.default_rng(0)
        names = [v.name for v in views]
        pairs = [(names[i], names[j]) if rng.random() < 0.5 else (names[j], names[i])
                 for i in range(12) for j in range(i + 1, 12) if rng.random() < 0.6]
        pairs = [pairs[k] for k in rng.permutation(len(pairs))]
        reads = []
        real = hloc_io.read_features
        monkeypatch.setattr(hloc_io, "read_features", lambda p, n: reads.append(n) or real(p, n))
        out = points.match_features(pairs, feats, tmp_path / "m.h5", chunk=5, block=3)
        n_blocks = 4
        assert max(reads.count(n) for n in names) <= 2 * n_blocks
        assert len(reads) < len(pairs)  # the former FIFO-in-pair-order reads ~2 per pair at this cache size
        for a, b in pairs:
            m, s = hloc_io_matches(out, a, b)
            da, db = (pmatching._DescriptorCache(feats)(n) for n in (a, b))
            m_ref, s_ref = points.mutual_nn_ratio(da, db)
            np.testing.assert_array_equal(m, m_ref)
            np.testing.assert_array_equal(s, s_ref)

    def test_cache_bounded(self, tmp_path):
        views = texture_views(tmp_path, 5, seed=1)
        feats = extract_sift(views, tmp_path / "f.h5", SiftConfig(max_keypoints=200, first_octave=0), workers=1)
        cache = pmatching._DescriptorCache(feats, max_items=3, max_bytes=10**9)
        for v in views + views[::-1]:
            cache(v.name)
            assert len(cache.items) <= 3
        assert cache.reads == 5 + 2  # the last three read are still there on the way back
        one = cache(views[0].name).nbytes
        small = pmatching._DescriptorCache(feats, max_items=100, max_bytes=int(2.5 * one))
        for v in views:
            small(v.name)
        assert small.nbytes <= 2.5 * one and len(small.items) <= 2


def hloc_io_matches(path, a, b):
    import h5py

    from localization.hloc_io import names_to_pair

    with h5py.File(path, "r") as fd:
        g = fd[names_to_pair(a, b)]
        return g["matches0"][()], g["matching_scores0"][()]


class TestRetrieval:
    @pytest.mark.parametrize("k,block", [(1, 7), (10, 16), (50, 1000), (200, 5)])
    def test_blocked_top_k_equals_full_sort(self, k, block):
        """Blocked partial ranking = the former full sort, ties included. Small integer descriptors
        make every similarity exact: a block's matmul may round differently from the full one's,
        which can swap scores within an ulp of each other on real descriptors."""
        from localization.points.retrieval import _top_k_full_sort, top_k

        rng = np.random.default_rng(k)
        q = rng.integers(-3, 4, size=(53, 8)).astype(np.float32)
        d = rng.integers(-3, 4, size=(120, 8)).astype(np.float32)
        d[40:60] = d[0]  # many exact ties
        np.testing.assert_array_equal(top_k(q, d, k, block=block), _top_k_full_sort(q, d, k))


def test_commit_batches_cover_the_items_and_copy_linear_bytes():
    from lipmap.imageio import commit_batches

    assert commit_batches(0) == []
    assert commit_batches(40, 0, 16) == [(0, 16), (16, 32), (32, 40)]
    b = commit_batches(7000, 0, 16)
    assert b[0] == (0, 16) and b[-1][1] == 7000 and all(s1 == e0 for (_, e0), (s1, _) in zip(b, b[1:]))
    copied = sum(e for _, e in b)  # each commit copies the file as it is after it
    assert copied <= 6 * 7000 and len(b) < 40
    # resuming into a file that holds 4,000 items starts with batches of 1,000
    assert commit_batches(3000, 4000, 16)[0] == (0, 1000)
