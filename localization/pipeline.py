"""Per-scene localization benchmark: map (if needed), 2D-3D points, point-only pose, line query,
point+line pose, evaluation. Every step caches its artifact, stamped with the settings that made it;
per-query results go to a journal so an interrupted run resumes where it stopped.

    OUT/<dataset>/<scene>/
        map-<method>-<preset>-<digest>/         the line map of one mapping variant (lipmap.mapping.pipeline):
                                                linemap.h5, lines2d.h5, linemap.ply, renders
        planes-<preset>-<digest>/               planes.h5, planes.ply: one plane optimization, shared by the map
                                                variants that differ only after it (lipmap.mapping.joint)
        points-<preset>-<digest>/               SIFT features, pairs, matches, sfm model (built-in points)
        lines2d_query-<digest>.h5               2D lines of the queries (the mapping's detector)
        queries-<digest>.jsonl                  per-query journal of one configuration (resume)
        results_point.txt, results_point_line.txt   hloc format (name qw qx qy qz tx ty tz), latest run
        results.json                            per-query errors, inliers, timings; summary; which map
                                                and points the run used
    OUT/<dataset>/results.json, summary.md      all scenes, paper table beside ours
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from tqdm import tqdm

from lipmap import InputError, logger
from lipmap import geometry as geo
from lipmap.artifacts import Stamp, digest, scene_key, source_digest, variant_dir, views_key
from lipmap.imageio import write_text_atomic
from lipmap.poses import pose_errors

from . import evaluate as ev
from .estimate import (PointLinePoseConfig, PointPoseConfig, estimate_pose_point_line, estimate_pose_points,
                       refine_pose_point_line, subsample_matches)
from .hloc_outputs import HlocOutputs, as_hloc_outputs
from .hypotheses import HypothesisConfig, line_verified_poses
from .linequery import LineQuery, LineQueryConfig, correct_line_matches


# hloc-format results of each method (name qw qx qy qz tx ty tz, cam_from_world)
RESULT_FILES = {"point": "results_point.txt", "point+line": "results_point_line.txt"}


@dataclass
class LineRescueConfig:
    """Lines for the queries whose points alone give no trustworthy pose.

    A point-only pose with fewer than ``weak_inliers`` inliers (or none) is too far off for the narrow gates of
    the line query, and with few matches a wrong P3P pose often explains as many of them as the right one. Lines
    then start from several poses instead: that pose when it exists, the P3P poses of the point matches that the
    most map lines agree with (``hypotheses``, :mod:`localization.hypotheses`), and optionally the poses of the
    ``prior_views`` best retrieved database images. From each, every query line takes its ``candidates`` nearest
    map lines within the wide gate (no ambiguity test), and PnPL's RANSAC over all point matches and these
    candidates picks a pose; the pose with the most point + line inliers (at least ``min_line_inliers`` lines)
    starts the usual narrowing refinement, with ``max_point_error`` for the points.
    """

    weak_inliers: int = 20  # 0: off. Ten point matches are always weak; a full query (hundreds of inliers) never
    prior_views: int = 0  # retrieved images' poses as starts (on the held-out split they lie ~90 cm off: no gain)
    # P3P poses of the point matches that the most map lines agree with, as starts (localization.hypotheses)
    hypotheses: HypothesisConfig = field(default_factory=HypothesisConfig)
    # (px, deg[, candidates]) per stage: the first from every prior, the next from the best pose; the second bridges
    # the wide gate and the 8 px of the narrowing rounds, which a pose 5-10 cm off missed (docs/localization.md, `-sweep2`
    # variants). From that pose each query line's nearest map line is enough: 20 % less time (`-speed2`)
    gates: tuple = ((30.0, 5.0), (15.0, 3.0, 1))
    candidates: int = 3  # per query line, in a stage that does not name its own
    min_length_px: float = 20.0  # query lines shorter than this stay out of the rescue (the line query's own minimum)
    max_query_lines: int = 0  # only the longest this many query lines enter the rescue (0: all)
    min_line_inliers: int = 6
    max_iterations: int = 1000  # of each start's PnPL RANSAC (2,000 and 10,000: 1.6x and 6x the time, no more accurate)
    # px, the point threshold of a rescued query's PnPL: with ten points a wrong match within 12 px pulls the pose,
    # while with hundreds 6 px costs accuracy (held-out, all matches: 2.51 cm against 1.96)
    max_point_error: float = 6.0
    # starts this close to an earlier one (and same_pose_deg) are skipped: within the wide gate they find the same
    # lines (held-out, 10 matches: 15 % less time than at 3 cm / 1 deg, same accuracy; docs/localization.md, `-speed2` variants)
    same_pose_m: float = 0.10
    same_pose_deg: float = 3.0
    # "ransac": each start's candidates go through PoseLib's PnPL RANSAC, and the later ``gates`` refine the best pose;
    # "refine": each start goes through every stage of ``refine_gates`` as a robust refinement (Cauchy, scale
    # ``refine_scale`` x the gate) of its nearest candidates, without RANSAC: half the time, a higher median (docs/localization.md)
    solver: str = "ransac"
    refine_gates: tuple = ((30.0, 5.0, 1), (15.0, 3.0, 1), (8.0, 3.0, 1))
    refine_scale: float = 0.25


@dataclass
class LocalizationConfig:
    seed: int = 0
    max_point_matches: Optional[int] = None  # seeded random subset per query (same for both methods)
    match_seed: Optional[int] = None  # seed of that subset (None: ``seed``); vary it alone to average over draws
    points: str = "sift-n4096"  # localization.points preset (built-in SIFT)
    retrieval: str = "vlad64"  # localization.retrieval preset
    num_retrieved: int = 10
    point_pose: PointPoseConfig = field(default_factory=PointPoseConfig)
    point_line_pose: PointLinePoseConfig = field(default_factory=PointLinePoseConfig)
    line_query: LineQueryConfig = field(default_factory=LineQueryConfig)
    line_iters: int = 2  # line query -> refine, repeated with the refined pose (when line_gates is empty)
    # per iteration (max_dist_px, max_angle_deg) gates of the line query, overriding line_iters and the gates of
    # line_query: wide while the pose is the point-only one, narrower once lines have refined it; () = fixed gates
    line_gates: tuple = ((8.0, 3.0), (4.0, 2.0), (2.0, 1.0))
    line_rescue: LineRescueConfig = field(default_factory=LineRescueConfig)
    # (m, deg): a narrowing round whose pose moves farther than this from the pose it started from is not taken (the
    # rounds refine a pose; a RANSAC jump is a different solution that few right matches support). () = off.
    # Held-out split, 5 matches, 20 draws: 14.73 cm median against 15.23 without (docs/localization.md, `-step` variants)
    max_line_step: tuple = (0.3, 5.0)
    mapping: str = "fast"  # lipmap.mapping.pipeline preset
    # the LiP-Map map: with scarce points it localizes better than lift's on both mini scenes and the held-out split
    # (lift's is ahead on the synthetic room; README, docs/localization.md)
    map_method: str = "lipmap"

    def digest(self) -> str:
        return digest(asdict(self), 10)


# ----------------------------------------------------------------------------------------------
# point sources
# ----------------------------------------------------------------------------------------------
class BuiltinPoints:
    """SIFT + known-pose triangulation + VLAD retrieval, all cached under ``out_dir``."""

    def __init__(self, scene, scene_dir: Path, conf: LocalizationConfig, overwrite=False):
        from . import points as pts
        from .hloc_io import ModelIndex, pairs_by_query, read_pairs, read_sfm
        from .retrieval import get_conf as retrieval_conf

        pconf = pts.get_conf(conf.points)
        rconf = replace(retrieval_conf(conf.retrieval), num_retrieved=conf.num_retrieved, seed=conf.seed)
        self.stamp = Stamp("points", {"points": asdict(pconf), "retrieval": asdict(rconf), "scene": scene_key(scene),
                                      "queries": views_key(scene.query)})
        out_dir = self.folder = variant_dir(scene_dir, f"points-{conf.points}", self.stamp)
        t = time.time()
        self.map = pts.build_point_map(scene.mapping, out_dir, pconf, overwrite)
        t_map = time.time() - t
        q = pts.match_queries(scene.query, [v.name for v in scene.mapping], self.map["features"], out_dir, pconf,
                              retrieval=rconf, overwrite=overwrite)
        # the mapping side (SIFT, pairs, triangulation) and the query side (SIFT, retrieval, matching) apart
        self.timings = {"point_map_s": t_map, "query_points_s": time.time() - t - t_map}
        self.features, self.matches = self.map["features"], q["matches"]
        self.retrieved = pairs_by_query(read_pairs(q["pairs"]))
        self.model = ModelIndex(read_sfm(self.map["sfm"]), self.map["sfm"])
        self._pts = pts

    def matches_for(self, name: str):
        return self._pts.point_matches_for_query(name, self.retrieved.get(name, []), self.features, self.matches, self.model)

    def retrieved_for(self, name: str) -> list:
        """The database images retrieved for query ``name``, best first."""
        return list(self.retrieved.get(name, []))


class HlocPoints:
    """hloc's outputs for one scene: an SfM model, features, the query matches and the query pairs, chosen in hloc's
    output tree by rule or given (:mod:`localization.hloc_outputs`), and checked against the scene."""

    def __init__(self, hloc, scene):
        from . import hloc_outputs as ho
        from .hloc_io import ModelIndex, read_pairs, read_sfm

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

    def matches_for(self, name: str):
        from .points import point_matches_from_hloc

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


# ----------------------------------------------------------------------------------------------
# per-query localization
# ----------------------------------------------------------------------------------------------
def localize_query(name, camera, points, lines2d, lq: LineQuery, conf: LocalizationConfig, cam_from_world_gt=None,
                   trace: Optional[list] = None) -> dict:
    """Point-only and point+line poses of one query of a benchmark run, from its point source. Never raises:
    failures are recorded.

    The point matches come from ``points.matches_for(name)``, limited to ``conf.max_point_matches`` (a seeded draw);
    the rest is :func:`localize_matches`. ``trace`` (a list) also receives the point matches as
    ``{"point_matches": pm}``.
    """
    rec = {"name": name, "point": {"success": False}, "point+line": {"success": False}}
    t0 = time.perf_counter()
    try:
        pm = points.matches_for(name)
    except InputError as e:
        rec["error"] = str(e)
        return rec
    idx = subsample_matches(len(pm), conf.max_point_matches, conf.seed if conf.match_seed is None else conf.match_seed, name)
    pm = pm.subset(idx)
    if trace is not None:
        trace.append({"point_matches": pm})
    return localize_matches(pm, lines2d, camera, lq, conf, name, points, cam_from_world_gt, trace, t0)[0]


def localize_matches(pm, lines2d, camera, lq: LineQuery, conf: LocalizationConfig, name: str = "query", points=None,
                     cam_from_world_gt=None, trace: Optional[list] = None, t0: Optional[float] = None) -> tuple:
    """Point-only and point+line poses of one query from its 2D-3D point matches and 2D lines: the one
    implementation behind the benchmark loop (:func:`localize_query`) and the per-query API
    (:class:`localization.api.Localizer`). Never raises for a bad query: failures are recorded.

    Args:
        pm: :class:`~localization.points.PointMatches` (p2d COLMAP pixels, p3d world).
        lines2d: :math:`(L, 4)` query segments, COLMAP pixels.
        points: the point source (for retrieved images' poses as rescue starts, ``LineRescueConfig.prior_views``).
        cam_from_world_gt: with it, the line matches of the last refinement (and its PnPL line inliers) are checked
            (:func:`~localization.linequery.correct_line_matches`) - after the timing, so the check costs nothing.
        trace: a list receiving the line rescue's starts and their outcomes (:func:`rescue_pose`).
        t0: ``time.perf_counter()`` when the query started (default: now); its times count from there.

    Returns:
        (record, detail): the journal record (``point`` and ``point+line`` dicts) and the arrays behind it,
        ``point_inliers`` (N,) bool, ``point_line_inliers`` (N,) bool, ``line_matches`` (the line query's dict:
        ``lines2d`` (M, 2, 2), ``lines3d`` (M, 2, 3), ``line_idx`` (M,)) and ``line_inliers`` (M,) bool.
    """
    t0 = time.perf_counter() if t0 is None else t0
    rec = {"name": name, "point": {"success": False}, "point+line": {"success": False}}
    detail = {"point_inliers": np.zeros(len(pm), bool), "point_line_inliers": np.zeros(len(pm), bool),
              "line_matches": None, "line_inliers": np.zeros(0, bool)}
    est = estimate_pose_points(pm.p2d, pm.p3d, camera, replace(conf.point_pose, seed=conf.seed))
    t_point = (time.perf_counter() - t0) * 1000
    rec["point"] = {"success": bool(est["success"]), "n_matches": len(pm), "n_inliers": int(est["n_inliers"]),
                    "ms": t_point, "cam_from_world": _T(est["cam_from_world"] if est["success"] else None)}
    if not est["success"]:
        rec["point"]["reason"] = est.get("reason")
    detail["point_inliers"] = np.asarray(est["inliers"], bool)
    t1 = time.perf_counter()
    T = est["cam_from_world"] if est["success"] else None
    plconf = replace(conf.point_line_pose, seed=conf.seed)
    rescue = conf.line_rescue
    rescued = False
    if rescue.weak_inliers > 0 and (T is None or est["n_inliers"] < rescue.weak_inliers):
        priors = line_priors(name, est, points, rescue.prior_views)
        if rescue.hypotheses.keep > 0:
            hc = rescue.hypotheses
            dirs = (lq.dominant_directions(hc.n_map_lines, hc.min_support, hc.map_directions, hc.direction_tol_deg)
                    if hc.upright else None)
            priors += line_verified_poses(pm.p2d, pm.p3d, lines2d, lq.scoring_lines(hc.n_map_lines, hc.min_support),
                                          camera, hc, seed=conf.seed, directions=dirs)
        r = rescue_pose(pm, lines2d, priors, lq, camera, conf, trace)
        if r is not None:
            T, rescued = r["cam_from_world"], True
            plconf = replace(plconf, max_reproj_error=rescue.max_point_error)
            detail["point_line_inliers"] = np.asarray(r["inliers"], bool)
    t_rescue = (time.perf_counter() - t1) * 1000
    if T is None:
        why = "no point-only pose, and the line rescue found none" if rescue.weak_inliers > 0 else "no point-only pose to start from"
        rec["point+line"] = {"success": False, "reason": why,
                             "ms": t_point + (time.perf_counter() - t1) * 1000}
        return rec, detail
    if not rescued:
        detail["point_line_inliers"] = detail["point_inliers"]
    m, inliers, used_lines = None, None, False
    visible = lq.visible_lines(T, camera, conf.line_query.occlusion_tol) if conf.line_query.method == "projection" else None
    for lconf in line_query_schedule(conf):
        tried = lq.match(lines2d, T, camera, lconf, visible)
        r = estimate_pose_point_line(pm.p2d, pm.p3d, tried["lines2d"], tried["lines3d"], camera, initial=T, conf=plconf)
        if r["success"] and conf.max_line_step and not _within(r["cam_from_world"], T, *conf.max_line_step):
            r = {**r, "success": False}
        if not r["success"]:
            m = m or tried  # the matches the pose rests on: the last successful refinement's
            break
        T, m, inliers, used_lines = r["cam_from_world"], tried, r["line_inliers"], True
        detail["point_line_inliers"] = np.asarray(r["inliers"], bool)
    t_line = (time.perf_counter() - t1) * 1000
    n_lm = len(m["line_idx"])
    rec["point+line"] = {"success": True, "used_lines": used_lines, "rescued": rescued, "n_line_matches": n_lm,
                         "n_line_inliers": int(inliers.sum()) if used_lines else 0,
                         "n_query_lines": int(len(lines2d)), "ms": t_point + t_line, "line_stage_ms": t_line,
                         "rescue_ms": t_rescue,
                         "cam_from_world": _T(T)}
    if cam_from_world_gt is not None and m is not None:
        ok = correct_line_matches(m["lines2d"], m["lines3d"], cam_from_world_gt, camera)
        rec["point+line"]["n_line_matches_correct"] = int(ok.sum())
        rec["point+line"]["n_line_inliers_correct"] = int((ok & inliers).sum()) if used_lines else 0
    detail["line_matches"] = m
    detail["line_inliers"] = np.asarray(inliers, bool) if used_lines else np.zeros(n_lm, bool)
    return rec, detail


def line_priors(name: str, est: dict, points, k: int) -> list:
    """Starting poses for a weak query's lines: its point-only pose (when finite) and the poses of its ``k`` best
    retrieved database images (point sources that know them: ``retrieved_for`` and a ``model``)."""
    priors = []
    if est.get("cam_from_world") is not None and np.all(np.isfinite(est["cam_from_world"])):
        priors.append(np.asarray(est["cam_from_world"], dtype=float))
    retrieved = getattr(points, "retrieved_for", None)
    model = getattr(points, "model", None)
    if retrieved is not None and model is not None and k > 0:
        for db in retrieved(name)[:k]:
            if db in model:
                priors.append(model.cam_from_world(db))
    return priors


def rescue_pose(pm, lines2d, priors: list, lq: LineQuery, camera, conf: LocalizationConfig,
                trace: Optional[list] = None) -> Optional[dict]:
    """The best PnPL pose over ``priors`` with wide-gate line candidates (:class:`LineRescueConfig`), or None.

    The refinement solver finds the map lines a start sees (the plane occlusion test) once per start: its narrower
    stages move the pose by centimetres. RANSAC's pose may lie far from its start, and is tested anew.
    ``trace`` (a list) receives one dict per start and stage: ``stage``, ``start`` and ``result`` (the solver's
    dict), ``kept`` (whether it passed ``min_line_inliers``) and ``score``.
    """
    rc = conf.line_rescue
    priors = distinct_poses(priors, rc.same_pose_m, rc.same_pose_deg)
    lines2d = longest_lines(lines2d, rc.max_query_lines)
    if rc.solver == "refine":
        return _rescue_by_refinement(pm, lines2d, priors, lq, camera, conf, trace)
    if rc.solver != "ransac":
        raise ValueError(f"unknown line rescue solver {rc.solver!r} (ransac, refine)")
    plconf = replace(conf.point_line_pose, seed=conf.seed, max_iterations=rc.max_iterations, max_reproj_error=rc.max_point_error,
                     min_iterations=min(conf.point_line_pose.min_iterations, rc.max_iterations))
    best, best_score = None, -1
    for stage, gate in enumerate(rc.gates):
        qconf = _rescue_query(conf, gate)
        for T0 in (priors if stage == 0 else [best["cam_from_world"]] if best is not None else []):
            m = lq.match(lines2d, T0, camera, qconf)
            r = estimate_pose_point_line(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, conf=plconf)
            kept = r["success"] and r["n_line_inliers"] >= rc.min_line_inliers
            score = r["n_inliers"] + r["n_line_inliers"] if kept else -1
            if trace is not None:
                trace.append({"stage": stage, "start": T0, "result": r, "kept": kept, "score": score})
            if not kept:
                continue
            if score > best_score or stage > 0:  # a later stage refines the best pose with narrower gates
                best, best_score = r, score
    return best


def longest_lines(lines2d: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` longest of the segments ``lines2d`` (N, 4), in their order (all when ``k`` is 0 or N <= k)."""
    lines2d = np.asarray(lines2d, dtype=float).reshape(-1, 4)
    if k <= 0 or len(lines2d) <= k:
        return lines2d
    return lines2d[np.sort(np.argsort(-geo.segment_lengths(lines2d), kind="stable")[:k])]


def _rescue_query(conf: LocalizationConfig, gate) -> LineQueryConfig:
    """The line query of one rescue stage, ``gate`` = (px, deg[, candidates])."""
    rc = conf.line_rescue
    px, deg, *k = gate
    return replace(conf.line_query, method="projection", max_dist_px=float(px), max_angle_deg=float(deg),
                   max_candidates=int(k[0]) if k else rc.candidates, min_margin=0.0, one_to_one=False,
                   min_length_px=max(rc.min_length_px, conf.line_query.min_length_px))


def _rescue_by_refinement(pm, lines2d, priors: list, lq: LineQuery, camera, conf: LocalizationConfig,
                          trace: Optional[list] = None) -> Optional[dict]:
    """``rescue_pose`` with ``solver="refine"``: every start through every stage, each a robust refinement."""
    rc = conf.line_rescue
    best, best_score = None, -1
    for T in priors:
        T0 = T
        vis, r = lq.visible_lines(T, camera, conf.line_query.occlusion_tol), None
        for gate in rc.refine_gates:
            m = lq.match(lines2d, T, camera, _rescue_query(conf, gate), vis)
            if len(m["line_idx"]) < conf.point_line_pose.min_lines:
                r = None
                break
            r = refine_pose_point_line(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, T,
                                       point_scale=rc.max_point_error / 2, line_scale=rc.refine_scale * gate[0],
                                       max_reproj_error=rc.max_point_error, max_line_error=conf.point_line_pose.max_line_error)
            if not r["success"]:
                break
            T = r["cam_from_world"]
        kept = r is not None and r["success"] and r["n_line_inliers"] >= rc.min_line_inliers
        score = r["n_inliers"] + r["n_line_inliers"] if kept else -1
        if trace is not None:
            trace.append({"stage": 0, "start": T0, "result": r, "kept": kept, "score": score})
        if not kept:
            continue
        if score > best_score:
            best, best_score = r, score
    return best


def _within(U: np.ndarray, T: np.ndarray, max_m: float, max_deg: float) -> bool:
    dt, dr = pose_errors(U, T)
    return dt <= max_m and dr <= max_deg


def distinct_poses(poses: list, max_m: float, max_deg: float) -> list:
    """``poses`` without those within ``max_m`` and ``max_deg`` of an earlier one (the same start twice costs a RANSAC
    and finds the same lines)."""
    out = []
    for T in poses:
        if not any(_within(U, T, max_m, max_deg) for U in out):
            out.append(T)
    return out


def line_query_schedule(conf: LocalizationConfig) -> list:
    """The :class:`LineQueryConfig` of each query-and-refine iteration."""
    if conf.line_gates:
        return [replace(conf.line_query, max_dist_px=float(d), max_angle_deg=float(a)) for d, a in conf.line_gates]
    return [conf.line_query] * max(1, conf.line_iters)


def _T(T):
    return None if T is None else np.asarray(T).tolist()


def _read_journal(path: Path) -> dict:
    done = {}
    if not path.exists():
        return done
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
            done[r["name"]] = r
        except (json.JSONDecodeError, KeyError):
            continue  # a line cut by an interrupted write: that query is redone
    return done


class _Journal:
    def __init__(self, path: Path):
        self.f = open(path, "a")

    def write(self, rec: dict):
        self.f.write(json.dumps(rec) + "\n")
        self.f.flush()
        os.fsync(self.f.fileno())

    def close(self):
        self.f.close()


@dataclass
class SceneJob:
    """One scene's localization once :func:`prepare_scene` has made its artifacts: everything a worker needs to
    localize some of its queries from the files under ``out_dir`` (:func:`localize_chunk`), and the driver to
    journal them and write the results (:func:`journal_records`, :func:`finish_scene`). Small and picklable."""

    scene: object  # lipmap.scene.Scene with the frames that passed check_scene
    out_dir: Path
    conf: LocalizationConfig
    hloc_dir: Optional[HlocOutputs]
    map_info: dict
    qlines_h5: Path
    journal_path: Path
    bad_queries: dict  # query name -> problem (reported as failed)
    gt: dict  # cam_from_world of every query, bad ones included
    skipped: dict  # query name -> why its ground truth is invalid
    timings: dict
    sources: dict

    def open_points(self):
        """The point source, reopened from its artifacts (nothing is rebuilt)."""
        return open_points(self.scene, self.out_dir, self.conf, self.hloc_dir)

    def open_line_query(self) -> LineQuery:
        """The line query on the line map, reloaded from ``linemap.h5``."""
        from lipmap.linemap import LineMap

        return _line_query(LineMap.load(self.out_dir / self.map_info["path"]), self.conf, self.map_info)


def localize_scene(scene, out_dir, conf: LocalizationConfig, hloc_dir=None, lines_source=None, overwrite=False,
                   skip_bad_frames: bool = False, checkpoint: Optional[Callable[[str], None]] = None,
                   linemap=None) -> dict:
    """Run the whole per-scene pipeline and write the scene's results; returns the scene summary.

    Each variant of an artifact lives where its settings put it: the line map in
    ``map-<method>-<preset>-<digest>/``, the point map in ``points-<preset>-<digest>/``, the queries' journal
    in ``queries-<digest>.jsonl`` (the digest covers the settings, the map and the points), so runs with other
    settings into the same ``out_dir`` never reuse each other's artifacts. The results files describe the
    latest run and name the map and points they used.

    Bad frames are found first (lipmap.datasets.validate): a bad mapping frame stops the run with a
    message naming it unless ``skip_bad_frames``; a bad query is reported as failed and the others run.
    ``checkpoint(event)`` is called after each artifact ("lines2d", "planes", "linemap", "mapped") and
    after each query's journal entry ("query"): progress for benchmarks, fault injection for tests.
    """
    job, points, lq = prepare_scene(scene, out_dir, conf, hloc_dir, lines_source, overwrite, skip_bad_frames, checkpoint,
                                    linemap)
    done = resume_scene(job, overwrite)
    todo = pending_queries(job, done)
    journal_records(job, done, localize_views(tqdm(todo, desc=f"localize {job.scene.name}"), points, job.qlines_h5, lq, conf),
                    checkpoint)
    return finish_scene(job, done)


def prepare_scene(scene, out_dir, conf: LocalizationConfig, hloc_dir=None, lines_source=None, overwrite=False,
                  skip_bad_frames: bool = False, checkpoint: Optional[Callable[[str], None]] = None, linemap=None):
    """Check the frames, then make (or reuse) the scene's line map, point source and query lines.

    Returns (:class:`SceneJob`, point source, :class:`LineQuery`): the job names the artifacts on disk; the other
    two are the objects already in memory, which a worker elsewhere reopens with ``job.open_points()`` and
    ``job.open_line_query()``.
    """
    from lipmap.datasets.validate import check_scene

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not scene.query:
        raise InputError(f"scene {scene.name} has no query views", scene.root / "TestSplit.txt")
    checkpoint = checkpoint or (lambda event: None)
    all_queries = list(scene.query)
    scene, bad_queries = check_scene(scene, skip_bad_frames)
    t0 = time.time()
    linemap, map_info = scene_linemap(scene, out_dir, conf, lines_source, overwrite, checkpoint, linemap)
    t_map = time.time() - t0
    checkpoint("mapped")
    lq = _line_query(linemap, conf, map_info)
    points = open_points(scene, out_dir, conf, hloc_dir, overwrite)
    qlines_h5 = query_lines_file(scene, out_dir, conf, overwrite)
    journal_path = out_dir / f"queries-{_journal_digest(scene, conf, map_info, points, qlines_h5)}.jsonl"
    sources = {"map": map_info, "points": {"folder": _rel(points.folder, out_dir), "digest": points.stamp.digest,
                                           **getattr(points, "info", {})},
               "journal": journal_path.name}
    job = SceneJob(scene, out_dir, conf, as_hloc_outputs(hloc_dir), map_info, qlines_h5, journal_path,
                   bad_queries, gt={v.name: v.cam_from_world for v in all_queries},
                   skipped={v.name: v.meta["gt_error"] for v in all_queries if v.meta.get("gt_error")},
                   timings={"map_s": t_map, **points.timings}, sources=sources)
    return job, points, lq


def open_points(scene, out_dir: Path, conf: LocalizationConfig, hloc_dir=None, overwrite: bool = False):
    """The scene's 2D-3D point source: hloc's files under ``hloc_dir/<scene>`` (a folder or
    :class:`~localization.hloc_outputs.HlocOutputs`), else the built-in one (made or reused)."""
    return HlocPoints(hloc_dir, scene) if hloc_dir else BuiltinPoints(scene, out_dir, conf, overwrite)


def finish_scene(job: SceneJob, done: dict) -> dict:
    """Write the scene's results files from the records of its queries; returns the scene's results."""
    return write_scene_results(job.scene, job.out_dir, done, job.conf, job.map_info["n_lines"], job.timings, job.gt,
                               job.skipped, job.sources)


def _rel(path: Path, base: Path) -> str:
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return str(path)


def scene_linemap(scene, out_dir: Path, conf: LocalizationConfig, lines_source=None, overwrite: bool = False,
                  checkpoint: Optional[Callable[[str], None]] = None, linemap=None):
    """The line map of this configuration, built or reused in its own variant folder, or the map ``linemap`` (a
    ``linemap.h5`` already built, e.g. by :func:`lipmap.mapping.pipeline.map_scene`); returns (LineMap, info)."""
    from lipmap.linemap import LineMap

    if linemap is not None:
        return given_linemap(scene, Path(linemap), out_dir)
    from lipmap.mapping.pipeline import get_conf as map_conf
    from lipmap.mapping.pipeline import map_scene, map_variant_dir, mapping_stamp

    mconf = replace(map_conf(conf.mapping), seed=conf.seed)
    map_dir = map_variant_dir(out_dir, scene, mconf, conf.map_method, lines_source)
    # the planes in a folder of their own: map variants that differ only after the plane optimization share them
    path = map_scene(scene, map_dir, mconf, conf.map_method, lines_source, overwrite, checkpoint=checkpoint,
                     planes_root=out_dir)
    linemap = LineMap.load(path)
    info = {"method": conf.map_method, "preset": mconf.preset, "path": _rel(path, out_dir), "n_lines": len(linemap),
            "digest": mapping_stamp(scene, mconf, conf.map_method, lines_source).digest}
    if not len(linemap):
        logger.warning("%s: the line map has no lines; point+line poses will be the point-only poses", path)
    return linemap, info


def given_linemap(scene, path: Path, out_dir: Path):
    """A line map built elsewhere, checked against the scene (same world frame: the pose source); (LineMap, info)."""
    from lipmap.artifacts import digest as _digest
    from lipmap.artifacts import read_stamp
    from lipmap.linemap import LineMap

    if not path.is_file():
        raise InputError("line map file is missing", path)
    stamp = read_stamp(path)
    made = (stamp.settings.get("scene") or {}) if stamp is not None else {}
    if made.get("pose_source") not in (None, scene.pose_source):
        raise InputError(f"the line map was made with --pose-source {made['pose_source']}, and this run localizes "
                         f"with {scene.pose_source}: their poses live in different world frames", path,
                         f"evaluate with --pose-source {made['pose_source']}, or map again")
    if made.get("scene") not in (None, scene.name):
        logger.warning("%s was made for scene %s, not %s", path, made["scene"], scene.name)
    lm = LineMap.load(path)
    st = path.stat()
    info = {"method": lm.metadata.get("method", "given"), "preset": lm.metadata.get("preset"), "path": _rel(path, out_dir),
            "n_lines": len(lm), "given": True,
            "digest": stamp.digest if stamp is not None else _digest([str(path.resolve()), st.st_size, st.st_mtime_ns])}
    logger.info("Localizing %s against the line map %s (%d lines).", scene.name, path, len(lm))
    return lm, info


def _line_query(linemap, conf: LocalizationConfig, map_info: dict) -> LineQuery:
    lq = LineQuery.from_linemap(linemap)
    if conf.line_query.method == "raycast" and len(linemap) and (lq.caster is None or lq.edge_line is None):
        # otherwise every query fails alone with the same ValueError
        raise InputError(f"the raycast line query needs a line map with planes; this one was made by "
                         f"{linemap.metadata.get('method', '?')!r} and has none", map_info["path"],
                         "use --line-query projection or --method lipmap")
    return lq


def query_lines_file(scene, out_dir: Path, conf: LocalizationConfig, overwrite: bool = False) -> Path:
    """2D lines of the queries, with the mapping's detector, in a file named by the detector's settings."""
    from lipmap.lines2d import detect_lines, get_conf as lines_conf, lines_stamp
    from lipmap.mapping.pipeline import get_conf as map_conf

    lconf = lines_conf(map_conf(conf.mapping).lines)
    stamp = lines_stamp(lconf.name, asdict(lconf))
    return detect_lines(scene.query, out_dir / f"lines2d_query-{stamp.digest[:8]}.h5", lconf, overwrite=overwrite)


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """Digest of the source of the ``lipmap`` and ``localization`` packages (every ``.py`` file, path and bytes)."""
    import lipmap

    return source_digest([Path(lipmap.__file__).parent, Path(__file__).parent])


def _journal_digest(scene, conf: LocalizationConfig, map_info: dict, points, qlines_h5: Path) -> str:
    # A journal resumes an interrupted run of the same code: after a change to the code its records (poses and
    # timings) would be the old code's, so another code starts another journal.
    return digest({"conf": asdict(conf), "map": map_info["digest"], "points": points.stamp.digest,
                   "query_lines": qlines_h5.name, "queries": views_key(scene.query), "code": code_digest()}, 10)


def resume_scene(job: SceneJob, overwrite: bool = False) -> dict:
    """Queries already localized by this configuration (from its journal), plus the bad ones as failures."""
    if overwrite and job.journal_path.exists():
        job.journal_path.unlink()
    done = _read_journal(job.journal_path)
    if done:
        logger.info("Resuming %s: %d of %d queries already localized (%s).", job.scene.name, len(done),
                    len(job.scene.query), job.journal_path.name)
    for name, problem in job.bad_queries.items():
        done[name] = {"name": name, "point": {"success": False}, "point+line": {"success": False}, "error": problem}
    return done


def pending_queries(job: SceneJob, done: dict) -> list:
    """The query views not in ``done``, in the scene's order."""
    return [v for v in job.scene.query if v.name not in done]


def localize_views(views, points, qlines_h5: Path, lq: LineQuery, conf: LocalizationConfig):
    """Yield the record of each view, in order (:func:`localize_query`); a failing query never stops the others."""
    from lipmap.lines2d import load_lines

    for v in views:
        try:
            lines2d = load_lines(qlines_h5, v.name)
        except Exception as e:  # noqa: BLE001 - a bad query must not stop the others
            lines2d = np.zeros((0, 4))
            logger.warning("No lines for query %s: %s", v.name, e)
        try:
            rec = localize_query(v.name, v.camera, points, lines2d, lq, conf, v.cam_from_world)
        except Exception as e:  # noqa: BLE001
            logger.warning("Query %s failed: %s", v.name, e)
            rec = {"name": v.name, "point": {"success": False}, "point+line": {"success": False}, "error": repr(e)}
        yield rec


def localize_chunk(job: SceneJob, names: list) -> list:
    """Records of the queries ``names`` of a prepared scene, reopening its artifacts from disk: the unit of work
    that a worker process or machine runs (localization.scaleout)."""
    views = {v.name: v for v in job.scene.query}
    return list(localize_views([views[n] for n in names], job.open_points(), job.qlines_h5, job.open_line_query(), job.conf))


def journal_records(job: SceneJob, done: dict, records, checkpoint: Optional[Callable[[str], None]] = None) -> None:
    """Append each record to the scene's journal (fsync'd, so a killed run resumes after it) and to ``done``,
    in the order given; ``checkpoint("query")`` after each."""
    journal = _Journal(job.journal_path)
    try:
        for rec in records:
            journal.write(rec)
            done[rec["name"]] = rec
            if checkpoint:
                checkpoint("query")
    finally:
        journal.close()


def line_match_stats(recs) -> dict:
    """Per-scene line-correspondence figures, checked with the ground-truth pose: medians of matches and
    correct matches per query, and the precision of the matches and of the PnPL line inliers."""
    pl = [r["point+line"] for r in recs if "n_line_matches_correct" in r.get("point+line", {})]
    if not pl:
        return {}
    tot = {k: sum(p.get(k, 0) for p in pl) for k in ("n_line_matches", "n_line_matches_correct", "n_line_inliers",
                                                       "n_line_inliers_correct")}
    return {
        "median_line_matches": float(np.median([p["n_line_matches"] for p in pl])),
        "median_line_matches_correct": float(np.median([p["n_line_matches_correct"] for p in pl])),
        "line_match_precision": round(tot["n_line_matches_correct"] / tot["n_line_matches"], 4) if tot["n_line_matches"] else None,
        "line_inlier_precision": round(tot["n_line_inliers_correct"] / tot["n_line_inliers"], 4) if tot["n_line_inliers"] else None,
    }


def write_scene_results(scene, out_dir: Path, recs: dict, conf: LocalizationConfig, n_map_lines: int, timings, gt=None,
                        skipped=None, sources: Optional[dict] = None) -> dict:
    from .hloc_io import write_results

    gt = scene.query_gt if gt is None else gt
    summary, per_query = {}, {}
    for key, fname in RESULT_FILES.items():
        est = {n: (np.array(r[key]["cam_from_world"]) if r[key].get("success") else None) for n, r in recs.items()}
        write_results(out_dir / fname, {n: T for n, T in est.items() if T is not None})
        errs = ev.query_errors(est, gt)
        ms = [r[key]["ms"] for r in recs.values() if r[key].get("ms") is not None]
        summary[key] = ev.summarize(errs, ms)
        for n, (t, r) in errs.items():
            per_query.setdefault(n, {})[key] = {"t_cm": round(t * 100, ev.DECIMALS) if math.isfinite(t) else None,
                                                 "R_deg": round(r, ev.DECIMALS) if math.isfinite(r) else None,
                                                 **{k: v for k, v in recs.get(n, {}).get(key, {}).items() if k != "cam_from_world"}}
    line_ms = [r["point+line"]["line_stage_ms"] for r in recs.values() if "line_stage_ms" in r["point+line"]]
    summary["point+line"]["median_ms_line_stage"] = float(np.median(line_ms)) if line_ms else None
    summary["point+line"]["median_line_inliers"] = float(np.median([r["point+line"].get("n_line_inliers", 0) for r in recs.values()]))
    summary["point+line"].update(line_match_stats(recs.values()))
    out = {
        "scene": scene.name,
        "dataset": scene.dataset,
        "pose_source": scene.pose_source,
        "pgt_files": (scene.meta or {}).get("pgt_files", []),
        "n_map_lines": n_map_lines,
        **(sources or {}),
        "config": json.loads(json.dumps(asdict(conf), default=str)),
        "timings": timings,
        "summary": summary,
        "queries": per_query,
        "errors": {n: r["error"] for n, r in recs.items() if "error" in r},
        "skipped_invalid_gt": skipped or {},
        "skipped_mapping_frames": scene.meta.get("skipped_frames", []),
    }
    write_text_atomic(out_dir / "results.json", json.dumps(out, indent=1, default=float))
    return out


def localize_scenes(scenes, conf: LocalizationConfig, hloc_dir=None, overwrite=False, skip_bad_frames: bool = False,
                    checkpoint: Optional[Callable[[str], None]] = None, linemaps: Optional[dict] = None):
    """The local scene runner of :func:`run_eval`: ``scenes`` yields (scene, out_dir); yields each scene's results,
    in order. localization.scaleout.RayRunner is the other one (same arguments, same results)."""
    for scene, out_dir in scenes:
        yield localize_scene(scene, out_dir, conf, hloc_dir, overwrite=overwrite, skip_bad_frames=skip_bad_frames,
                             checkpoint=checkpoint, linemap=(linemaps or {}).get(scene.name))


def run_eval(dataset: str, root, scenes, out, conf: LocalizationConfig, hloc_dir=None, pose_source="posetxt",
             register_depth=True, overwrite=False, mapping_step: int = 1, skip_bad_frames: bool = False,
             checkpoint: Optional[Callable[[str], None]] = None, runner: Optional[Callable] = None,
             pgt_dir=None, linemap=None) -> Path:
    """Localize every scene and write OUT/<dataset>/results.json and summary.md; returns the results path.

    ``runner`` localizes the scenes (default :func:`localize_scenes`, here, one after the other); e.g.
    ``localization.scaleout.RayRunner`` spreads them and their queries over a Ray cluster.
    ``linemap``: line maps already built (``linemap.h5``), used instead of mapping here: a path (``{scene}`` in it
    becomes each scene's name) or ``{scene: path}``.
    """
    from lipmap.datasets import load_scene

    # absolute paths: a runner's workers may start elsewhere, and the paths in messages are the same either way
    root, out = Path(root).resolve(), Path(out).resolve() / dataset
    hloc_dir = as_hloc_outputs(hloc_dir)
    all_res = {"dataset": dataset, "root": str(root), "pose_source": pose_source, "config": json.loads(json.dumps(asdict(conf), default=str)),
               "scenes": {}, "scene_details": {}}

    def loaded():
        for name in scenes:
            scene = load_scene(dataset, root, name, pose_source=pose_source, register_depth=register_depth,
                               mapping_step=mapping_step, skip_bad_frames=skip_bad_frames, pgt_dir=pgt_dir)
            logger.info("Scene %s: %d mapping, %d query views (poses: %s).", name, len(scene.mapping), len(scene.query), pose_source)
            yield scene, out / name

    if linemap is not None and not isinstance(linemap, dict):
        linemap = {name: str(linemap).replace("{scene}", name) for name in scenes}
    linemap = {k: Path(v).resolve() for k, v in (linemap or {}).items()}
    results = (runner or localize_scenes)(loaded(), conf, hloc_dir=hloc_dir, overwrite=overwrite,
                                          skip_bad_frames=skip_bad_frames, checkpoint=checkpoint, linemaps=linemap)
    for name, res in zip(scenes, results, strict=True):  # a runner yields the scenes' results in their order
        all_res["scenes"][name] = res["summary"]
        all_res["scene_details"][name] = {"n_map_lines": res["n_map_lines"], "map": res["map"], "timings": res["timings"]}
        s = res["summary"]
        logger.info("%s point-only: %s | point+line: %s", name, ev.format_summary(s["point"]), ev.format_summary(s["point+line"]))
    path = out / "results.json"
    write_text_atomic(path, json.dumps(all_res, indent=1, default=float))
    notes = [f"Mapping: {conf.map_method} ({conf.mapping} preset); points: "
             + ("hloc files" if hloc_dir else f"built-in {conf.points} + {conf.retrieval} top-{conf.num_retrieved}")
             + (f"; point matches limited to {conf.max_point_matches} per query (seed {conf.seed})" if conf.max_point_matches else ""),
             f"Line query: {conf.line_query.method}, "
             + (f"map lines seen in at least {conf.line_query.min_support} mapping image(s) by the track test"
                if conf.line_query.min_support else "every map line")]
    write_text_atomic(out / "summary.md", ev.summary_markdown(all_res, dataset, pose_source, notes))
    return path
