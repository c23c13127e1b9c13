"""`eval --hloc` on hloc's real output tree (hloc/pipelines/7Scenes/pipeline.py's names and layouts).

The fixture is the built-in SIFT data of a small synthetic scene written as hloc writes it: per scene folder
``sfm_sift/``, ``sfm_superpoint+superglue/`` (+ ``+depth/``), ``feats-superpoint-n4096-r1024.h5`` in float16,
the covisibility and the query matches files (int16 / float16, keys from ``names_to_pair``),
``pairs-db-covis30.txt``, ``query_list_with_intrinsics.txt``, ``results_sparse.txt``; the query pairs
``<scene>_top10.txt`` in the dataset's ``7scenes_densevlad_retrieval_top_10/``. The networks' weights cannot be
downloaded here, so the files hold SIFT under SuperPoint's names: what is tested is where things are and how
they are stored. Localized from it, every query must come out where the built-in points put it, up to float16
rounding of the keypoints.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pycolmap
import pytest

from lipmap import InputError
from lipmap.datasets import load_scene
from lipmap.poses import invert_T, pose_errors, qt_from_T
from localization.cli import main as cli_main
from localization.hloc_io import ModelIndex, names_to_pair, read_features, read_matches, read_pairs, read_sfm
from localization.hloc_outputs import HlocOutputs, check_world_frame, find_hloc_files
from localization.pipeline import run_eval

from test_pipeline import CONF, MINI

SCENE = "room-s1"
FEATS = "feats-superpoint-n4096-r1024"
RETRIEVAL = "7scenes_densevlad_retrieval_top_10"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict:
    """A built-in run on the mini scene: data root, output folder, results, and its points folder."""
    from lipmap.datasets.synthetic import generate_scene

    data = tmp_path_factory.mktemp("data")
    generate_scene(data, seed=1, preset=MINI)
    out = tmp_path_factory.mktemp("builtin")
    path = run_eval("synthetic", data, [SCENE], out, CONF)
    (points,) = (out / "synthetic" / SCENE).glob("points-*")
    return {"data": data, "out": out, "points": points,
            "scene": json.loads((path.parent / SCENE / "results.json").read_text())}


def _write_features_as_hloc(src: Path, dst: Path):
    """hloc's extract_features with as_half: every float32 array stored as float16, keypoints in OpenCV origin."""
    with h5py.File(src, "r") as f:
        names = []
        f.visititems(lambda n, o: names.append(o.parent.name.strip("/")) if isinstance(o, h5py.Dataset) else None)
    with h5py.File(dst, "w", libver="latest") as fd:
        for name in sorted(set(names)):
            feats = read_features(src, name)
            grp = fd.create_group(name)
            grp.create_dataset("keypoints", data=(feats["keypoints"] - 0.5).astype(np.float16))
            grp.create_dataset("descriptors", data=feats["descriptors"].T.astype(np.float16))
            grp.create_dataset("scores", data=np.ones(len(feats["keypoints"]), np.float16))
            grp.create_dataset("image_size", data=np.asarray(feats["image_size"] or (240, 180), np.int64))


def _write_matches_as_hloc(src: Path, pairs: list, n_kp: dict, dst: Path):
    """hloc's match_features: one group per pair named by names_to_pair, int16 matches0, float16 scores."""
    with h5py.File(dst, "w", libver="latest") as fd:
        for a, b in pairs:
            m, s = read_matches(src, a, b)
            m0 = np.full(n_kp[a], -1, np.int16)
            s0 = np.zeros(n_kp[a], np.float16)
            m0[m[:, 0]], s0[m[:, 0]] = m[:, 1], s
            grp = fd.create_group(names_to_pair(a, b))
            grp.create_dataset("matches0", data=m0)
            grp.create_dataset("matching_scores0", data=s0)


