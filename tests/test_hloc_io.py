"""hloc interchange: files written here with h5py exactly as hloc writes them (float16, the 0.5 px
origin, nested image groups, int16 matches, both pair namings) must read back right."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from lipmap.errors import InputError
from lipmap.poses import T_from_qt, pose_errors
from localization import hloc_io
from localization.points import point_matches_from_hloc
from localization.hloc_io import (
    ModelIndex,
    check_pairs_in_features,
    find_pair,
    names_to_pair,
    names_to_pair_old,
    read_features,
    read_keypoints,
    read_matches,
    read_pairs,
    read_results,
    write_pairs,
    write_results,
)

Q = "seq-02/frame-000005.color.png"
DB = ["seq-01/frame-000000.color.png", "seq-01/frame-000010.color.png"]


def hloc_write_features(path, name, kp_hloc, desc_DN, as_half=True, uncertainty=1.0, size=(640, 480)):
    """hloc extract_features.main's writer: as_half float16, keypoints in its own (OpenCV) origin."""
    pred = {
        "keypoints": kp_hloc.astype(np.float32),
        "descriptors": desc_DN.astype(np.float32),
        "scores": np.ones(kp_hloc.shape[0], np.float32),
        "image_size": np.array(size),  # original_size from torch: int64 (w, h)
    }
    if as_half:
        for k in pred:
            if pred[k].dtype == np.float32:
                pred[k] = pred[k].astype(np.float16)
    with h5py.File(str(path), "a", libver="latest") as fd:
        if name in fd:
            del fd[name]
        grp = fd.create_group(name)
        for k, v in pred.items():
            grp.create_dataset(k, data=v)
        grp["keypoints"].attrs["uncertainty"] = uncertainty


def hloc_write_matches(path, name0, name1, matches0, scores0, old=False):
    """hloc match_features's writer: int16 matches0, float16 scores; ``old`` = '_'-joined flat group."""
    key = names_to_pair_old(name0, name1) if old else names_to_pair(name0, name1)
    with h5py.File(str(path), "a", libver="latest") as fd:
        grp = fd.create_group(key)
        grp.create_dataset("matches0", data=np.asarray(matches0).astype(np.int16))
        grp.create_dataset("matching_scores0", data=np.asarray(scores0).astype(np.float16))


class TestPairNames:
    def test_names(self):
        assert names_to_pair("a/b.png", "c/d.png") == "a-b.png/c-d.png"
        assert names_to_pair_old("a/b.png", "c/d.png") == "a-b.png_c-d.png"

    def test_find_pair_orders_and_namings(self, tmp_path):
        p = tmp_path / "m.h5"
        hloc_write_matches(p, Q, DB[0], [0, -1], [0.9, 0])
        hloc_write_matches(p, DB[1], Q, [1, -1], [0.9, 0], old=True)
        with h5py.File(p, "r") as fd:
            assert find_pair(fd, Q, DB[0]) == (names_to_pair(Q, DB[0]), False)
            assert find_pair(fd, DB[0], Q) == (names_to_pair(Q, DB[0]), True)
            assert find_pair(fd, Q, DB[1]) == (names_to_pair_old(DB[1], Q), True)
            with pytest.raises(InputError, match="tried groups"):
                find_pair(fd, DB[0], DB[1])


