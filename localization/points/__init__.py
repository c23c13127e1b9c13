"""2D-3D point matches of query images, from one of two point sources behind one interface:

- :class:`BuiltinPoints` (:mod:`.builtin`): a SIFT pipeline with hloc-shaped steps, each an artifact in hloc's
  layout - features (:mod:`.features`), covisible pairs (:mod:`.pairs`), matching (:mod:`.matching`), known-pose
  triangulation (:mod:`.triangulation`) and retrieval (:mod:`.retrieval`);
- :class:`HlocPoints` (:mod:`.hloc`): hloc's own output tree.

A point source has ``matches_for(query) -> PointMatches`` (:mod:`.matches`), ``retrieved_for(query)`` (database
images, best first), ``model`` (:class:`~localization.hloc_io.ModelIndex`), ``stamp`` (what made it), ``folder``,
``timings`` and ``info``. :func:`open_points` gives a scene's.

Pixel convention: keypoints in memory are COLMAP's (pixel centre at +0.5); the files hold hloc's (integer
centres) and :mod:`localization.hloc_io` converts.
"""
from __future__ import annotations

from pathlib import Path
from typing import Protocol

from .builtin import BuiltinPoints, build_point_map, match_queries
from .config import MatchConfig, PairsConfig, PointsConfig, SiftConfig, TriangulationConfig, confs, get_conf
from .features import extract_sift, sift_features
from .hloc import HlocPoints
from .matches import PointMatches, point_matches_for_query, point_matches_from_hloc
from .matching import match_features, mutual_nn_ratio
from .pairs import frustum_overlap, pairs_from_poses
from .triangulation import fundamental_from_poses, model_stats, sampson_distance, triangulate_map


class PointSource(Protocol):
    """What the localization loop asks of a point source."""

    stamp: object  # lipmap.artifacts.Stamp: the settings and inputs that made it
    folder: Path
    timings: dict
    info: dict

    def matches_for(self, name: str) -> PointMatches: ...

    def retrieved_for(self, name: str) -> list: ...


def open_points(scene, out_dir: Path, points: str = "sift-n4096", retrieval: str = "vlad64", num_retrieved: int = 10,
                seed: int = 0, hloc=None, overwrite: bool = False) -> PointSource:
    """The scene's point source: hloc's files when ``hloc`` (a folder holding one folder per scene, or
    :class:`~localization.hloc_outputs.HlocOutputs`) is given, else the built-in one, made or reused under ``out_dir``."""
    if hloc:
        return HlocPoints(hloc, scene)
    return BuiltinPoints(scene, out_dir, points, retrieval, num_retrieved, seed, overwrite)


__all__ = [
    "PointSource", "open_points", "BuiltinPoints", "HlocPoints", "PointMatches", "point_matches_for_query",
    "point_matches_from_hloc", "build_point_map", "match_queries", "SiftConfig", "MatchConfig", "PairsConfig",
    "TriangulationConfig", "PointsConfig", "confs", "get_conf", "sift_features", "extract_sift", "frustum_overlap",
    "pairs_from_poses", "mutual_nn_ratio", "match_features", "sampson_distance", "fundamental_from_poses",
    "triangulate_map", "model_stats",
]
