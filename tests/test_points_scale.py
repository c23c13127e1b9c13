"""The point pipeline at scale: parallel SIFT, grouped matching, pruned pairs from poses and
bounded retrieval give today's outputs (the sequential / dense versions are the references)."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from lipmap.imageio import write_color
from lipmap.scene import Camera, View
from localization import points
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
            assert a.attrs[points.STAMP_ATTR] == b.attrs[points.STAMP_ATTR]
        for v in views:  # and both equal SIFT on each image alone (the former loop)
            f = points.sift_features(v.load_color(gray=True), conf)
            np.testing.assert_array_equal(d1[f"{v.name}/descriptors"], f["descriptors"].astype(np.float16).T)
            np.testing.assert_array_equal(d1[f"{v.name}/keypoints"], (f["keypoints"] - 0.5).astype(np.float32))

    def test_device_selection(self, monkeypatch):
        import pycolmap

        assert points.sift_device("cpu") == "cpu"
        monkeypatch.setattr(pycolmap, "has_cuda", False, raising=False)
        assert points.sift_device("auto") == "cpu"
        with pytest.raises(points.InputError):
            points.sift_device("cuda")
        with pytest.raises(points.InputError):
            points.sift_device("tpu")
        monkeypatch.setattr(pycolmap, "has_cuda", True, raising=False)
        monkeypatch.setattr(pycolmap, "get_num_cuda_devices", lambda: 1, raising=False)
        assert points.sift_device("auto") == "cuda"
        monkeypatch.setattr(pycolmap, "get_num_cuda_devices", lambda: 0, raising=False)
        assert points.sift_device("auto") == "cpu"

    def test_cuda_extractor_requested(self, tmp_path, monkeypatch):
        """On a CUDA pycolmap the extractor is created on Device.cuda and the stamp names the device."""
        made = []
        real = points._sift_extractor

        def fake(conf, device="cpu"):
            made.append(device)
            return real(conf, "cpu")

        monkeypatch.setattr(points, "_sift_extractor", fake)
        monkeypatch.setattr(points, "sift_device", lambda device="auto": "cuda")
        views = texture_views(tmp_path, 2)
        out = extract_sift(views, tmp_path / "f.h5", SiftConfig(max_keypoints=100, first_octave=0))
        assert made == ["cuda"]
        with h5py.File(out, "r") as fd:
            assert "cuda" in fd.attrs[points.STAMP_ATTR]