class TestFeatures:
    def test_hloc_float16_layout(self, tmp_path):
        p = tmp_path / "features.h5"
        rng = np.random.default_rng(0)
        kp = rng.uniform(0, 600, (50, 2))
        desc = rng.normal(size=(128, 50))
        hloc_write_features(p, Q, kp, desc, uncertainty=2.0)
        out, unc = read_keypoints(p, Q, return_uncertainty=True)
        assert out.dtype == np.float64 and out.shape == (50, 2)
        # hloc origin -> COLMAP origin: +0.5 on the stored float16 values
        np.testing.assert_array_equal(out, kp.astype(np.float16).astype(np.float64) + 0.5)
        assert unc == 2.0
        f = read_features(p, Q)
        assert f["descriptors"].shape == (50, 128) and f["descriptors"].dtype == np.float32
        np.testing.assert_allclose(f["descriptors"], desc.T.astype(np.float16), rtol=0)
        assert f["image_size"] == (640, 480)
        assert hloc_io.list_h5_names(p) == [Q]  # nested groups: the full relative name

    def test_float32_without_uncertainty(self, tmp_path):
        p = tmp_path / "features.h5"
        kp = np.array([[0.0, 0.0], [639.0, 479.0]])
        hloc_write_features(p, Q, kp, np.eye(2), as_half=False)
        with h5py.File(p, "a") as fd:
            del fd[Q]["keypoints"].attrs["uncertainty"]
        out, unc = read_keypoints(p, Q, return_uncertainty=True)
        np.testing.assert_array_equal(out, [[0.5, 0.5], [639.5, 479.5]])
        assert unc is None

    def test_write_is_hloc_layout(self, tmp_path):
        p = tmp_path / "features.h5"
        kp = np.array([[10.5, 20.5], [0.5, 0.5]])  # COLMAP convention
        with h5py.File(p, "w") as fd:
            hloc_io.write_features(fd, Q, kp, np.ones((2, 4)), scores=[1, 2], image_size=(64, 48), uncertainty=1.0)
        with h5py.File(p, "r") as fd:
            np.testing.assert_array_equal(fd[Q]["keypoints"][()], [[10, 20], [0, 0]])
            assert fd[Q]["descriptors"].shape == (4, 2)
            assert fd[Q]["keypoints"].attrs["uncertainty"] == 1.0
            np.testing.assert_array_equal(fd[Q]["image_size"][()], [64, 48])
        np.testing.assert_array_equal(read_keypoints(p, Q), kp)

    @pytest.mark.parametrize(
        "broken, match",
        [
            ("no_keypoints", "missing dataset 'keypoints'"),
            ("string_keypoints", "numeric dtype"),
            ("bad_shape", r"shape \(N, 2\)"),
            ("desc_mismatch", "descriptors must have shape"),
        ],
    )
    def test_bad_features(self, tmp_path, broken, match):
        p = tmp_path / "features.h5"
        with h5py.File(p, "w") as fd:
            g = fd.create_group(Q)
            if broken == "string_keypoints":
                g.create_dataset("keypoints", data=np.array([b"a", b"b"]))
            elif broken == "bad_shape":
                g.create_dataset("keypoints", data=np.zeros((3, 3), np.float32))
            elif broken == "desc_mismatch":
                g.create_dataset("keypoints", data=np.zeros((3, 2), np.float32))
                g.create_dataset("descriptors", data=np.zeros((128, 4), np.float32))
        with pytest.raises(InputError, match=match) as e:
            read_features(p, Q)
        assert str(p) in str(e.value) and Q in str(e.value)

    def test_missing_image_and_file(self, tmp_path):
        p = tmp_path / "features.h5"
        hloc_write_features(p, Q, np.zeros((2, 2)), np.zeros((4, 2)))
        with pytest.raises(InputError, match="no group") as e:
            read_keypoints(p, DB[0])
        assert str(p) in str(e.value) and DB[0] in str(e.value)
        with pytest.raises(InputError, match="missing"):
            read_keypoints(tmp_path / "nope.h5", Q)
        (tmp_path / "garbage.h5").write_text("not hdf5")
        with pytest.raises(InputError, match="cannot open"):
            read_keypoints(tmp_path / "garbage.h5", Q)


