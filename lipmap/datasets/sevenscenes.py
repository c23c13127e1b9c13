"""Reader for the official 7-Scenes layout (also used for synthetic scenes written in that layout).

    <root>/<scene>/TrainSplit.txt, TestSplit.txt      lines "sequenceN"
    <root>/<scene>/seq-NN/frame-NNNNNN.color.{png,jpg}, .depth.png, .pose.txt (camera-to-world)
    <root>/<scene>/pgt/{dslam,sfm}_<scene>.txt        optional pseudo ground truth, one list per scene
    <root>/pgt/{dslam,sfm}/7scenes/<scene>_{train,test}.txt   or the lists as Brachmann et al. publish them

Pose sources (same source for mapping and evaluation; never mixed):
- ``posetxt``: pose.txt, which is the DEPTH camera's pose (KinectFusion). With depth registration on,
  the colour camera's pose is ``colour_from_depth @ depth_from_world``; without it, pose.txt is used for
  the colour camera as most pipelines do.
- ``dslam`` / ``sfm``: the pseudo ground-truth lists (colour camera, COLMAP world-to-camera), lines
  ``name qw qx qy qz tx ty tz f``. Each view's camera takes its line's focal ``f`` (fx = fy = f, principal
  point kept): the SfM lists were made with 526.22 for Chess and 525.505 for RedKitchen, not 525.
  Where they are read from: :func:`pgt_lists`.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import logger
from ..errors import InputError
from ..poses import T_from_qt, check_rigid, invert_T
from ..scene import Camera, Scene, View
from .registration import SEVENSCENES_COLOR_FROM_DEPTH

SEVENSCENES_SCENES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
DOWNLOAD_HINT = (
    "the official 7-Scenes data is at https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/ "
    "(`lipmap-loc download 7scenes --root ROOT` fetches and unpacks them, or unzip each scene and its seq-NN.zip "
    "files under ROOT/<scene>/)"
)
POSE_SOURCES = ("posetxt", "dslam", "sfm")
COLOR_CAMERA = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))
DEPTH_CAMERA = Camera(640, 480, (585.0, 585.0, 320.0, 240.0))
_FRAME_RE = re.compile(r"^frame-(\d{6})\.pose\.txt$")
PGT_REPOSITORY = "https://github.com/tsattler/visloc_pseudo_gt_limitations"
PGT_HINT = (f"give --pgt DIR: a clone of {PGT_REPOSITORY}, its pgt/ folder or its pgt/<source>/7scenes/ folder; "
            "by default ROOT/pgt/<source>/7scenes/ is read when it exists, else ROOT/<scene>/pgt/<source>_<scene>.txt")


@dataclass
class SevenScenesConfig:
    pose_source: str = "posetxt"  # posetxt | dslam | sfm
    register_depth: bool = True
    mapping_step: int = 1  # keep every k-th mapping frame
    query_step: int = 1
    query_list: str | None = None  # hloc list_test.txt: restrict queries to these names
    color_from_depth: np.ndarray | None = None  # override the Kinect depth-to-colour extrinsic
    skip_bad_frames: bool = False  # a bad MAPPING frame is skipped with a warning instead of stopping
    pgt_dir: str | Path | None = None  # published pseudo-GT lists (see pgt_lists); default ROOT/pgt, else per scene


def find_scene_dir(root, scene: str) -> Path:
    """``root/scene`` or ``root`` itself when it is a scene folder (has TrainSplit.txt) named ``scene``."""
    root = Path(root)
    if not root.is_dir():
        raise InputError("dataset root does not exist or is not a folder", root, DOWNLOAD_HINT)
    cand = root / scene
    if (cand / "TrainSplit.txt").exists() or (cand / "TestSplit.txt").exists():
        return cand
    if root.name == scene and (root / "TrainSplit.txt").exists():
        return root
    if cand.is_dir():
        raise InputError(f"scene folder {cand} has no TrainSplit.txt / TestSplit.txt", cand)
    raise InputError(f"scene {scene!r} not found (looked for {cand}/TrainSplit.txt)", root, DOWNLOAD_HINT)


def list_scenes(root) -> list[str]:
    root = Path(root)
    if (root / "TrainSplit.txt").exists():
        return [root.name]
    if not root.is_dir():
        raise InputError("dataset root does not exist or is not a folder", root, DOWNLOAD_HINT)
    return sorted(p.name for p in root.iterdir() if (p / "TrainSplit.txt").exists())


def read_split(path: Path) -> list[int]:
    if not path.exists():
        raise InputError("split file is missing", path)
    seqs = []
    for i, line in enumerate(path.read_text().splitlines()):
        line = line.strip()
        if not line:
            continue
        m = re.fullmatch(r"sequence(\d+)", line)
        if not m:
            raise InputError(f"line {i + 1}: expected 'sequenceN', got {line!r}", path)
        if int(m.group(1)) in seqs:
            raise InputError(f"line {i + 1}: {line} is listed twice (its frames would have duplicate names)", path)
        seqs.append(int(m.group(1)))
    if not seqs:
        raise InputError("split file lists no sequences (empty split)", path)
    return seqs


def read_pose_txt(path: Path) -> np.ndarray:
    """camera-to-world 4x4 from a 7-Scenes pose file, rotation projected onto SO(3)."""
    try:
        T = np.loadtxt(path, dtype=float)
    except (ValueError, OSError) as e:
        raise InputError(f"cannot parse pose file: {e}", path) from None
    if T.shape != (4, 4):
        raise InputError(f"pose file must hold a 4x4 matrix, got shape {T.shape}", path)
    return check_rigid(T, path)


def read_pgt_list(path: Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """One pseudo-GT list, lines ``seq-XX/frame-NNNNNN.color.png qw qx qy qz tx ty tz [f]``.

    Returns ``{frame key: cam_from_world}`` and ``{frame key: focal in pixels}`` for the lines that give a focal.
    """
    if not path.exists():
        raise InputError("pseudo ground-truth file is missing", path, PGT_HINT)
    poses, focals = {}, {}
    for i, line in enumerate(path.read_text().splitlines()):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) < 8:
            raise InputError(f"line {i + 1}: expected 'name qw qx qy qz tx ty tz [f]', got {line!r}", path)
        try:
            vals = np.array([float(v) for v in parts[1:8]])
        except ValueError:
            raise InputError(f"line {i + 1}: non-numeric pose values", path) from None
        if not np.all(np.isfinite(vals)) or np.linalg.norm(vals[:4]) < 1e-6:
            raise InputError(f"line {i + 1}: invalid pose values {parts[1:8]}", path)
        key = _frame_key(parts[0])
        poses[key] = T_from_qt(vals[:4] / np.linalg.norm(vals[:4]), vals[4:7])
        if len(parts) > 8:
            try:
                f = float(parts[8])
            except ValueError:
                f = float("nan")
            if not (np.isfinite(f) and f > 0):
                raise InputError(f"line {i + 1}: focal length must be a positive number of pixels, got {parts[8]!r}",
                                 path)
            focals[key] = f
    return poses, focals


def read_pgt(path: Path) -> dict[str, np.ndarray]:
    """Pseudo-GT list -> {frame key: cam_from_world} (:func:`read_pgt_list` without the focal lengths)."""
    return read_pgt_list(path)[0]


def published_pgt_folder(pgt_dir, source: str) -> Path:
    """The ``pgt/<source>/7scenes`` folder of ``pgt_dir``: a clone of the published repository, its ``pgt``
    folder, or that folder itself."""
    d = Path(pgt_dir)
    if not d.is_dir():
        raise InputError("pseudo ground-truth folder does not exist or is not a folder", d, PGT_HINT)
    for cand in (d / "pgt" / source / "7scenes", d / source / "7scenes", d / "7scenes" if d.name == source else None):
        if cand is not None and cand.is_dir():
            return cand
    if d.name == "7scenes" or any(d.glob("*_train.txt")) or any(d.glob("*_test.txt")):
        if d.parent.name in POSE_SOURCES and d.parent.name != source:
            raise InputError(f"this is the {d.parent.name} pseudo-GT folder, but the pose source is {source}", d,
                             f"give {d.parent.parent / source / '7scenes'} or the folder that holds pgt/")
        return d
    raise InputError(f"no {source} pseudo-GT lists here: expected {d / 'pgt' / source / '7scenes'}/ (a clone of the "
                     f"published repository), {d / source / '7scenes'}/ (its pgt folder) or <scene>_train.txt and "
                     "<scene>_test.txt in the folder itself", d, PGT_HINT)


def _published_lists(folder: Path, scene: str) -> list[Path]:
    files = {split: folder / f"{scene}_{split}.txt" for split in ("train", "test")}
    for split, f in files.items():
        if not f.exists():
            raise InputError(f"the {split} list of scene {scene} is missing from this pseudo-GT folder (expected "
                             f"{f.name})", folder, PGT_HINT)
    return list(files.values())


def pgt_lists(root, scene_dir: Path, source: str, pgt_dir=None) -> list[Path]:
    """The pseudo-GT list files of a scene: the published ``<scene>_train.txt`` and ``<scene>_test.txt`` of
    ``pgt_dir`` (any form :func:`published_pgt_folder` takes); without it, those of ``root/pgt`` when that folder
    holds ``<source>/7scenes/``, else the scene's own ``pgt/<source>_<scene>.txt``."""
    name = scene_dir.name
    if pgt_dir is not None:
        return _published_lists(published_pgt_folder(pgt_dir, source), name)
    per_scene = scene_dir / "pgt" / f"{source}_{name}.txt"
    default = Path(root) / "pgt" / source / "7scenes"
    if default.is_dir():
        if any((default / f"{name}_{split}.txt").exists() for split in ("train", "test")) or not per_scene.exists():
            return _published_lists(default, name)
        logger.info("%s has no %s lists for %s: reading %s", default, source, name, per_scene)
    return [per_scene]


