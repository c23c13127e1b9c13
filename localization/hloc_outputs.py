"""Which of hloc's output files serve one scene: the SfM model, features, query matches and query pairs.

hloc's 7-Scenes pipeline (``hloc/pipelines/7Scenes/pipeline.py``) writes, per scene folder::

    sfm_sift/                                   reference model made from the 7-Scenes SIFT models
    sfm_superpoint+superglue/                   the learned features triangulated with known poses
    sfm_superpoint+superglue+depth/             the same, corrected with dense depth (--use_dense_depth)
    feats-superpoint-n4096-r1024.h5             features (float16 with as_half)
    <features>_matches-superglue_pairs-db-covis30.h5   matches of the covisibility pairs (mapping)
    <features>_matches-superglue_<scene>_top10.h5      matches of the query pairs
    pairs-db-covis30.txt, query_list_with_intrinsics.txt, results_{sparse,dense}.txt

and leaves the query pairs ``<scene>_top10.txt`` in the dataset's ``7scenes_densevlad_retrieval_top_10/``.
A matches file is named ``<features stem>_<matcher>_<pairs stem>.h5``, whatever the features and matcher
(SuperPoint + LightGlue, SIFT + NN-mutual, ...), which is what the rules below rest on.

Each file is chosen by a rule, or given by the user (an override); :class:`HlocFiles` records the choice and
why, for the log and ``results.json``:

- SfM model: a dense-depth model (``+depth``) when there is one, else a learned-feature model, ``sfm_sift``
  only when it is the only one (its keypoints are COLMAP's SIFT, which no features file of the tree holds).
- query pairs: a pairs file whose first image is a query of the scene, in the scene's output folder, else
  the dataset's retrieval folder (``ROOT/*retrieval*/<scene>_top*.txt``, inside the dataset root or beside it).
- query matches: the matches file named after those pairs (or, failing that, the one holding their first pair).
- features: the file the matches file's name starts with.

Then two checks, so a mismatch stops the run instead of giving wrong poses: the model's images have as many
2D points as the features file has keypoints (the model was triangulated from these features), and the
model's cameras lie where the scene's poses put them (:func:`check_world_frame`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from lipmap import InputError, logger

# a model folder holds one of these (COLMAP binary or text)
_MODEL_FILES = ("images.bin", "images.txt")
# median camera-centre gap (m) between the SfM model and the scene's poses above which they are in other frames
MAX_FRAME_GAP_M = 0.05


@dataclass
class HlocOutputs:
    """hloc's outputs for the scenes of a run: ``root/<scene>/`` per scene, and optional overrides.

    An override is a path; ``{scene}`` in it becomes the scene's name, and a relative path is taken in the
    scene's folder (``feats-superpoint-n4096-r1024.h5``) or, when not there, relative to ``cwd`` (the current
    directory where this object was made: workers elsewhere resolve the paths the user meant).
    """

    root: Path
    sfm: Optional[str] = None
    features: Optional[str] = None
    matches: Optional[str] = None
    pairs: Optional[str] = None
    cwd: Optional[Path] = None

    def __post_init__(self):
        self.cwd = Path(self.cwd) if self.cwd is not None else Path.cwd()
        self.root = (self.cwd / Path(self.root)).resolve()

    def scene_folder(self, scene_name: str) -> Path:
        return self.root / scene_name

    def override(self, what: str, scene_name: str) -> Optional[Path]:
        value = getattr(self, what)
        if value is None:
            return None
        p = Path(str(value).replace("{scene}", scene_name))
        if p.is_absolute():
            return p
        if (self.scene_folder(scene_name) / p).exists():
            return self.scene_folder(scene_name) / p
        return self.cwd / p


@dataclass
class HlocFiles:
    """The files chosen for one scene, and why each (``reasons``: what -> one sentence)."""

    sfm: Path
    features: Path
    matches: Path
    pairs: Path
    reasons: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {k: str(v) for k, v in asdict(self).items() if k != "reasons"} | {"reasons": dict(self.reasons)}


def as_hloc_outputs(hloc) -> Optional[HlocOutputs]:
    """``None``, a folder (``--hloc DIR``) or :class:`HlocOutputs` as :class:`HlocOutputs` (or None)."""
    if hloc is None or isinstance(hloc, HlocOutputs):
        return hloc
    return HlocOutputs(Path(hloc))


# ----------------------------------------------------------------------------------------------
# the rules
# ----------------------------------------------------------------------------------------------
def find_models(folder: Path, depth: int = 2) -> list[Path]:
    """Folders under ``folder`` (itself included, at most ``depth`` levels down) that hold a COLMAP model, the
    shallowest of each top-level folder (hloc's reconstruction leaves ``models/0`` inside the model it copies out)."""
    found, level = {}, [folder]
    for _ in range(depth + 1):
        nxt = []
        for d in level:
            top = (d.relative_to(folder).parts or ("",))[0]
            if top not in found and any((d / f).exists() for f in _MODEL_FILES):
                found[top] = d
            nxt += sorted(p for p in d.iterdir() if p.is_dir()) if d.is_dir() else []
        level = nxt
    return list(found.values())


def _model_rank(path: Path, folder: Path) -> int:
    """0: corrected with dense depth, 1: any other model but hloc's SIFT reference, 2: ``sfm_sift``."""
    name = (path.relative_to(folder).parts or (path.name,))[0].lower()
    if "+depth" in name or name.endswith("depth"):
        return 0
    return 2 if name == "sfm_sift" else 1


_RANK_WHY = {0: "the dense-depth model", 1: "the model triangulated from the features (no dense-depth model)",
             2: "hloc's SIFT reference model, the only model in the folder"}


def is_matches_file(path: Path) -> bool:
    """hloc names a matches file ``<features stem>_<matcher>_<pairs stem>.h5``: it starts with another .h5 file's
    stem and an underscore (or says 'match' in its name)."""
    return "match" in path.name.lower() or any(path.name.startswith(q.stem + "_") for q in path.parent.glob("*.h5")
                                               if q != path)


def choose_model(folder: Path, fits=None) -> tuple[Path, str]:
    """The model of the hloc folder by the rule of the module docstring; ``fits(model_dir) -> bool`` breaks a tie
    (the model triangulated from the chosen features)."""
    models = find_models(folder)
    if not models:
        raise InputError("no SfM model (a folder with images.bin) in the hloc folder", folder, "give one with --hloc-sfm")
    ranks = [_model_rank(m, folder) for m in models]
    best = min(ranks)
    top = [m for m, r in zip(models, ranks) if r == best]
    why = _RANK_WHY[best]
    if len(top) > 1 and fits is not None:
        top = [m for m in top if fits(m)] or top
        why += ", made from the chosen features"
    if len(top) > 1:
        raise InputError(f"several SfM models fit equally well: {[str(m.relative_to(folder)) for m in top]}", folder,
                         "choose one with --hloc-sfm")
    if len(models) > 1:
        others = [str(m.relative_to(folder)) for m in models if m != top[0]]
        why += f"; not {', '.join(others)}"
    return top[0], why


def _first_pair(path: Path) -> Optional[tuple[str, str]]:
    """The first ``name0 name1`` line of a text file, or None when it is not a pairs file."""
    try:
        with open(path, errors="replace") as f:
            for line in f:
                parts = line.split()
                if not parts or parts[0].startswith("#"):
                    continue
                return (parts[0], parts[1]) if len(parts) == 2 else None
    except OSError:
        return None
    return None


def _query_pairs_in(folder: Path, queries: set, pattern: str = "*.txt") -> list[Path]:
    if not folder.is_dir():
        return []
    out = []
    for p in sorted(folder.glob(pattern)):
        first = _first_pair(p)
        if first is not None and first[0] in queries:
            out.append(p)
    return out


def _dataset_retrieval_dirs(scene_root: Path) -> list[Path]:
    """The retrieval folders inside the dataset root and beside it (hloc: ``7scenes_densevlad_retrieval_top_10``)."""
    out = []
    for base in (scene_root.parent, scene_root.parent.parent):
        if base.is_dir():
            out += sorted(p for p in base.iterdir() if p.is_dir() and "retrieval" in p.name.lower())
    return out


def choose_pairs(folder: Path, scene, matches_files: list[Path]) -> tuple[Path, str]:
    queries = {v.name for v in scene.query}
    local = _query_pairs_in(folder, queries)
    named = [p for p in local if any(m.stem.endswith("_" + p.stem) for m in matches_files)]
    if len(named) == 1:
        return named[0], "the query pairs file in the hloc folder that a matches file is named after"
    if len(local) == 1:
        return local[0], "the only query pairs file in the hloc folder"
    if len(local) > 1:
        raise InputError(f"several query pairs files in the hloc folder: {[p.name for p in local]}", folder,
                         "choose one with --hloc-pairs")
    beside = []
    for d in _dataset_retrieval_dirs(Path(scene.root)):
        beside += _query_pairs_in(d, queries, f"{scene.name}_top*.txt") or _query_pairs_in(d, queries, f"{scene.name}*.txt")
    named = [p for p in beside if any(m.stem.endswith("_" + p.stem) for m in matches_files)]
    pick = named if len(named) == 1 else beside
    if len(pick) == 1:
        return pick[0], f"the retrieval pairs of the dataset ({pick[0].parent.name}/)"
    if not pick:
        raise InputError(f"no query pairs file: none in the hloc folder starts with a query of {scene.name}, and no "
                         f"<retrieval folder>/{scene.name}_top*.txt inside or beside the dataset root {Path(scene.root).parent}",
                         folder, "give it with --hloc-pairs (hloc: 7scenes_densevlad_retrieval_top_10/<scene>_top10.txt)")
    raise InputError(f"several query pairs files fit: {[str(p) for p in pick]}", folder, "choose one with --hloc-pairs")


def choose_matches(folder: Path, matches_files: list[Path], pairs: list[tuple[str, str]], pairs_path: Path) -> tuple[Path, str]:
    from .hloc_io import open_h5, pair_in_file

    named = [m for m in matches_files if m.stem.endswith("_" + pairs_path.stem)]
    if len(named) == 1:
        return named[0], f"the matches file named after the query pairs ({pairs_path.stem})"
    cands = named or matches_files
    if pairs:
        holding = []
        for m in cands:
            with open_h5(m) as fd:
                if pair_in_file(fd, *pairs[0]):
                    holding.append(m)
        if len(holding) == 1:
            return holding[0], f"the matches file that holds the query pairs' first pair {pairs[0]}"
        cands = holding or cands
    if not cands:
        raise InputError("no matches file (<features>_<matcher>_<pairs>.h5, or *.h5 with 'match' in its name) in the "
                         "hloc folder", folder,
                         "give it with --hloc-matches")
    raise InputError(f"cannot tell which matches file belongs to the query pairs {pairs_path.name}: "
                     f"{[m.name for m in cands]}", folder, "choose one with --hloc-matches")


def choose_features(folder: Path, matches: Path) -> tuple[Path, str]:
    feats = [p for p in sorted(folder.glob("*.h5")) if not is_matches_file(p)]
    named = [p for p in feats if matches.name.startswith(p.stem + "_")]
    if named:
        best = max(named, key=lambda p: len(p.stem))
        return best, "the features file the matches file is named after"
    if len(feats) == 1:
        return feats[0], "the only features file in the hloc folder"
    if not feats:
        raise InputError("no features file in the hloc folder (only matches files)", folder,
                         "give it with --hloc-features")
    raise InputError(f"cannot tell which features file the matches {matches.name} were made from: "
                     f"{[p.name for p in feats]}", folder, "choose one with --hloc-features")


def find_hloc_files(hloc: HlocOutputs, scene) -> HlocFiles:
    """The model, features, query matches and query pairs of ``scene`` in hloc's outputs (rules: module docstring)."""
    from .hloc_io import read_pairs

    folder = hloc.scene_folder(scene.name)
    if not folder.is_dir():
        raise InputError(f"hloc output folder for scene {scene.name} is missing", folder,
                         "--hloc takes the folder that holds one folder per scene, as hloc's outputs/7scenes/")
    reasons = {}
    matches_files = [p for p in sorted(folder.glob("*.h5")) if is_matches_file(p)]
    pairs = hloc.override("pairs", scene.name)
    if pairs is None:
        pairs, reasons["pairs"] = choose_pairs(folder, scene, matches_files)
    else:
        reasons["pairs"] = "given (--hloc-pairs)"
    pair_list = read_pairs(pairs)
    matches = hloc.override("matches", scene.name)
    if matches is None:
        matches, reasons["matches"] = choose_matches(folder, matches_files, pair_list, pairs)
    else:
        reasons["matches"] = "given (--hloc-matches)"
    features = hloc.override("features", scene.name)
    if features is None:
        features, reasons["features"] = choose_features(folder, matches)
    else:
        reasons["features"] = "given (--hloc-features)"
    sfm = hloc.override("sfm", scene.name)
    if sfm is None:
        sfm, reasons["sfm"] = choose_model(folder, fits=lambda m: _made_from(m, features))
    else:
        reasons["sfm"] = "given (--hloc-sfm)"
    for what, p in (("SfM model", sfm), ("features file", features), ("matches file", matches), ("pairs file", pairs)):
        if not Path(p).exists():
            raise InputError(f"the {what} is missing", p)
    files = HlocFiles(Path(sfm), Path(features), Path(matches), Path(pairs), reasons)
    for what in ("sfm", "features", "matches", "pairs"):
        logger.info("hloc %s for %s: %s (%s)", what, scene.name, getattr(files, what), reasons[what])
    return files


# ----------------------------------------------------------------------------------------------
# checks
# ----------------------------------------------------------------------------------------------
def _made_from(sfm_dir: Path, features_h5: Path) -> bool:
    from .hloc_io import ModelIndex, read_sfm

    try:
        check_model_features(ModelIndex(read_sfm(sfm_dir), sfm_dir), features_h5, sfm_dir, sample=3)
    except InputError:
        return False
    return True


def check_model_features(model, features_h5: Path, sfm_dir: Path, sample: int = 20) -> None:
    """InputError when the model's images do not have one 2D point per keypoint of the features file.

    hloc's triangulation gives every image of the model all its keypoints as 2D points, so the counts agree;
    a model triangulated from other features (``sfm_sift`` beside SuperPoint features) indexes other keypoints.
    """
    import h5py

    names = model.image_names()
    with h5py.File(str(features_h5), "r") as fd:
        shared = [n for n in names if n in fd and "keypoints" in fd[n]]
        if not shared:
            raise InputError(f"the SfM model's images are not in the features file {features_h5} (e.g. {names[:1]})",
                             sfm_dir, "model and features from different runs? choose with --hloc-sfm / --hloc-features")
        step = max(1, len(shared) // sample)
        for n in shared[::step]:
            n_kp = len(fd[n]["keypoints"])
            n_2d = model.num_points2D(n)
            if n_kp != n_2d:
                raise InputError(f"image {n} has {n_2d} 2D points in the SfM model but {n_kp} keypoints in "
                                 f"{features_h5.name}: the model was not triangulated from these features", sfm_dir,
                                 "choose the model made from them with --hloc-sfm (sfm_sift holds COLMAP's SIFT "
                                 "keypoints, not hloc's features)")


def frame_gap(model, views) -> tuple[float, int]:
    """Median distance (m) between the camera centres of the model's images and those of ``views`` with the same
    names, and how many images they share."""
    from lipmap.poses import camera_center

    gaps = [np.linalg.norm(camera_center(model.cam_from_world(v.name)) - camera_center(v.cam_from_world))
            for v in views if v.name in model and v.cam_from_world is not None]
    return (float(np.median(gaps)) if gaps else float("nan")), len(gaps)


def check_world_frame(model, scene, sfm_dir: Path, other_sources=None) -> float:
    """The median camera-centre gap between the SfM model and the scene's mapping poses; InputError above
    :data:`MAX_FRAME_GAP_M`, naming the gap and the pose source(s) whose poses fit the model.

    ``other_sources``: {pose source: mapping views} to compare with when the scene's own poses do not fit.
    """
    gap, n = frame_gap(model, scene.mapping)
    if n == 0:
        raise InputError(f"the SfM model shares no image with the mapping views of {scene.name} "
                         f"(model: {model.image_names()[:1]}, scene: {[v.name for v in scene.mapping[:1]]})", sfm_dir,
                         "hloc names 7-Scenes images seq-XX/frame-XXXXXX.color.png, relative to the scene folder")
    if gap <= MAX_FRAME_GAP_M:
        return gap
    fits = []
    for source, views in (other_sources or {}).items():
        g, k = frame_gap(model, views)
        if k and g <= MAX_FRAME_GAP_M:
            fits.append(f"{source} ({100 * g:.1f} cm)")
    hint = (f"its poses fit --pose-source {' or '.join(fits)}" if fits else
            "no pose source fits it: was the model made for another scene, or with poses in another world frame?")
    raise InputError(f"the SfM model's cameras lie {100 * gap:.1f} cm (median over {n} shared mapping images) from the "
                     f"scene's {scene.pose_source} poses: the model is in another world frame, and its points would be "
                     f"localized against a line map in this one", sfm_dir, hint)
