"""Reader for the official 7-Scenes layout (also used for synthetic scenes written in that layout).

    <root>/<scene>/TrainSplit.txt, TestSplit.txt      lines "sequenceN"
    <root>/<scene>/seq-NN/frame-NNNNNN.color.{png,jpg}, .depth.png, .pose.txt (camera-to-world)
    <root>/<scene>/pgt/{dslam,sfm}_<scene>.txt        optional pseudo ground truth (world-to-camera, colour)

Pose sources (same source for mapping and evaluation; never mixed):
- ``posetxt``: pose.txt, which is the DEPTH camera's pose (KinectFusion). With depth registration on,
  the colour camera's pose is ``colour_from_depth @ depth_from_world``; without it, pose.txt is used for
  the colour camera as most pipelines do.
- ``dslam`` / ``sfm``: the pseudo ground-truth lists (colour camera, COLMAP world-to-camera).
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
    "(unzip each scene and its seq-NN.zip files under ROOT/<scene>/)"
)
POSE_SOURCES = ("posetxt", "dslam", "sfm")
COLOR_CAMERA = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))
DEPTH_CAMERA = Camera(640, 480, (585.0, 585.0, 320.0, 240.0))
_FRAME_RE = re.compile(r"^frame-(\d{6})\.pose\.txt$")


@dataclass
class SevenScenesConfig:
    pose_source: str = "posetxt"  # posetxt | dslam | sfm
    register_depth: bool = True
    mapping_step: int = 1  # keep every k-th mapping frame
    query_step: int = 1
    query_list: str | None = None  # hloc list_test.txt: restrict queries to these names
    color_from_depth: np.ndarray | None = None  # override the Kinect depth-to-colour extrinsic
    skip_bad_frames: bool = False  # a bad MAPPING frame is skipped with a warning instead of stopping


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


def read_pgt(path: Path) -> dict[str, np.ndarray]:
    """Pseudo-GT list: ``seq-XX/frame-NNNNNN.color.png qw qx qy qz tx ty tz f`` -> {stem: cam_from_world}."""
    if not path.exists():
        raise InputError("pseudo ground-truth file is missing", path)
    out = {}
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
        out[_frame_key(parts[0])] = T_from_qt(vals[:4] / np.linalg.norm(vals[:4]), vals[4:7])
    return out


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
                   is_query: bool = False, bad: list | None = None):
    """Views of one sequence. A frame that cannot be used raises InputError, except:
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
                camera=camera,
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
    pgt, pgt_path = {}, None
    if conf.pose_source != "posetxt":
        pgt_path = scene_dir / "pgt" / f"{conf.pose_source}_{scene_dir.name}.txt"
        pgt = read_pgt(pgt_path)
    train = read_split(scene_dir / "TrainSplit.txt")
    test = read_split(scene_dir / "TestSplit.txt")
    if set(train) & set(test):
        both = min(set(train) & set(test))
        raise InputError(f"sequence{both} is in both TrainSplit.txt and TestSplit.txt (mapping and query frames "
                         "would have the same names)", scene_dir / "TestSplit.txt")
    bad: list = []
    mapping = [
        v for s in train
        for v in _read_sequence(scene_dir, s, conf.mapping_step, camera, dcam, c_from_d, conf, pgt, pgt_path, False, bad)
    ]
    query = [
        v for s in test for v in _read_sequence(scene_dir, s, conf.query_step, camera, dcam, c_from_d, conf, pgt, pgt_path, True)
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
              "skipped_frames": bad},
    )
