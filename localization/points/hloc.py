"""hloc's outputs as a point source: one scene's SfM model, features, query matches and query pairs, chosen in
hloc's output tree by rule or given (:mod:`localization.hloc_outputs`), and checked against the scene."""
from __future__ import annotations

from pathlib import Path

from lipmap import InputError
from lipmap.artifacts import Stamp

from .. import hloc_outputs as ho
from ..hloc_io import ModelIndex, read_pairs, read_sfm
from .matches import PointMatches, point_matches_from_hloc


class HlocPoints:
    """The point source of one scene from hloc's files (``hloc``: a folder or
    :class:`~localization.hloc_outputs.HlocOutputs`)."""

    def __init__(self, hloc, scene):
        hloc = ho.as_hloc_outputs(hloc)
        self.files = ho.find_hloc_files(hloc, scene)
        self.sfm, self.features, self.matches = self.files.sfm, self.files.features, self.files.matches
        self.pairs_file = self.files.pairs
        self.pairs = read_pairs(self.pairs_file)
        self.model = ModelIndex(read_sfm(self.sfm), self.sfm)
        ho.check_model_features(self.model, self.features, self.sfm)
        self.frame_gap_m = ho.check_world_frame(self.model, scene, self.sfm, _other_pose_sources(scene))
        self.timings = {}
        self.folder = hloc.scene_folder(scene.name)
        self.info = {"hloc": self.files.to_json(), "frame_gap_cm": round(100 * self.frame_gap_m, 2)}
        # hloc's files are the user's: their paths and sizes stand for their content
        self.stamp = Stamp("points", {"hloc": [(str(Path(p).resolve()), Path(p).stat().st_size) for p in
                                               (self.features, self.matches, self.pairs_file, _model_file(self.sfm))]})

    def retrieved_for(self, name: str) -> list:
        """The database images paired with query ``name`` in the pairs file, in file order."""
        return [b for a, b in self.pairs if a == name]

    def matches_for(self, name: str) -> PointMatches:
        """The 2D-3D point matches of query ``name``."""
        return point_matches_from_hloc(name, self.sfm, self.features, self.matches, self.pairs, model=self.model,
                                       pairs_name=self.pairs_file)


def _model_file(sfm_dir: Path) -> Path:
    """The file of a COLMAP model whose size stands for its 3D points (binary or text)."""
    return next((sfm_dir / f for f in ("points3D.bin", "points3D.txt") if (sfm_dir / f).exists()), sfm_dir / "images.bin")


def _other_pose_sources(scene) -> dict:
    """{pose source: mapping views} of the scene under each other pose source that loads (for the frame message)."""
    from lipmap.datasets import load_scene

    out = {}
    if scene.dataset != "7scenes":
        return out
    for source in ("posetxt", "dslam", "sfm"):
        if source == scene.pose_source:
            continue
        try:
            out[source] = load_scene(scene.dataset, Path(scene.root).parent, scene.name, pose_source=source).mapping
        except InputError:
            continue
    return out
