"""Pseudo ground truth as Brachmann et al. publish it (pgt/<source>/7scenes/<scene>_{train,test}.txt) and its focal."""
import json

import numpy as np
import pytest

from lipmap import InputError
from lipmap.artifacts import scene_key
from lipmap.datasets import load_scene
from lipmap.datasets.sevenscenes import read_split
from lipmap.poses import qt_from_T
from localization.cli import main

FOCAL = 531.25  # neither 525 (the loader's default) nor 525.505 (the mini's sfm lists)


def _scene_root(tmp_path, scene_dir):
    """A fresh dataset root holding ``scene_dir`` (linked): the session's shared roots must not gain a pgt/ folder."""
    root = tmp_path / "data"
    root.mkdir()
    (root / scene_dir.name).symlink_to(scene_dir.resolve())
    return root


def _split_rows(scene_dir, rows):
    """``rows`` (list lines) divided into the scene's train and test lists by their sequence."""
    train = {f"seq-{s:02d}" for s in read_split(scene_dir / "TrainSplit.txt")}
    out = {"train": [], "test": []}
    for row in rows:
        out["train" if row.split("/")[0] in train else "test"].append(row)
    return out


def write_published(folder, scene_dir, rows):
    """``folder/<scene>_{train,test}.txt`` from list lines."""
    folder.mkdir(parents=True, exist_ok=True)
    for split, lines in _split_rows(scene_dir, rows).items():
        (folder / f"{scene_dir.name}_{split}.txt").write_text("\n".join(lines) + "\n")
    return folder


def synthetic_rows(root, scene, focal=FOCAL):
    """List lines of the scene's own poses (pose.txt), each with ``focal`` (None: no focal column)."""
    s = load_scene("synthetic", root, scene)
    rows = []
    for v in s.mapping + s.query:
        q, t = qt_from_T(v.cam_from_world)
        rows.append(" ".join([v.name, *(repr(float(x)) for x in (*q, *t))] + ([] if focal is None else [repr(focal)])))
    return s, rows


@pytest.fixture
def synth(synthetic_root, tmp_path):
    """(dataset root with the synthetic scene and no pgt/, scene folder, posetxt scene, list lines with FOCAL)."""
    scene_dir = next(p for p in synthetic_root.iterdir() if (p / "TrainSplit.txt").exists())
    root = _scene_root(tmp_path, scene_dir)
    ref, rows = synthetic_rows(root, scene_dir.name)
    return root, scene_dir, ref, rows


def _assert_same_poses(a, b, atol=0.0):
    assert [v.name for v in a.mapping + a.query] == [v.name for v in b.mapping + b.query]
    for x, y in zip(a.mapping + a.query, b.mapping + b.query):
        np.testing.assert_allclose(x.cam_from_world, y.cam_from_world, atol=atol, rtol=0)