def read_pgt_lists(files: list[Path]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """:func:`read_pgt_list` of each file, merged; a frame listed in two files is an error."""
    poses, focals, where = {}, {}, {}
    for f in files:
        p, fo = read_pgt_list(f)
        both = sorted(set(p) & set(poses))
        if both:
            raise InputError(f"{len(both)} frame(s) are also in {where[both[0]].name}, e.g. {both[0]}", f)
        poses.update(p)
        focals.update(fo)
        where.update(dict.fromkeys(p, f))
    return poses, focals


def _frame_key(name: str) -> str:
    """'seq-01/frame-000010.color.png' -> 'seq-01/frame-000010' (extension-independent)."""
    return name.split(".")[0]


def estimate_color_from_depth(scene_dir: Path) -> np.ndarray | None:
    """colour_from_depth from pose.txt (depth camera) and the dSLAM list (colour camera), median over frames."""
    pgt = scene_dir / "pgt" / f"dslam_{scene_dir.name}.txt"
    if not pgt.exists():
        return None
    from scipy.spatial.transform import Rotation

    cw = read_pgt(pgt)
    Ts = []
    for key, T_cw in cw.items():
        pose = scene_dir / f"{key}.pose.txt"
        if pose.exists():
            Ts.append(T_cw @ read_pose_txt(pose))
    if not Ts:
        return None
    Ts = np.stack(Ts)
    R = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = np.median(Ts[:, :3, 3], axis=0)
    return out


def _color_path(seq_dir: Path, idx: str) -> Path:
    for ext in ("png", "jpg"):
        p = seq_dir / f"frame-{idx}.color.{ext}"
        if p.exists():
            return p
    raise InputError("colour image is missing (frame has a pose file; looked for .color.png and .color.jpg)",
                     seq_dir / f"frame-{idx}.color.png")


def _read_sequence(scene_dir: Path, seq: int, step: int, camera: Camera, dcam, c_from_d, conf, pgt, meta_name,
                   is_query: bool = False, bad: list | None = None, cams: dict | None = None):
    """Views of one sequence; ``cams`` holds the camera of each frame key whose pseudo-GT line gives a focal
    (others take ``camera``). A frame that cannot be used raises InputError, except:
    - a query whose ground-truth pose is invalid is kept with ``cam_from_world=None`` and the reason
      in ``meta["gt_error"]`` (it is skipped by the evaluation and reported, not counted);
    - with ``conf.skip_bad_frames`` a bad mapping frame is left out and the reason appended to ``bad``.
    """
    seq_dir = scene_dir / f"seq-{seq:02d}"
    if not seq_dir.is_dir():
        raise InputError(f"sequence folder seq-{seq:02d} listed in the split is missing", seq_dir)
    files = [p.name for p in seq_dir.iterdir()]
    idxs = sorted(m.group(1) for f in files if (m := _FRAME_RE.match(f)))
    if not idxs:
        raise InputError("sequence folder holds no frame-NNNNNN.pose.txt files", seq_dir)
    have = set(idxs)
    orphans = sorted(f for f in files if ".color." in f and f.split(".")[0][len("frame-"):] not in have)
    if orphans:  # frames are found by their pose files: say so rather than drop images silently
        logger.warning("%s: %d colour image(s) have no pose file and are not used, e.g. %s", seq_dir, len(orphans), orphans[0])
    views = []
    for idx in idxs[::step]:
        name = f"seq-{seq:02d}/frame-{idx}.color.png"  # hloc's name, whatever the extension on disk
        key = _frame_key(name)
        depth = seq_dir / f"frame-{idx}.depth.png"
        normal = seq_dir / f"frame-{idx}.normal.png"
        meta = {}
        try:
            try:
                color = _color_path(seq_dir, idx)
            except InputError:
                if not is_query:
                    raise
                # a missing query image is one failed query (reported by validate.check_scene), not a stop
                color = seq_dir / f"frame-{idx}.color.png"
            try:
                if conf.pose_source == "posetxt":
                    depth_from_world = invert_T(read_pose_txt(seq_dir / f"frame-{idx}.pose.txt"))
                    registered = conf.register_depth and c_from_d is not None
                    cfw = c_from_d @ depth_from_world if registered else depth_from_world
                else:
                    if key not in pgt:
                        raise InputError(f"no {conf.pose_source} pose for {name}", meta_name)
                    cfw = pgt[key]
            except InputError as e:
                if not is_query:
                    raise
                cfw, meta["gt_error"] = None, str(e)
                logger.warning("query %s has no valid ground-truth pose (%s): it will be skipped in the evaluation", name, e)
        except InputError as e:
            if is_query or not conf.skip_bad_frames:
                raise
            logger.warning("skipping bad mapping frame %s: %s", name, e)
            if bad is not None:
                bad.append(str(e))
            continue
        views.append(
            View(
                name=name,
                camera=(cams or {}).get(key, camera),
                cam_from_world=cfw,
                color_path=color,
                depth_path=depth if depth.exists() else None,
                normal_path=normal if normal.exists() else None,
                depth_camera=dcam if conf.register_depth else None,
                color_from_depth=c_from_d if conf.register_depth else None,
                meta=meta,
            )
        )
    return views


def _focal_cameras(camera: Camera, focals: dict[str, float]) -> dict[str, Camera]:
    """{frame key: ``camera`` with fx = fy = the key's focal}; one Camera object per distinct focal, ``camera``
    itself where the focal is its own."""
    by_focal = {}
    for f in sorted(set(focals.values())):
        same = camera.fx == f and camera.fy == f
        by_focal[f] = camera if same else Camera(camera.width, camera.height, (f, f, camera.cx, camera.cy))
    return {k: by_focal[f] for k, f in focals.items()}


def load_scene(root, scene: str, conf: SevenScenesConfig | None = None, dataset: str = "7scenes", **kw) -> Scene:
    """Load one 7-Scenes scene (or a synthetic scene in the same layout) as a :class:`Scene`."""
    conf = conf or SevenScenesConfig(**kw)
    if conf.pose_source not in POSE_SOURCES:
        raise InputError(f"unknown pose source {conf.pose_source!r}; choose one of {', '.join(POSE_SOURCES)}")
    if conf.mapping_step < 1 or conf.query_step < 1:
        raise InputError("mapping_step and query_step must be >= 1")
    scene_dir = find_scene_dir(root, scene)
    meta = {}
    info_path = scene_dir / "scene.json"
    if info_path.exists():
        try:
            meta = json.loads(info_path.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"scene.json is not valid JSON: {e}", info_path) from None
    if meta.get("intrinsics"):
        camera = Camera(int(meta["width"]), int(meta["height"]), tuple(meta["intrinsics"]))
    else:
        camera = COLOR_CAMERA
    if meta.get("depth_registered", False):
        dcam, c_from_d = None, None
    else:
        dcam = DEPTH_CAMERA
        c_from_d = conf.color_from_depth if conf.color_from_depth is not None else SEVENSCENES_COLOR_FROM_DEPTH
    pgt, cams, pgt_files = {}, {}, []
    focal_source = "scene.json" if meta.get("intrinsics") else f"the 7-Scenes colour camera (fx = fy = {camera.fx:g})"
    if conf.pose_source != "posetxt":
        pgt_files = pgt_lists(root, scene_dir, conf.pose_source, conf.pgt_dir)
        pgt, focals = read_pgt_lists(pgt_files)
        cams = _focal_cameras(camera, focals)
        where = ", ".join(str(f) for f in pgt_files)
        logger.info("%s: %s poses and focal lengths from %s", scene_dir.name, conf.pose_source, where)
        n_default = len(set(pgt) - set(focals))
        focal_source = f"the {conf.pose_source} pseudo-GT lines ({where})" + (
            f"; {n_default} line(s) give none and keep {focal_source}" if n_default else "")
    elif conf.pgt_dir is not None:
        raise InputError("pseudo-GT lists are given (--pgt) but the pose source is posetxt: choose --pose-source "
                         "sfm or dslam", conf.pgt_dir)
    # the train list for mapping frames, the test list for queries (one file in the per-scene layout)
    pgt_train, pgt_test = (pgt_files[0], pgt_files[-1]) if pgt_files else (None, None)
    train = read_split(scene_dir / "TrainSplit.txt")
    test = read_split(scene_dir / "TestSplit.txt")
    if set(train) & set(test):
        both = min(set(train) & set(test))
        raise InputError(f"sequence{both} is in both TrainSplit.txt and TestSplit.txt (mapping and query frames "
                         "would have the same names)", scene_dir / "TestSplit.txt")
    bad: list = []
    mapping = [
        v for s in train
        for v in _read_sequence(scene_dir, s, conf.mapping_step, camera, dcam, c_from_d, conf, pgt, pgt_train, False,
                                bad, cams=cams)
    ]
    query = [
        v for s in test
        for v in _read_sequence(scene_dir, s, conf.query_step, camera, dcam, c_from_d, conf, pgt, pgt_test, True,
                                cams=cams)
    ]
    if conf.query_list:
        wanted = [ln.split()[0] for ln in Path(conf.query_list).read_text().splitlines() if ln.strip()]
        by_key = {_frame_key(v.name): v for v in query}
        missing = [n for n in wanted if _frame_key(n) not in by_key]
        if missing:
            raise InputError(f"{len(missing)} listed queries are not in the test split, e.g. {missing[0]}", conf.query_list)
        query = [by_key[_frame_key(n)] for n in wanted]
    names = [v.name for v in mapping + query]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})[0]
        raise InputError(f"duplicate frame name {dup} in mapping and query splits", scene_dir)
    if not mapping:
        raise InputError("no mapping frames", scene_dir / "TrainSplit.txt")
    gt_mesh = scene_dir / "mesh.ply"
    logger.debug("loaded %s: %d mapping, %d query views", scene_dir, len(mapping), len(query))
    return Scene(
        name=scene_dir.name,
        dataset=dataset,
        root=scene_dir,
        mapping=mapping,
        query=query,
        pose_source=conf.pose_source,
        gt_mesh=gt_mesh if gt_mesh.exists() else None,
        depth_registered=bool(meta.get("depth_registered", False)) or conf.register_depth,
        meta={**meta, "color_from_depth": None if c_from_d is None else np.asarray(c_from_d).tolist(),
              "skipped_frames": bad, "pgt_files": [str(f) for f in pgt_files], "focal_source": focal_source},
    )
