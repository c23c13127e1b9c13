"""The built-in point source: SIFT, covisible pairs, matching and known-pose triangulation on the mapping side;
SIFT, retrieval and matching on the query side, each step an hloc-layout artifact that later runs reuse.

    extract_sift(views, features_h5)                  -> features.h5   (pycolmap SIFT)
    pairs_from_poses(mapping_views, pairs_txt)        -> pairs file    (covisible mapping pairs)
    match_features(pairs, features_h5, matches_h5)    -> matches.h5    (mutual NN + Lowe ratio)
    triangulate_map(mapping_views, ..., sfm_dir)      -> sfm/          (COLMAP model, KNOWN poses)
    point_matches_for_query(query, retrieved, ...)    -> PointMatches  (hloc localize_sfm's 2D-3D)

Because the files are hloc's, any step can be replaced by hloc's own output.
"""
from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Optional, Sequence

from lipmap.artifacts import Stamp, reuse, scene_key, variant_dir, views_key, write_stamp

from ..hloc_io import ModelIndex, pairs_by_query, read_pairs, read_sfm
from .config import PointsConfig, get_conf
from .features import extract_sift
from .matches import PointMatches, point_matches_for_query
from .matching import match_features
from .pairs import pairs_from_poses
from .retrieval import RetrievalConfig, pairs_from_retrieval
from .retrieval import get_conf as retrieval_conf
from .triangulation import triangulate_map


def build_point_map(mapping_views: Sequence, out_dir, conf: Optional[PointsConfig] = None, overwrite: bool = False) -> dict:
    """Mapping side of the built-in pipeline: SIFT, covisible pairs, matches, triangulation.

    Returns:
        dict of artifact paths: ``features``, ``pairs``, ``matches``, ``sfm`` and per-step
        ``timings`` (seconds; 0 when a step was skipped).
    """
    conf = conf or PointsConfig()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    features = out_dir / f"feats-{conf.sift.name}.h5"
    pairs = out_dir / f"pairs-db-covis{conf.pairs.num_neighbors}.txt"
    matches = out_dir / f"feats-{conf.sift.name}_{conf.match.name}_{pairs.stem}.h5"
    sfm = out_dir / f"sfm_{conf.sift.name}_{conf.match.name}"
    timings = {}
    t = time.time()
    extract_sift(mapping_views, features, conf.sift, overwrite)
    timings["extract"] = time.time() - t
    t = time.time()
    pairs_stamp = Stamp("pairs-covisible", {"pairs": asdict(conf.pairs), "views": views_key(mapping_views)})
    if not reuse(pairs, pairs_stamp, overwrite, "covisible pairs", replace_stale=True):
        pairs_from_poses(mapping_views, pairs, conf.pairs)
        write_stamp(pairs, pairs_stamp)
    timings["pairs"] = time.time() - t
    t = time.time()
    match_features(pairs, features, matches, conf.match, overwrite)
    timings["match"] = time.time() - t
    t = time.time()
    sfm_stamp = Stamp("sfm", {"triangulation": asdict(conf.triangulation), "sift": asdict(conf.sift),
                              "match": asdict(conf.match), "pairs": pairs_stamp.digest, "views": views_key(mapping_views)})
    if not reuse(sfm, sfm_stamp, overwrite, "triangulation", replace_stale=True):
        triangulate_map(mapping_views, features, pairs, matches, sfm, conf.triangulation, overwrite=True)
        write_stamp(sfm, sfm_stamp)
    timings["triangulate"] = time.time() - t
    return {"features": features, "pairs": pairs, "matches": matches, "sfm": sfm, "timings": timings}


def match_queries(
    query_views: Sequence,
    mapping_names: Sequence[str],
    features_h5,
    out_dir,
    conf: Optional[PointsConfig] = None,
    retrieval=None,
    pairs=None,
    overwrite: bool = False,
) -> dict:
    """Query side: SIFT on the queries (into the mapping ``features_h5``), retrieval (or a given
    pairs file), matching against the retrieved mapping images.

    Args:
        retrieval: :class:`~localization.points.retrieval.RetrievalConfig` (default VLAD top-10) - unused
            when ``pairs`` is given.
        pairs: an existing query pairs file / list to use instead of retrieval.

    Returns:
        dict with ``pairs`` (path), ``matches`` (path), ``timings`` (seconds per step).
    """

    conf = conf or PointsConfig()
    out_dir = Path(out_dir)
    timings = {}
    t = time.time()
    extract_sift(query_views, features_h5, conf.sift, overwrite)
    timings["extract"] = time.time() - t
    t = time.time()
    if pairs is None:
        rconf = retrieval or RetrievalConfig()
        pairs = out_dir / f"pairs-query-{rconf.name}-top{rconf.num_retrieved}_{Path(features_h5).stem}.txt"
        pairs_from_retrieval([v.name for v in query_views], list(mapping_names), features_h5, pairs, rconf, overwrite=overwrite)
    timings["retrieval"] = time.time() - t
    pairs_name = Path(pairs).stem if isinstance(pairs, (str, Path)) else "pairs-query"
    matches = out_dir / f"feats-{conf.sift.name}_{conf.match.name}_{pairs_name}.h5"
    t = time.time()
    match_features(pairs, features_h5, matches, conf.match, overwrite)
    timings["match"] = time.time() - t
    return {"pairs": pairs, "matches": matches, "timings": timings}



class BuiltinPoints:
    """SIFT + known-pose triangulation + retrieval of one scene, all cached in a variant folder of ``scene_dir``
    named by the settings (``points-<preset>-<digest>``).

    Args:
        scene: :class:`lipmap.scene.Scene` (its mapping views are triangulated, its queries matched).
        points: a :mod:`localization.points` preset name (or config); retrieval: a retrieval preset name (or config);
        num_retrieved: database images per query; seed: of the retrieval's k-means.
    """

    def __init__(self, scene, scene_dir: Path, points="sift-n4096", retrieval="vlad64", num_retrieved: int = 10,
                 seed: int = 0, overwrite: bool = False):
        pconf = get_conf(points)
        rconf = replace(retrieval_conf(retrieval), num_retrieved=num_retrieved, seed=seed)
        self.stamp = Stamp("points", {"points": asdict(pconf), "retrieval": asdict(rconf), "scene": scene_key(scene),
                                      "queries": views_key(scene.query)})
        name = points if isinstance(points, str) else "custom"
        out_dir = self.folder = variant_dir(scene_dir, f"points-{name}", self.stamp)
        t = time.time()
        self.map = build_point_map(scene.mapping, out_dir, pconf, overwrite)
        t_map = time.time() - t
        q = match_queries(scene.query, [v.name for v in scene.mapping], self.map["features"], out_dir, pconf,
                          retrieval=rconf, overwrite=overwrite)
        # the mapping side (SIFT, pairs, triangulation) and the query side (SIFT, retrieval, matching) apart
        self.timings = {"point_map_s": t_map, "query_points_s": time.time() - t - t_map}
        self.features, self.matches = self.map["features"], q["matches"]
        self.retrieved = pairs_by_query(read_pairs(q["pairs"]))
        self.model = ModelIndex(read_sfm(self.map["sfm"]), self.map["sfm"])
        self.info = {}

    def matches_for(self, name: str) -> PointMatches:
        """The 2D-3D point matches of query ``name``."""
        return point_matches_for_query(name, self.retrieved.get(name, []), self.features, self.matches, self.model)

    def retrieved_for(self, name: str) -> list:
        """The database images retrieved for query ``name``, best first."""
        return list(self.retrieved.get(name, []))