def make_hloc_tree(built: dict, root: Path, dense_depth: bool = False) -> tuple[Path, Path]:
    """hloc's outputs for the scene under ``root/outputs/<scene>``, and a dataset root holding the scene and the
    retrieval folder; returns (outputs root, dataset root)."""
    src = built["points"]
    data = root / "data"
    shutil.copytree(built["data"], data)
    outputs = root / "outputs"
    scene_out = outputs / SCENE
    scene_out.mkdir(parents=True)
    (model,) = src.glob("sfm_*")
    for name in ["sfm_sift", "sfm_superpoint+superglue"] + (["sfm_superpoint+superglue+depth"] if dense_depth else []):
        shutil.copytree(model, scene_out / name)
    features = scene_out / f"{FEATS}.h5"
    (builtin_feats,) = [p for p in src.glob("feats-*.h5") if "_" not in p.stem]
    _write_features_as_hloc(builtin_feats, features)
    with h5py.File(features, "r") as f:
        n_kp = {}
        f.visititems(lambda n, o: n_kp.__setitem__(o.parent.name.strip("/"), len(o)) if n.endswith("keypoints") else None)
    (covis,) = src.glob("pairs-db-covis*.txt")
    shutil.copy(covis, scene_out / "pairs-db-covis30.txt")
    _write_matches_as_hloc(next(src.glob(f"*_{covis.stem}.h5")), read_pairs(covis), n_kp,
                           scene_out / f"{FEATS}_matches-superglue_pairs-db-covis30.h5")
    (qpairs,) = src.glob("pairs-query-*.txt")
    (data / RETRIEVAL).mkdir()
    shutil.copy(qpairs, data / RETRIEVAL / f"{SCENE}_top10.txt")
    _write_matches_as_hloc(next(src.glob(f"*_{qpairs.stem}.h5")), read_pairs(qpairs), n_kp,
                           scene_out / f"{FEATS}_matches-superglue_{SCENE}_top10.h5")
    scene = load_scene("synthetic", data, SCENE)
    (scene_out / "query_list_with_intrinsics.txt").write_text("".join(
        f"{v.name} PINHOLE {v.camera.width} {v.camera.height} {' '.join(map(str, v.camera.params))}\n" for v in scene.query))
    (scene_out / "results_sparse.txt").write_text("".join(
        f"{v.name} {' '.join(map(str, np.concatenate(qt_from_T(v.cam_from_world))))}\n" for v in scene.query))
    return outputs, data


def _pose_of(results: dict, name: str, key: str):
    return results["queries"][name][key]["t_cm"], results["queries"][name][key]["R_deg"]


def _eval(built, tmp_path, outputs, data, **over):
    out = tmp_path / "out"
    # the built-in run's line map and query lines, without its points and journal: only the points differ
    shutil.copytree(built["out"], out, ignore=shutil.ignore_patterns("queries-*.jsonl", "results*", "points-*"))
    path = run_eval("synthetic", data, [SCENE], out, CONF, hloc_dir=HlocOutputs(outputs, **over))
    return json.loads((path.parent / SCENE / "results.json").read_text())