class TestPublishedLayout:
    def test_redkitchen_mini_published_lists_give_todays_poses_and_their_focal(self, redkitchen_root, tmp_path):
        scene_dir = redkitchen_root / "redkitchen"
        root = _scene_root(tmp_path, scene_dir)
        today = load_scene("7scenes", root, "redkitchen", pose_source="sfm")
        assert {v.camera.fx for v in today.all_views()} == {525.505}  # the per-scene list's own focal, not 525
        rows = [" ".join(line.split()[:8] + [str(FOCAL)])
                for line in (scene_dir / "pgt" / "sfm_redkitchen.txt").read_text().splitlines() if line.strip()]
        write_published(root / "pgt" / "sfm" / "7scenes", scene_dir, rows)
        s = load_scene("7scenes", root, "redkitchen", pose_source="sfm")  # default: ROOT/pgt
        _assert_same_poses(s, today)
        folder = root / "pgt" / "sfm" / "7scenes"
        assert s.meta["pgt_files"] == [str(folder / f"redkitchen_{x}.txt") for x in ("train", "test")]
        cams = {id(v.camera) for v in s.all_views()}
        assert len(cams) == 1  # one Camera object when all lines agree
        assert s.mapping[0].camera.params == (FOCAL, FOCAL, 320.0, 240.0)
        assert "redkitchen_train.txt" in s.meta["focal_source"]

    def test_the_focal_reaches_depth_registration(self, redkitchen_root, tmp_path):
        # depth is registered into each view's colour camera: at focal 600 the depth map is the focal-525 one
        # magnified by 600 / 525 about the principal point
        scene_dir = redkitchen_root / "redkitchen"
        root = _scene_root(tmp_path, scene_dir)
        rows = [" ".join(line.split()[:8] + ["600"])
                for line in (scene_dir / "pgt" / "dslam_redkitchen.txt").read_text().splitlines() if line.strip()]
        write_published(root / "pgt" / "dslam" / "7scenes", scene_dir, rows)
        long = load_scene("7scenes", root, "redkitchen", pose_source="dslam").mapping[0]
        (root / "pgt").rename(tmp_path / "moved")  # back to the per-scene list: focal 525
        default = load_scene("7scenes", root, "redkitchen", pose_source="dslam").mapping[0]
        assert (long.camera.fx, default.camera.fx) == (600.0, 525.0)
        d_long, d_def = long.load_depth(), default.load_depth()
        h, w = d_def.shape
        col = np.clip(np.floor(320 + (np.arange(w) + 0.5 - 320) * 525 / 600).astype(int), 0, w - 1)
        row = np.clip(np.floor(240 + (np.arange(h) + 0.5 - 240) * 525 / 600).astype(int), 0, h - 1)
        magnified = d_def[row][:, col]
        ok = (magnified > 0) & (d_long > 0)
        assert ok.mean() > 0.5 and np.median(np.abs(magnified - d_long)[ok]) < 2e-3
        same = (d_def > 0) & (d_long > 0)
        assert np.median(np.abs(d_def - d_long)[same]) > 2e-2  # without the magnification they disagree

    @pytest.mark.parametrize("form", ["clone", "pgt", "pgt/sfm", "7scenes"])
    def test_every_folder_form(self, synth, tmp_path, form):
        root, scene_dir, ref, rows = synth
        clone = tmp_path / "visloc_pseudo_gt_limitations"
        write_published(clone / "pgt" / "sfm" / "7scenes", scene_dir, rows)
        write_published(clone / "pgt" / "dslam" / "7scenes", scene_dir, rows)
        given = {"clone": clone, "pgt": clone / "pgt", "pgt/sfm": clone / "pgt" / "sfm",
                 "7scenes": clone / "pgt" / "sfm" / "7scenes"}[form]
        s = load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=given)
        _assert_same_poses(s, ref, atol=1e-12)
        c = ref.mapping[0].camera
        assert {v.camera.params for v in s.all_views()} == {(FOCAL, FOCAL, c.cx, c.cy)}
        assert s.meta["pgt_files"][0] == str(clone / "pgt" / "sfm" / "7scenes" / f"{scene_dir.name}_train.txt")

    def test_default_is_root_pgt_then_the_per_scene_list(self, synth, tmp_path):
        root, scene_dir, ref, rows = synth
        with pytest.raises(InputError, match=r"sfm_room-s3\.txt: pseudo ground-truth file is missing.*--pgt DIR"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm")
        write_published(root / "pgt" / "sfm" / "7scenes", scene_dir, rows)
        s = load_scene("synthetic", root, scene_dir.name, pose_source="sfm")
        assert s.mapping[0].camera.fx == FOCAL and s.meta["pgt_files"][0].startswith(str(root / "pgt"))
        # a scene the published folder does not list reads its own pgt/ list
        other = tmp_path / "other"
        (other / "pgt").mkdir(parents=True)
        for p in scene_dir.iterdir():
            if p.name != "pgt":
                (other / p.name).symlink_to(p)
        (other / "pgt" / "sfm_other.txt").write_text("\n".join(r.rsplit(" ", 1)[0] + " 530" for r in rows) + "\n")
        (root / "other").symlink_to(other)
        s2 = load_scene("synthetic", root, "other", pose_source="sfm")
        assert s2.meta["pgt_files"] == [str(root / "other" / "pgt" / "sfm_other.txt")]
        assert s2.mapping[0].camera.fx == 530.0
        _assert_same_poses(s2, s)

    def test_lines_without_a_focal_keep_the_default(self, synth):
        root, scene_dir, ref, rows = synth
        _, bare = synthetic_rows(root, scene_dir.name, focal=None)
        rows = rows[:1] + bare[1:]  # only the first mapping frame's line gives a focal
        write_published(root / "pgt" / "dslam" / "7scenes", scene_dir, rows)
        s = load_scene("synthetic", root, scene_dir.name, pose_source="dslam")
        assert s.mapping[0].camera.fx == FOCAL
        assert all(v.camera is ref.mapping[0].camera or v.camera == ref.mapping[0].camera for v in s.all_views()[1:])
        assert f"{len(rows) - 1} line(s) give none" in s.meta["focal_source"]

    def test_the_digest_follows_the_focal_not_the_folder(self, synth, tmp_path):
        root, scene_dir, ref, rows = synth
        a = load_scene("synthetic", root, scene_dir.name, pose_source="sfm",
                       pgt_dir=write_published(tmp_path / "a", scene_dir, rows))
        b = load_scene("synthetic", root, scene_dir.name, pose_source="sfm",
                       pgt_dir=write_published(tmp_path / "b", scene_dir, rows))
        other = [r.rsplit(" ", 1)[0] + " 530" for r in rows]
        c = load_scene("synthetic", root, scene_dir.name, pose_source="sfm",
                       pgt_dir=write_published(tmp_path / "c", scene_dir, other))
        assert scene_key(a) == scene_key(b)
        assert scene_key(a) != scene_key(c)
        assert scene_key(a, a.query) != scene_key(c, c.query)


class TestPublishedErrors:
    def test_missing_test_list_names_the_folder_and_the_file(self, synth, tmp_path):
        root, scene_dir, _, rows = synth
        folder = write_published(tmp_path / "pgt" / "sfm" / "7scenes", scene_dir, rows)
        (folder / f"{scene_dir.name}_test.txt").unlink()
        with pytest.raises(InputError, match=rf"{folder}: the test list of scene {scene_dir.name} is missing .*"
                                             rf"expected {scene_dir.name}_test\.txt"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=tmp_path)

    def test_folder_without_lists(self, synth, tmp_path):
        root, scene_dir, _, _ = synth
        (tmp_path / "empty").mkdir()
        with pytest.raises(InputError, match="no sfm pseudo-GT lists here"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=tmp_path / "empty")
        with pytest.raises(InputError, match="pseudo ground-truth folder does not exist"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=tmp_path / "nowhere")

    def test_the_other_sources_folder(self, synth, tmp_path):
        root, scene_dir, _, rows = synth
        folder = write_published(tmp_path / "pgt" / "dslam" / "7scenes", scene_dir, rows)
        with pytest.raises(InputError, match="this is the dslam pseudo-GT folder, but the pose source is sfm"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=folder)

    def test_pgt_with_posetxt(self, synth, tmp_path):
        root, scene_dir, _, _ = synth
        with pytest.raises(InputError, match="pose source is posetxt"):
            load_scene("synthetic", root, scene_dir.name, pgt_dir=tmp_path)

    @pytest.mark.parametrize("focal", ["abc", "0", "-525", "nan", "inf"])
    def test_bad_focal_names_the_file_and_line(self, synth, tmp_path, focal):
        root, scene_dir, _, rows = synth
        rows = list(rows)
        rows[2] = rows[2].rsplit(" ", 1)[0] + " " + focal  # the third mapping frame: line 3 of the train list
        folder = write_published(tmp_path / "sfm" / "7scenes", scene_dir, rows)
        with pytest.raises(InputError, match=rf"{scene_dir.name}_train\.txt: line 3: focal length must be a positive "
                                             rf"number of pixels, got '{focal}'"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=folder)

    def test_frame_in_both_lists(self, synth, tmp_path):
        root, scene_dir, _, rows = synth
        folder = write_published(tmp_path / "sfm" / "7scenes", scene_dir, rows)
        test = folder / f"{scene_dir.name}_test.txt"
        test.write_text(test.read_text() + rows[0] + "\n")
        with pytest.raises(InputError, match=rf"_test\.txt: 1 frame\(s\) are also in {scene_dir.name}_train\.txt"):
            load_scene("synthetic", root, scene_dir.name, pose_source="sfm", pgt_dir=folder)


class TestCommandLine:
    def test_info_shows_the_focal_and_its_files(self, synth, tmp_path, capsys):
        root, scene_dir, _, rows = synth
        clone = tmp_path / "clone"
        write_published(clone / "pgt" / "sfm" / "7scenes", scene_dir, rows)
        args = ["info", "--dataset", "synthetic", "--root", str(root), "--pose-source", "sfm", "--pgt", str(clone)]
        assert main(args + ["--json"]) == 0
        info = json.loads(capsys.readouterr().out)["scenes"][scene_dir.name]
        assert info["intrinsics"][:2] == [FOCAL, FOCAL] and info["focal"] == {f"{FOCAL:g}": len(rows)}
        assert f"{scene_dir.name}_train.txt" in info["focal_source"]
        assert main(args) == 0
        out = capsys.readouterr().out
        assert f"focal: {FOCAL:g} px, from the sfm pseudo-GT lines ({clone / 'pgt' / 'sfm' / '7scenes'}" in out

    def test_info_without_pgt_says_where_the_focal_comes_from(self, synth, capsys):
        root, scene_dir, _, _ = synth
        assert main(["info", "--dataset", "synthetic", "--root", str(root)]) == 0
        assert "focal: 262.5 px, from scene.json" in capsys.readouterr().out

    def test_bad_pgt_is_a_one_line_error(self, synth, tmp_path, capsys):
        root, scene_dir, _, _ = synth
        assert main(["info", "--dataset", "synthetic", "--root", str(root), "--pose-source", "sfm",
                     "--pgt", str(tmp_path / "nowhere")]) == 2
        assert "pseudo ground-truth folder does not exist" in capsys.readouterr().err

    def test_map_and_eval_pass_the_folder_on(self, synth, tmp_path, monkeypatch, capsys):
        root, scene_dir, _, rows = synth
        folder = write_published(tmp_path / "sfm" / "7scenes", scene_dir, rows)
        seen = {}

        def stop_map(scene, *a, **k):
            seen["map"] = scene
            raise InputError("stopped here")

        def stop_eval(*a, **k):
            seen["eval"] = k
            raise InputError("stopped here")

        import lipmap.mapping.pipeline
        import localization.pipeline

        monkeypatch.setattr(lipmap.mapping.pipeline, "map_scene", stop_map)
        monkeypatch.setattr(localization.pipeline, "run_eval", stop_eval)
        common = ["--dataset", "synthetic", "--root", str(root), "--out", str(tmp_path / "out"), "--pose-source", "sfm",
                  "--pgt", str(folder)]
        assert main(["map", "--scene", scene_dir.name] + common) == 2
        assert seen["map"].mapping[0].camera.fx == FOCAL
        assert main(["eval"] + common) == 2
        assert seen["eval"]["pgt_dir"] == folder and seen["eval"]["pose_source"] == "sfm"

    def test_run_eval_passes_the_folder_to_the_loader(self, monkeypatch, tmp_path):
        import lipmap.datasets
        from localization.config import LocalizationConfig
        from localization.pipeline import run_eval

        seen = {}

        def stop(*a, **k):
            seen.update(k)
            raise InputError("stopped here")

        monkeypatch.setattr(lipmap.datasets, "load_scene", stop)
        with pytest.raises(InputError, match="stopped here"):
            run_eval("7scenes", tmp_path, ["chess"], tmp_path / "out", LocalizationConfig(), pose_source="sfm",
                     pgt_dir=tmp_path / "pgt")
        assert seen["pgt_dir"] == tmp_path / "pgt" and seen["pose_source"] == "sfm"
