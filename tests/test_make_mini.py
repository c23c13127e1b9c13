"""The cut of the RedKitchen minis from a full 7-Scenes download (benchmarks/7scenes/make_mini.py).

A fake full download is built from the shared mini's own frames (original RedKitchen seq-01 frames 0, 5, ... 495,
spread over the mini's seq-01 and seq-02): colour as PNG, depth as is, poses in the official layout, the published
pseudo-GT lists with the frames under their original seq-01 names among other lines. The cut must give back the
shared mini: its file names, split files and pseudo-GT lists byte for byte, its depth maps and poses, and JPEGs of
the same size and quantization tables (JPEG bytes may differ: the encoder's version).
"""
from __future__ import annotations

import os
import re
import shutil

import cv2
import numpy as np
import pytest
from PIL import Image

from lipmap.datasets import load_scene

from conftest import benchmark_module

pytestmark = pytest.mark.shared

def _module():
    return benchmark_module("7scenes/make_mini.py")


def _official_pose(T: np.ndarray) -> str:
    """7-Scenes' own layout: 8 significant digits, 3-digit exponents, tab-separated, CRLF."""
    fmt = lambda v: re.sub(r"e([+-])(\d\d)$", r"e\g<1>0\2", f"{v: .7e}")  # noqa: E731
    return "".join("\t".join(fmt(v) for v in row) + "\t\r\n" for row in T)


@pytest.fixture(scope="module")
def full_download(redkitchen_root, tmp_path_factory):
    """DATA/redkitchen/seq-01 (frames 0, 5, ... 495 plus two others) and DATA/pgt in the published layout."""
    data = tmp_path_factory.mktemp("full")
    mini = redkitchen_root / "redkitchen"
    seq = data / "redkitchen" / "seq-01"
    seq.mkdir(parents=True)
    (data / "redkitchen" / "TrainSplit.txt").write_bytes(b"sequence1\r\nsequence2\r\nsequence5\r\n")
    (data / "redkitchen" / "TestSplit.txt").write_bytes(b"sequence3\r\nsequence4\r\n")
    for src in sorted(mini.glob("seq-0[12]/frame-*.pose.txt")):
        stem = src.name[: -len(".pose.txt")]
        img = cv2.imread(str(src.parent / f"{stem}.color.jpg"))
        cv2.imwrite(str(seq / f"{stem}.color.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        shutil.copyfile(src.parent / f"{stem}.depth.png", seq / f"{stem}.depth.png")
        (seq / f"{stem}.pose.txt").write_text(_official_pose(np.loadtxt(src)), newline="")
    for extra in ("frame-000001", "frame-000002"):  # frames the cut must leave out
        for kind in ("color.png", "depth.png", "pose.txt"):
            shutil.copyfile(seq / f"frame-000000.{kind}", seq / f"{extra}.{kind}")
    rng = np.random.default_rng(0)
    for src in ("dslam", "sfm"):
        published = (mini / "pgt" / f"{src}_redkitchen.txt").read_text().splitlines()
        lines = [re.sub(r"^seq-02/", "seq-01/", ln) for ln in published]
        lines += [f"seq-02/frame-{i:06d}.color.png 1 0 0 0 0.{i} 0 0 525.0" for i in range(0, 500, 5)]
        folder = data / "pgt" / src / "7scenes"
        folder.mkdir(parents=True)
        (folder / "redkitchen_train.txt").write_text("\n".join(rng.permutation(lines)) + "\n")
        (folder / "redkitchen_test.txt").write_text("seq-03/frame-000000.color.png 1 0 0 0 0 0 0 525.0\n")
    shutil.copyfile(redkitchen_root / "LICENSE.visloc_pseudo_gt_limitations.BSD3", data / "pgt" / "LICENSE")
    shutil.copyfile(redkitchen_root / "LICENSE-7scenes-data.rtf", data / "LICENSE-7scenes-data.rtf")
    return data


@pytest.mark.slow
def test_the_cut_gives_back_the_shared_minis(full_download, redkitchen_root, tmp_path):
    out = tmp_path / "mini"
    _module().main(["--root", str(full_download), "--out", str(out)])
    for name in ("LICENSE-7scenes-data.rtf", "LICENSE.visloc_pseudo_gt_limitations.BSD3"):
        assert (out / name).read_bytes() == (redkitchen_root / name).read_bytes()
    for mini in ("redkitchen", "redkitchen-sparse"):
        ref, cut = redkitchen_root / mini, out / mini
        files = lambda d: sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())  # noqa: E731
        assert files(cut) == files(ref)
        for same in ("TrainSplit.txt", "TestSplit.txt", f"pgt/dslam_{mini}.txt", f"pgt/sfm_{mini}.txt"):
            assert (cut / same).read_bytes() == (ref / same).read_bytes(), same
        diffs = []
        for p in sorted(ref.glob("seq-0*/frame-*.pose.txt")):
            stem = str(p.relative_to(ref))[: -len(".pose.txt")]
            assert np.allclose(np.loadtxt(cut / f"{stem}.pose.txt"), np.loadtxt(p), rtol=0, atol=1e-7), stem
            assert (cut / f"{stem}.depth.png").read_bytes() == (ref / f"{stem}.depth.png").read_bytes(), stem
            a, b = Image.open(cut / f"{stem}.color.jpg"), Image.open(ref / f"{stem}.color.jpg")
            assert a.size == b.size == (640, 480) and a.quantization == b.quantization, stem
            diffs.append(np.abs(np.asarray(a, float) - np.asarray(b, float)).mean())
        # re-encoding the decoded JPEG at the same quality moves pixels by a fraction of a grey level
        assert max(diffs) < 1.0, max(diffs)
        s, r = (load_scene("7scenes", d, mini, pose_source="sfm") for d in (out, redkitchen_root))
        assert [v.name for v in s.mapping + s.query] == [v.name for v in r.mapping + r.query]
        assert all(np.array_equal(v.cam_from_world, w.cam_from_world) for v, w in zip(s.query, r.query))


def test_a_missing_frame_or_pseudo_gt_names_the_file(full_download, tmp_path):
    from lipmap import InputError

    mod = _module()
    broken = tmp_path / "data"
    shutil.copytree(full_download, broken, copy_function=os.symlink)
    (broken / "redkitchen" / "seq-01" / "frame-000005.depth.png").unlink()
    with pytest.raises(InputError, match="frame-000005.depth.png"):
        mod.make_mini(broken, tmp_path / "out", "redkitchen")
    with pytest.raises(InputError, match=r"nowhere/dslam/7scenes/redkitchen_train.txt"):
        mod.make_mini(full_download, tmp_path / "out", "redkitchen", pgt_dir=tmp_path / "nowhere")