class TestMatches:
    @pytest.mark.parametrize("old", [False, True])
    @pytest.mark.parametrize("stored_reversed", [False, True])
    def test_read(self, tmp_path, old, stored_reversed):
        p = tmp_path / "matches.h5"
        # stored first image has 4 keypoints; keypoint 0 -> 2, 2 -> 0, 3 -> 5
        m0 = [2, -1, 0, 5]
        a, b = (DB[0], Q) if stored_reversed else (Q, DB[0])
        hloc_write_matches(p, a, b, m0, [0.5, 0, 0.25, 1.0], old=old)
        m, s = read_matches(p, Q, DB[0])
        expected = np.array([[0, 2], [2, 0], [3, 5]])
        if stored_reversed:
            expected = expected[:, ::-1]
        np.testing.assert_array_equal(m, expected)
        np.testing.assert_allclose(s, [0.5, 0.25, 1.0])

    def test_float_matches_rejected(self, tmp_path):
        p = tmp_path / "matches.h5"
        with h5py.File(p, "w") as fd:
            fd.create_group(names_to_pair(Q, DB[0])).create_dataset("matches0", data=np.zeros(3, np.float32))
        with pytest.raises(InputError, match="integer dtype") as e:
            read_matches(p, Q, DB[0])
        assert str(p) in str(e.value)

    def test_missing_matches0(self, tmp_path):
        p = tmp_path / "matches.h5"
        with h5py.File(p, "w") as fd:
            fd.create_group(names_to_pair(Q, DB[0])).create_dataset("scores", data=np.zeros(3))
        with pytest.raises(InputError, match="missing dataset 'matches0'"):
            read_matches(p, Q, DB[0])

    def test_writer_layout(self, tmp_path):
        p = tmp_path / "matches.h5"
        with h5py.File(p, "w") as fd:
            hloc_io.write_matches(fd, Q, DB[0], [1, -1], [0.9, 0.0])
        with h5py.File(p, "r") as fd:
            g = fd[Q.replace("/", "-")][DB[0].replace("/", "-")]
            assert g["matches0"].dtype == np.int32
            np.testing.assert_array_equal(g["matches0"][()], [1, -1])


class TestTextFiles:
    def test_pairs_roundtrip(self, tmp_path):
        pairs = [(Q, DB[0]), (Q, DB[1])]
        p = write_pairs(tmp_path / "pairs.txt", pairs)
        assert p.read_text() == f"{Q} {DB[0]}\n{Q} {DB[1]}\n"
        assert read_pairs(p) == pairs

    def test_bad_pairs_line(self, tmp_path):
        p = tmp_path / "pairs.txt"
        p.write_text(f"{Q} {DB[0]}\n{Q}\n")
        with pytest.raises(InputError, match="line 2") as e:
            read_pairs(p)
        assert str(p) in str(e.value)

    def test_pairs_not_in_features(self, tmp_path):
        f = tmp_path / "features.h5"
        hloc_write_features(f, Q, np.zeros((2, 2)), np.zeros((4, 2)))
        p = write_pairs(tmp_path / "pairs.txt", [(Q, DB[0])])
        with pytest.raises(InputError) as e:
            check_pairs_in_features(read_pairs(p), f, p)
        msg = str(e.value)
        assert str(p) in msg and DB[0] in msg and str(f) in msg

    def test_results_roundtrip(self, tmp_path):
        rng = np.random.default_rng(1)
        poses = {}
        for name in (Q, DB[0]):
            q = rng.normal(size=4)
            poses[name] = T_from_qt(q / np.linalg.norm(q), rng.normal(size=3))
        p = write_results(tmp_path / "results.txt", poses)
        line = p.read_text().splitlines()[0].split()
        assert len(line) == 8 and float(line[1]) >= 0  # name qw qx qy qz tx ty tz
        back = read_results(p)
        for name, T in poses.items():
            dt, dr = pose_errors(T, back[name])
            assert dt < 1e-8 and dr < 1e-6
            np.testing.assert_allclose(back[name][:3, 3], T[:3, 3], atol=1e-9)  # t is cam_from_world's

    def test_results_bad(self, tmp_path):
        p = tmp_path / "results.txt"
        p.write_text(f"{Q} 1 0 0 0 0 0\n")
        with pytest.raises(InputError, match="line 1"):
            read_results(p)
        p.write_text(f"{Q} 0 0 0 0 0 0 0\n")
        with pytest.raises(InputError, match="invalid pose"):
            read_results(p)


# ----------------------------------------------------------------------------------------------
# 2D-3D from a full set of hloc files
# ----------------------------------------------------------------------------------------------


