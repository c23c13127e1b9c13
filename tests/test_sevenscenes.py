import shutil

import cv2
import numpy as np
import pytest

from lipmap import InputError
from lipmap.datasets import load_scene
from lipmap.datasets.registration import cross_view_depth_residuals
from lipmap.datasets.sevenscenes import estimate_color_from_depth, read_pose_txt
from lipmap.poses import invert_T, pose_errors


class TestRedKitchenMini:
    def test_counts_and_names(self, redkitchen_root):
        s = load_scene("7scenes", redkitchen_root, "redkitchen")
        assert (len(s.mapping), len(s.query)) == (50, 50)
        assert s.mapping[0].name == "seq-01/frame-000000.color.png"  # hloc naming, even for .jpg files
        assert s.mapping[0].color_path.suffix == ".jpg"
        sp = load_scene("7scenes", redkitchen_root, "redkitchen-sparse")
        assert (len(sp.mapping), len(sp.query)) == (25, 25)

    def test_pose_matches_file(self, redkitchen_root):
        s = load_scene("7scenes", redkitchen_root, "redkitchen", register_depth=False)
        v = s.query[3]
        T_file = np.loadtxt(redkitchen_root / "redkitchen" / "seq-02" / "frame-000035.pose.txt")
        assert v.name == "seq-02/frame-000035.color.png"
        # pose.txt is camera-to-world; we hold cam_from_world.
        np.testing.assert_allclose(invert_T(v.cam_from_world), T_file, atol=2e-4)
        np.testing.assert_allclose(v.cam_from_world[:3, :3] @ v.cam_from_world[:3, :3].T, np.eye(3), atol=1e-12)

    def test_registered_posetxt_matches_dslam(self, redkitchen_root):
        # With registration, pose.txt (depth camera) is moved into the colour camera, which is what
        # the dSLAM pseudo-GT is: the two must agree to a millimetre.
        a = load_scene("7scenes", redkitchen_root, "redkitchen", register_depth=True)
        b = load_scene("7scenes", redkitchen_root, "redkitchen", pose_source="dslam")
        errs = np.array([pose_errors(x.cam_from_world, y.cam_from_world) for x, y in zip(a.query, b.query)])
        assert errs[:, 0].max() < 1e-3 and errs[:, 1].max() < 0.05

    def test_extrinsic_estimate(self, redkitchen_root):
        T = estimate_color_from_depth(redkitchen_root / "redkitchen")
        assert abs(T[0, 3] + 0.0256) < 1e-3 and abs(T[1, 3]) < 1e-3

    def test_mapping_step(self, redkitchen_root):
        s = load_scene("7scenes", redkitchen_root, "redkitchen", mapping_step=5)
        assert len(s.mapping) == 10 and s.mapping[1].name == "seq-01/frame-000050.color.png"

    def test_registration_reduces_cross_view_disagreement(self, redkitchen_root):
        med = {}
        for reg in (True, False):
            s = load_scene("7scenes", redkitchen_root, "redkitchen", register_depth=reg)
            vs = s.mapping[:12:2]  # frames 0, 20, ..., 100: a 20-frame gap between neighbours
            d = [v.load_depth(register=reg) for v in vs]
            r = np.concatenate([cross_view_depth_residuals(d[i], vs[i], d[i + 1], vs[i + 1]) for i in range(5)])
            med[reg] = np.median(r)
        assert med[True] < 0.7 * med[False]
        assert med[True] < 0.015


class TestStairsFixture:
    def test_official_layout(self, stairs_root):
        s = load_scene("7scenes", stairs_root, stairs_root.name)
        # TrainSplit: sequence2, sequence3; TestSplit: sequence1, sequence4 (3 frames each, CRLF files)
        assert len(s.mapping) == 6 and len(s.query) == 6
        assert {v.name.split("/")[0] for v in s.mapping} == {"seq-02", "seq-03"}
        T = read_pose_txt(stairs_root / "seq-01" / "frame-000000.pose.txt")
        np.testing.assert_allclose(T[:3, 3], [-1.4903377, -0.49737796, -0.054694783], atol=1e-7)


def _copy_scene(src, dst):
    shutil.copytree(src, dst)
    return dst


class TestBadInput:
    @pytest.fixture
    def scene_copy(self, stairs_root, tmp_path):
        return _copy_scene(stairs_root, tmp_path / "stairs")

    def test_unknown_scene_says_where_to_download(self, stairs_root):
        with pytest.raises(InputError, match="microsoft.com"):
            load_scene("7scenes", stairs_root.parent, "chess")

    def test_missing_image(self, scene_copy):
        (scene_copy / "seq-02" / "frame-000001.color.jpg").unlink()
        with pytest.raises(InputError, match="frame-000001.color.png: colour image is missing"):
            load_scene("7scenes", scene_copy.parent, "stairs")

    def test_corrupt_image(self, scene_copy):
        p = scene_copy / "seq-02" / "frame-000001.color.jpg"
        p.write_bytes(b"not a jpeg")
        s = load_scene("7scenes", scene_copy.parent, "stairs")
        v = s.view("seq-02/frame-000001.color.png")
        with pytest.raises(InputError, match="frame-000001.color.jpg: image cannot be decoded"):
            v.load_color()

    @pytest.mark.parametrize(
        "content,msg",
        [
            ("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "NaN"),
            ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not rigid"),
            ("1 0 0\n0 1 0\n", "4x4"),
        ],
    )
    def test_bad_pose(self, scene_copy, content, msg):
        p = scene_copy / "seq-03" / "frame-000002.pose.txt"
        p.write_text(content)
        with pytest.raises(InputError, match=f"frame-000002.pose.txt.*{msg}"):
            load_scene("7scenes", scene_copy.parent, "stairs")

    def test_depth_wrong_size(self, scene_copy):
        p = scene_copy / "seq-02" / "frame-000000.depth.png"
        cv2.imwrite(str(p), np.zeros((100, 120), np.uint16))
        v = load_scene("7scenes", scene_copy.parent, "stairs").mapping[0]
        with pytest.raises(InputError, match="depth.png: depth map has size 120x100, expected 640x480"):
            v.load_depth()

    def test_depth_wrong_type(self, scene_copy):
        p = scene_copy / "seq-02" / "frame-000000.depth.png"
        cv2.imwrite(str(p), np.zeros((480, 640), np.uint8))
        v = load_scene("7scenes", scene_copy.parent, "stairs").mapping[0]
        with pytest.raises(InputError, match="16-bit"):
            v.load_depth()

    def test_empty_split(self, scene_copy):
        (scene_copy / "TestSplit.txt").write_text("\n")
        with pytest.raises(InputError, match="TestSplit.txt: split file lists no sequences"):
            load_scene("7scenes", scene_copy.parent, "stairs")

    def test_split_names_missing_sequence(self, scene_copy):
        (scene_copy / "TestSplit.txt").write_text("sequence9\n")
        with pytest.raises(InputError, match="seq-09"):
            load_scene("7scenes", scene_copy.parent, "stairs")

    def test_unknown_pose_source(self, scene_copy):
        with pytest.raises(InputError, match="pose source"):
            load_scene("7scenes", scene_copy.parent, "stairs", pose_source="gps")

    def test_missing_pgt(self, scene_copy):
        with pytest.raises(InputError, match="pseudo ground-truth file is missing"):
            load_scene("7scenes", scene_copy.parent, "stairs", pose_source="dslam")