def test_hloc_tree_gives_the_builtin_points_results(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    res = _eval(built, tmp_path, outputs, data)
    chosen = res["points"]["hloc"]
    assert Path(chosen["sfm"]).name == "sfm_superpoint+superglue"  # the learned-feature model, not sfm_sift
    assert Path(chosen["features"]).name == f"{FEATS}.h5"
    assert Path(chosen["matches"]).name == f"{FEATS}_matches-superglue_{SCENE}_top10.h5"
    assert Path(chosen["pairs"]) == data / RETRIEVAL / f"{SCENE}_top10.txt"
    assert set(chosen["reasons"]) == {"sfm", "features", "matches", "pairs"}
    assert res["points"]["frame_gap_cm"] < 0.01
    ref = built["scene"]
    dt = {k: [] for k in ("point", "point+line")}
    for name in ref["queries"]:
        for key in dt:
            (t_ref, r_ref), (t, r) = _pose_of(ref, name, key), _pose_of(res, name, key)
            dt[key].append((abs(t - t_ref), abs(r - r_ref)))
    # float16 keypoints (0.125 px steps at these sizes, f = 197 px, scene ~2 m away) move a pose by about
    # 0.04 px / 197 px x 2 m ~ 0.4 mm; the line rounds start from that pose and may take a line more or less, which
    # moves a query with ~10 line inliers, each weighted at PnPL's 1 px line scale, by up to some millimetres
    assert (np.max(dt["point"], axis=0) < [0.1, 0.03]).all(), dt["point"]
    assert (np.max(dt["point+line"], axis=0) < [0.6, 0.3]).all(), dt["point+line"]


def test_dense_depth_model_is_preferred(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path, dense_depth=True)
    files = find_hloc_files(HlocOutputs(outputs), load_scene("synthetic", data, SCENE))
    assert files.sfm.name == "sfm_superpoint+superglue+depth"
    assert "dense-depth" in files.reasons["sfm"]


def test_sfm_sift_only_when_alone_and_flags_override(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    scene = load_scene("synthetic", data, SCENE)
    shutil.rmtree(outputs / SCENE / "sfm_superpoint+superglue")
    assert find_hloc_files(HlocOutputs(outputs), scene).sfm.name == "sfm_sift"
    # every choice can be given, {scene} and paths relative to the scene's folder included
    alt = outputs / SCENE / "pairs-elsewhere.txt"
    shutil.copy(data / RETRIEVAL / f"{SCENE}_top10.txt", alt)
    files = find_hloc_files(HlocOutputs(outputs, pairs="pairs-elsewhere.txt", sfm="sfm_sift",
                                        matches=f"{FEATS}_matches-superglue_{{scene}}_top10.h5"), scene)
    assert files.pairs == alt and files.reasons["pairs"] == "given (--hloc-pairs)"
    assert files.matches.name == f"{FEATS}_matches-superglue_{SCENE}_top10.h5"


def test_lightglue_and_other_names_and_pairs_in_the_output_folder(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    scene_out = outputs / SCENE
    for p in scene_out.glob(f"{FEATS}*"):  # SuperPoint + LightGlue, as hloc names them
        p.rename(scene_out / p.name.replace(FEATS, "feats-superpoint-n2048-r1024").replace("superglue", "superpoint-lightglue"))
    shutil.move(data / RETRIEVAL / f"{SCENE}_top10.txt", scene_out / f"{SCENE}_top10.txt")
    files = find_hloc_files(HlocOutputs(outputs), load_scene("synthetic", data, SCENE))
    assert files.features.name == "feats-superpoint-n2048-r1024.h5"
    assert files.matches.name == f"feats-superpoint-n2048-r1024_matches-superpoint-lightglue_{SCENE}_top10.h5"
    assert files.pairs == scene_out / f"{SCENE}_top10.txt"


def test_missing_and_ambiguous_files_name_the_flag(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    scene = load_scene("synthetic", data, SCENE)
    shutil.copytree(outputs / SCENE / "sfm_superpoint+superglue", outputs / SCENE / "sfm_superpoint+lightglue")
    with pytest.raises(InputError, match=r"several SfM models fit equally well.*--hloc-sfm"):
        find_hloc_files(HlocOutputs(outputs), scene)
    shutil.rmtree(outputs / SCENE / "sfm_superpoint+lightglue")
    (data / RETRIEVAL / f"{SCENE}_top10.txt").unlink()
    with pytest.raises(InputError, match=r"no query pairs file.*--hloc-pairs"):
        find_hloc_files(HlocOutputs(outputs), scene)


def test_model_from_other_features_is_refused(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    features = outputs / SCENE / f"{FEATS}.h5"
    with h5py.File(features, "a") as f:  # one keypoint fewer: not the features the model was triangulated from
        name = "seq-01/frame-000000.color.png"
        kp = f[name]["keypoints"][()]
        del f[name]["keypoints"]
        f[name].create_dataset("keypoints", data=kp[:-1])
    with pytest.raises(InputError, match=r"2D points in the SfM model but .* keypoints .* not triangulated from these"):
        run_eval("synthetic", data, [SCENE], tmp_path / "out", CONF, hloc_dir=outputs)


def _moved_model(src: Path, dst: Path, shift) -> Path:
    rec = pycolmap.Reconstruction(str(src))
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), np.asarray(shift, float)))
    dst.mkdir(parents=True, exist_ok=True)
    rec.write(str(dst))
    return dst


def test_model_in_another_frame_stops_with_the_gap(built, tmp_path, capsys):
    outputs, data = make_hloc_tree(built, tmp_path)
    model = outputs / SCENE / "sfm_superpoint+superglue"
    _moved_model(model, model, (0.3, 0.0, 0.0))
    code = cli_main(["eval", "--dataset", "synthetic", "--root", str(data), "--scenes", SCENE, "--out",
                     str(tmp_path / "out"), "--hloc", str(outputs), "--method", "lift", "--points", "sift-n2048"])
    err = capsys.readouterr().err
    assert code == 2
    assert f"{model}: the SfM model's cameras lie 30.0 cm (median over 16 shared mapping images)" in err
    assert "another world frame" in err


def test_frame_message_names_the_pose_source_that_fits(redkitchen_root, tmp_path):
    """A model made with the SfM pseudo-GT poses, checked against a map made with pose.txt: the message names sfm."""
    posetxt = load_scene("7scenes", redkitchen_root, "redkitchen")
    sfm = load_scene("7scenes", redkitchen_root, "redkitchen", pose_source="sfm")
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[525, 525, 320, 240], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for i, v in enumerate(sfm.mapping, start=1):
        T = v.cam_from_world
        image = pycolmap.Image(name=v.name, camera_id=1, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3]))
    model = ModelIndex(rec, tmp_path / "sfm")
    assert check_world_frame(model, sfm, tmp_path / "sfm") < 1e-9
    with pytest.raises(InputError) as e:
        check_world_frame(model, posetxt, tmp_path / "sfm", {"sfm": sfm.mapping, "dslam": load_scene(
            "7scenes", redkitchen_root, "redkitchen", pose_source="dslam").mapping})
    msg = str(e.value)
    assert "from the scene's posetxt poses" in msg and "its poses fit --pose-source sfm (0.0 cm)" in msg
    assert "dslam" not in msg.split("fit --pose-source")[1]