@pytest.fixture()
def hloc_files(tmp_path):
    """A tiny SfM model (2 db images, 4 3D points) + hloc features/matches/pairs for one query."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    X = np.array([[0, 0, 5.0], [1, 0, 5], [0, 1, 5], [1, 1, 6]])
    kp_db = {}
    for i, name in enumerate(DB):
        kp = np.random.default_rng(i).uniform(10, 600, (6, 2))  # COLMAP convention
        kp_db[name] = kp
        im = pycolmap.Image(name=name, keypoints=kp, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d())
    # db0 keypoint j observes point j (j < 4); db1 keypoint 5 - j observes point j
    for j in range(4):
        tr = pycolmap.Track()
        tr.add_element(1, j)
        tr.add_element(2, 5 - j)
        rec.add_point3D(X[j], tr)
    sfm = tmp_path / "sfm"
    sfm.mkdir()
    rec.write(sfm)
    pid_of = {j: None for j in range(4)}
    for pid, p in rec.points3D.items():
        pid_of[int(np.argmin(np.linalg.norm(X - p.xyz, axis=1)))] = pid

    features = tmp_path / "features.h5"
    kq = np.array([[100.0, 100], [200, 200], [300, 300], [400, 400], [500, 50]])  # hloc convention
    hloc_write_features(features, Q, kq, np.zeros((4, 5)), as_half=True)
    for name in DB:
        hloc_write_features(features, name, kp_db[name] - 0.5, np.zeros((4, 6)))
    matches = tmp_path / "matches.h5"
    # query kp0 -> db0 kp0 (point 0) and -> db1 kp5 (point 0 again: one entry)
    # query kp1 -> db0 kp1 (point 1) and -> db1 kp3 (point 2: a second entry for kp1)
    # query kp2 -> db0 kp4 (no 3D point); query kp3 -> db1 kp2 (point 3)
    hloc_write_matches(matches, Q, DB[0], [0, 1, 4, -1, -1], np.ones(5))
    hloc_write_matches(matches, DB[1], Q, [-1, -1, 3, 1, -1, 0], np.ones(6), old=True)  # reversed + old naming
    pairs = write_pairs(tmp_path / "pairs.txt", [(Q, DB[0]), (Q, DB[1])])
    return {"sfm": sfm, "features": features, "matches": matches, "pairs": pairs, "kq": kq, "X": X, "pid": pid_of}


def test_point_matches_from_hloc(hloc_files):
    f = hloc_files
    pm = point_matches_from_hloc(Q, f["sfm"], f["features"], f["matches"], f["pairs"])
    p2d, p3d, ids = pm  # unpacks as a triple
    kq = f["kq"].astype(np.float16).astype(np.float64) + 0.5
    got = {(int(k), tuple(np.round(x, 6))) for k, x in zip(pm.keypoint_idx, p3d)}
    want = {(0, tuple(f["X"][0])), (1, tuple(f["X"][1])), (1, tuple(f["X"][2])), (3, tuple(f["X"][3]))}
    assert got == want
    np.testing.assert_array_equal(p2d, kq[pm.keypoint_idx])
    assert set(ids.tolist()) == {f["pid"][j] for j in range(4)}
    # a list of pairs and a reused model index give the same
    model = ModelIndex(hloc_io.read_sfm(f["sfm"]))
    pm2 = point_matches_from_hloc(Q, None, f["features"], f["matches"], [(Q, DB[0]), (Q, DB[1])], model=model)
    np.testing.assert_array_equal(pm2.p3d, pm.p3d)


def test_point_matches_from_hloc_bad_inputs(hloc_files, tmp_path):
    f = hloc_files
    bad_pairs = write_pairs(tmp_path / "bad_pairs.txt", [(Q, "seq-01/frame-999999.color.png")])
    with pytest.raises(InputError, match="not in the SfM model") as e:
        point_matches_from_hloc(Q, f["sfm"], f["features"], f["matches"], bad_pairs)
    assert "frame-999999" in str(e.value) and str(bad_pairs) in str(e.value)
    other = "seq-02/frame-000015.color.png"
    with pytest.raises(InputError, match="features file") as e:
        point_matches_from_hloc(other, f["sfm"], f["features"], f["matches"], [(other, DB[0])])
    assert other in str(e.value) and str(f["features"]) in str(e.value)
    # matches indexing beyond the model's keypoints
    with h5py.File(f["matches"], "a") as fd:
        del fd[names_to_pair(Q, DB[0])]
        fd.create_group(names_to_pair(Q, DB[0])).create_dataset("matches0", data=np.array([40, -1, -1, -1, -1], np.int16))
    with pytest.raises(InputError, match="beyond"):
        point_matches_from_hloc(Q, f["sfm"], f["features"], f["matches"], f["pairs"])
    with pytest.raises(InputError, match="SfM model folder is missing"):
        point_matches_from_hloc(Q, tmp_path / "nosfm", f["features"], f["matches"], f["pairs"])