def test_a_model_copied_out_of_models_0_is_one_model(built, tmp_path):
    outputs, data = make_hloc_tree(built, tmp_path)
    model = outputs / SCENE / "sfm_superpoint+superglue"
    shutil.copytree(model, model / "models" / "0", ignore=shutil.ignore_patterns("models"))
    files = find_hloc_files(HlocOutputs(outputs), load_scene("synthetic", data, SCENE))
    assert files.sfm == model


# ----------------------------------------------------------------------------------------------
# files hloc's own code wrote (tests/data/hloc_7scenes/README.md: hloc c13273b, pycolmap 3.13, SIFT + NN-mutual)
# ----------------------------------------------------------------------------------------------
HLOC_FIXTURE = Path(__file__).parent / "data" / "hloc_7scenes"


@pytest.fixture(scope="module")
def hloc_written(tmp_path_factory) -> dict:
    """The fixture's dataset side with the regenerated scene's images (the points come from hloc's files alone)."""
    from lipmap.datasets.synthetic import generate_scene

    full = tmp_path_factory.mktemp("full")
    scene_dir = generate_scene(full, seed=0, preset="small")
    data = tmp_path_factory.mktemp("hloc-data") / "7scenes"
    shutil.copytree(HLOC_FIXTURE / "datasets" / "7scenes", data)
    for pose in data.glob("room-s0/seq-*/frame-*.pose.txt"):
        stem = pose.name[: -len(".pose.txt")]
        for kind in ("color.png", "depth.png"):
            shutil.copy(scene_dir / pose.parent.name / f"{stem}.{kind}", pose.parent / f"{stem}.{kind}")
    return {"data": data, "outputs": HLOC_FIXTURE / "hloc_outputs" / "7scenes"}


def test_eval_on_files_hloc_wrote(hloc_written, tmp_path):
    from localization.hloc_io import read_results

    data, outputs = hloc_written["data"], hloc_written["outputs"]
    path = run_eval("synthetic", data, ["room-s0"], tmp_path / "out", CONF, hloc_dir=outputs)
    res = json.loads((path.parent / "room-s0" / "results.json").read_text())
    chosen = res["points"]["hloc"]
    assert Path(chosen["sfm"]).name == "sfm_sift+NN-mutual"  # triangulated from the features, not sfm_sift
    assert Path(chosen["features"]).name == "feats-sift.h5"
    assert Path(chosen["matches"]).name == "feats-sift_matches-NN-mutual_room-s0_top10.h5"
    assert Path(chosen["pairs"]) == data / "7scenes_densevlad_retrieval_top_10" / "room-s0_top10.txt"
    # point-only from hloc's own matches is at least as accurate as hloc's localize_sfm (pycolmap's
    # estimate_and_refine_absolute_pose) on them
    scene = load_scene("synthetic", data, "room-s0")
    hloc_poses = read_results(outputs / "room-s0" / "results_sparse.txt")
    hloc_t = [100 * pose_errors(v.cam_from_world, hloc_poses[v.name])[0] for v in scene.query]
    ours_t = [res["queries"][v.name]["point"]["t_cm"] for v in scene.query]
    assert np.median(ours_t) <= 1.05 * np.median(hloc_t) + 0.01, (ours_t, hloc_t)
    assert res["summary"]["point+line"]["n_failed"] == 0


def test_hlocs_sfm_sift_is_refused_with_the_reason(hloc_written, tmp_path):
    scene = load_scene("synthetic", hloc_written["data"], "room-s0")
    from localization.points import HlocPoints

    with pytest.raises(InputError, match=r"sfm_sift: cannot read the COLMAP model.*hloc's sfm_sift"):
        HlocPoints(HlocOutputs(hloc_written["outputs"], sfm="sfm_sift"), scene)
