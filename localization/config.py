"""The settings of a localization run: :class:`LocalizationConfig` (the per-query core's and the benchmark's point
source) with :class:`LineRescueConfig`, and :func:`check_config`, which refuses out-of-range values before any work.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field
from typing import Optional

from lipmap import InputError
from lipmap.artifacts import digest

from .estimate import PointLinePoseConfig, PointPoseConfig
from .hypotheses import HypothesisConfig
from .linequery import LINE_QUERY_METHODS, LineQueryConfig
from .near_ransac import NearRansacConfig

RESCUE_SOLVERS = ("ransac", "near", "refine")
RESCUE_ROUNDS = ("confirm", "local", "ransac")


@dataclass
class LineRescueConfig:
    """Lines for the queries whose points alone give no trustworthy pose.

    A point-only pose with fewer than ``weak_inliers`` inliers (or none) is too far off for the narrow gates of
    the line query, and with few matches a wrong P3P pose often explains as many of them as the right one. Lines
    then start from several poses instead: that pose when it exists, the P3P poses of the point matches that the
    most map lines agree with (``hypotheses``, :mod:`localization.hypotheses`), and optionally the poses of the
    ``prior_views`` best retrieved database images. From each, every query line takes its ``candidates`` nearest
    map lines within the wide gate (no ambiguity test), and a PnPL RANSAC about the start over all point matches and
    these candidates picks a pose (``solver``); each such pose is refined at the later ``gates`` without RANSAC, and the one with the
    most point + line inliers at the last gate (at least ``min_line_inliers`` lines) is the pose; the narrowing
    rounds only confirm it (``rounds``), with ``max_point_error`` for the points.
    """

    weak_inliers: int = 20  # 0: off. Ten point matches are always weak; a full query (hundreds of inliers) never
    prior_views: int = 0  # retrieved images' poses as starts (on the held-out split they lie ~90 cm off: no gain)
    # P3P poses of the point matches that the most map lines agree with, as starts (localization.hypotheses)
    hypotheses: HypothesisConfig = field(default_factory=HypothesisConfig)
    # (px, deg[, candidates]) per stage: the first, PnPL RANSAC from every start; the later ones refine each pose it
    # keeps with each query line's nearest map lines, without RANSAC, and the most inliers at the last one win. They
    # bridge the wide gate and the narrowing rounds, which a pose 5-10 cm off missed (docs/localization.md, `-polish`)
    gates: tuple = ((30.0, 5.0), (15.0, 3.0, 1), (8.0, 3.0, 1))
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
    # "near": each start's candidates go through a PnPL RANSAC about the start (localization.near_ransac: minimal
    # samples solved linearly near its rotation, scored as PoseLib's), and the later ``gates`` refine the pose it keeps;
    # "ransac": PoseLib's PnPL RANSAC instead, which samples with no regard to the start (held-out split, 1-10 matches:
    # "near" puts as many queries within 5 cm or more, in 15-35 % less time on 2 threads; docs/localization.md, `-near`);
    # "refine": each start goes through every stage of ``refine_gates`` as a robust refinement (Cauchy, scale
    # ``refine_scale`` x the gate) of its nearest candidates, without RANSAC: half the time, a higher median (docs/localization.md)
    solver: str = "near"
    refine_gates: tuple = ((30.0, 5.0, 1), (15.0, 3.0, 1), (8.0, 3.0, 1))
    near: NearRansacConfig = field(default_factory=NearRansacConfig)  # solver="near"'s RANSAC
    refine_scale: float = 0.25  # the Cauchy scale of the lines in a refinement stage, times its gate (px)
    # what the narrowing rounds do with a rescued pose. "confirm": the pose stands; the line query at the last strong
    # gate (``LocalizationConfig.strong_gates``) from it gives the line matches, and those within the line threshold
    # there confirm it (``min_final_lines``). The rescue's last stage already refined it with each query line's nearest
    # map line; moving it again made it worse (docs/localization.md, `-rounds`). "local": local refinements at the
    # strong gates; "ransac": RANSAC rounds at the line gates, which pulled such poses off further (`-polish`)
    rounds: str = "confirm"
    # a rescued pose whose last narrowing round keeps fewer line inliers is no pose: the point-only pose stands, narrowed
    # as usual, or without one the query fails with the reason; so does a weak point-only pose held by as few. 6, the
    # rescue's own bar (``min_line_inliers``), drops only wrong poses on the held-out split; 20 drops nearly all of them
    # but also right ones on the synthetic scenes, whose views hold fewer lines (docs/localization.md, `-final-lines`). 0: no count
    # (with min_final_share 0 too, the test is off)
    min_final_lines: int = 6
    # ... nor one that keeps fewer than this share of the query's lines of min_length_px or more: a wrong pose lays
    # a dozen map lines on some of a cluttered view's hundreds by chance (held-out split, 10 matches: 0.08 drops 35
    # wrong poses and 3 right ones; 5 and 3 matches, 58 and 56 wrong, none right; docs/localization.md). 0: no share
    min_final_share: float = 0.08
    # the starts' RANSACs and refinements run on this many threads (PoseLib works outside Python's lock); the poses are
    # the same for any number. 1: in the caller's thread (a worker that already has one core per query)
    threads: int = 2


@dataclass
class LocalizationConfig:
    seed: int = 0
    max_point_matches: Optional[int] = None  # seeded random subset per query (same for both methods)
    match_seed: Optional[int] = None  # seed of that subset (None: ``seed``); vary it alone to average over draws
    points: str = "sift-n4096"  # localization.points preset (built-in SIFT)
    retrieval: str = "vlad64"  # localization.points.retrieval preset
    num_retrieved: int = 10
    point_pose: PointPoseConfig = field(default_factory=PointPoseConfig)
    point_line_pose: PointLinePoseConfig = field(default_factory=PointLinePoseConfig)
    line_query: LineQueryConfig = field(default_factory=LineQueryConfig)
    line_iters: int = 2  # line query -> refine, repeated with the refined pose (when line_gates is empty)
    # per iteration (max_dist_px, max_angle_deg) gates of the line query, overriding line_iters and the gates of
    # line_query: wide while the pose is the point-only one, narrower once lines have refined it; () = fixed gates
    line_gates: tuple = ((8.0, 3.0), (4.0, 2.0), (2.0, 1.0))
    # a query with at least this many point-only inliers is held to about a pixel by its points: its narrowing rounds
    # are ``strong_gates``, each a local refinement from the inliers at the current pose instead of a RANSAC, whose
    # minimal samples only pulled such a pose about (docs/localization.md, `-strong` variants). 0: off
    strong_inliers: int = 50
    strong_gates: tuple = ((4.0, 2.0), (2.0, 1.0))
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


def check_config(conf: LocalizationConfig) -> LocalizationConfig:
    """``conf`` itself when every number is in range; otherwise an :class:`~lipmap.InputError` naming the field, its
    value and what it must be (a negative seed or match budget would fail every query one by one, later)."""
    rc, lq, pp, plp, hc = conf.line_rescue, conf.line_query, conf.point_pose, conf.point_line_pose, conf.line_rescue.hypotheses
    checks = [
        ("seed", conf.seed, _int(0), "an integer >= 0"),
        ("max_point_matches", conf.max_point_matches, lambda v: v is None or _int(0)(v), "None (every match) or an integer >= 0"),
        ("match_seed", conf.match_seed, lambda v: v is None or _int(0)(v), "None (the seed) or an integer >= 0"),
        ("num_retrieved", conf.num_retrieved, _int(1), "an integer >= 1"),
        ("line_iters", conf.line_iters, _int(1), "an integer >= 1"),
        ("line_gates", conf.line_gates, lambda v: all(len(g) == 2 and _pos(g[0]) and _pos(g[1]) for g in v),
         "pairs (px > 0, deg > 0)"),
        ("strong_inliers", conf.strong_inliers, _int(0), "an integer >= 0 (0: off)"),
        ("strong_gates", conf.strong_gates, lambda v: len(v) >= 1 and all(len(g) == 2 and _pos(g[0]) and _pos(g[1]) for g in v),
         "one or more pairs (px > 0, deg > 0)"),
        ("max_line_step", conf.max_line_step, lambda v: len(v) == 0 or (len(v) == 2 and _pos(v[0]) and _pos(v[1])),
         "() or (metres > 0, degrees > 0)"),
        ("point_pose.max_reproj_error", pp.max_reproj_error, _pos, "> 0 px"),
        ("point_pose.min_matches", pp.min_matches, _int(0), "an integer >= 0"),
        ("point_pose.min_inliers", pp.min_inliers, _int(0), "an integer >= 0"),
        ("point_pose.min_iterations", pp.min_iterations, _int(0), "an integer >= 0"),
        ("point_pose.max_iterations", pp.max_iterations, _int(1), "an integer >= 1"),
        ("point_pose.success_prob", pp.success_prob, lambda v: 0 < v < 1, "in (0, 1)"),
        ("point_pose.loss_scale", pp.loss_scale, lambda v: v is None or _pos(v), "None (adaptive) or > 0 px"),
        ("point_pose.min_loss_scale", pp.min_loss_scale, _pos, "> 0 px"),
        ("point_line_pose.max_reproj_error", plp.max_reproj_error, _pos, "> 0 px"),
        ("point_line_pose.max_line_error", plp.max_line_error, _pos, "> 0 px"),
        ("point_line_pose.min_lines", plp.min_lines, _int(0), "an integer >= 0"),
        ("point_line_pose.min_iterations", plp.min_iterations, _int(0), "an integer >= 0"),
        ("point_line_pose.max_iterations", plp.max_iterations, _int(1), "an integer >= 1"),
        ("point_line_pose.success_prob", plp.success_prob, lambda v: 0 < v < 1, "in (0, 1)"),
        ("point_line_pose.refine", plp.refine, lambda v: v in ("poselib", "weighted"), "'poselib' or 'weighted'"),
        ("point_line_pose.min_scale", plp.min_scale, _pos, "> 0 px"),
        ("point_line_pose.line_scale_factor", plp.line_scale_factor, _pos, "> 0"),
        ("point_line_pose.refine_iterations", plp.refine_iterations, _int(1), "an integer >= 1"),
        ("point_line_pose.refine_step_tol", plp.refine_step_tol, _pos, "> 0"),
        ("line_query.method", lq.method, lambda v: v in LINE_QUERY_METHODS, f"one of {', '.join(LINE_QUERY_METHODS)}"),
        ("line_query.max_angle_deg", lq.max_angle_deg, _pos, "> 0 degrees"),
        ("line_query.max_dist_px", lq.max_dist_px, _pos, "> 0 px"),
        ("line_query.min_overlap", lq.min_overlap, lambda v: 0 <= v <= 1, "in [0, 1]"),
        ("line_query.min_length_px", lq.min_length_px, _nonneg, ">= 0 px"),
        ("line_query.min_votes", lq.min_votes, lambda v: 0 <= v <= 1, "in [0, 1]"),
        ("line_query.min_pixels", lq.min_pixels, _int(0), "an integer >= 0"),
        ("line_query.region_radius", lq.region_radius, _nonneg, ">= 0 px"),
        ("line_query.occlusion_tol", lq.occlusion_tol, _nonneg, ">= 0 m"),
        ("line_query.min_support", lq.min_support, _int(0), "an integer >= 0 images"),
        ("line_query.min_margin", lq.min_margin, _nonneg, ">= 0"),
        ("line_query.margin_dup_3d", lq.margin_dup_3d, _nonneg, ">= 0 m"),
        ("line_query.max_candidates", lq.max_candidates, _int(1), "an integer >= 1"),
        ("line_rescue.weak_inliers", rc.weak_inliers, _int(0), "an integer >= 0 (0: off)"),
        ("line_rescue.prior_views", rc.prior_views, _int(0), "an integer >= 0"),
        ("line_rescue.gates", rc.gates, lambda v: len(v) >= 1 and all(len(g) in (2, 3) and _pos(g[0]) and _pos(g[1])
                                                       and (len(g) == 2 or _int(1)(g[2])) for g in v),
         "one or more (px > 0, deg > 0[, candidates >= 1]) stages"),
        ("line_rescue.refine_gates", rc.refine_gates, lambda v: len(v) >= 1 and all(len(g) in (2, 3) and _pos(g[0]) and _pos(g[1]) for g in v),
         "one or more (px > 0, deg > 0[, candidates]) stages"),
        ("line_rescue.candidates", rc.candidates, _int(1), "an integer >= 1"),
        ("line_rescue.min_length_px", rc.min_length_px, _nonneg, ">= 0 px"),
        ("line_rescue.max_query_lines", rc.max_query_lines, _int(0), "an integer >= 0 (0: all)"),
        ("line_rescue.min_line_inliers", rc.min_line_inliers, _int(0), "an integer >= 0"),
        ("line_rescue.min_final_lines", rc.min_final_lines, _int(0), "an integer >= 0 (0: off)"),
        ("line_rescue.threads", rc.threads, _int(1), "an integer >= 1"),
        ("line_rescue.max_iterations", rc.max_iterations, _int(1), "an integer >= 1"),
        ("line_rescue.max_point_error", rc.max_point_error, _pos, "> 0 px"),
        ("line_rescue.same_pose_m", rc.same_pose_m, _nonneg, ">= 0 m"),
        ("line_rescue.same_pose_deg", rc.same_pose_deg, _nonneg, ">= 0 degrees"),
        ("line_rescue.solver", rc.solver, lambda v: v in RESCUE_SOLVERS, f"one of {', '.join(RESCUE_SOLVERS)}"),
        ("line_rescue.refine_scale", rc.refine_scale, _pos, "> 0"),
        ("line_rescue.rounds", rc.rounds, lambda v: v in RESCUE_ROUNDS, f"one of {', '.join(RESCUE_ROUNDS)}"),
        ("line_rescue.hypotheses.keep", hc.keep, _int(0), "an integer >= 0 (0: off)"),
        ("line_rescue.hypotheses.max_triples", hc.max_triples, _int(1), "an integer >= 1"),
        ("line_rescue.hypotheses.max_point_error", hc.max_point_error, _pos, "> 0 px"),
        ("line_rescue.hypotheses.n_map_lines", hc.n_map_lines, _int(1), "an integer >= 1"),
        ("line_rescue.hypotheses.min_support", hc.min_support, _int(0), "an integer >= 0 images"),
        ("line_rescue.hypotheses.max_dist_px", hc.max_dist_px, _pos, "> 0 px"),
        ("line_rescue.hypotheses.angle_bins", hc.angle_bins, lambda v: _int(1)(v) and v <= 64, "an integer in [1, 64]"),
        ("line_rescue.hypotheses.min_agree", hc.min_agree, lambda v: 0 <= v <= 1, "in [0, 1]"),
        ("line_rescue.hypotheses.lines_first.below", hc.lines_first.below, _int(0), "an integer >= 0 (0: never)"),
        ("line_rescue.hypotheses.lines_first.views", hc.lines_first.views, _int(0), "an integer >= 0"),
        ("line_rescue.hypotheses.lines_first.max_prior_deg", hc.lines_first.max_prior_deg, lambda v: _pos(v) and v < 45,
         "in (0, 45) degrees"),
        ("line_rescue.hypotheses.lines_first.depth_bin", hc.lines_first.depth_bin, _pos, "> 0 m"),
    ]
    for name, value, ok, what in checks:
        try:
            good = bool(ok(value))
        except (TypeError, ValueError):
            good = False
        if not good:
            raise InputError(f"LocalizationConfig.{name} must be {what}, got {value!r}")
    return conf


def _int(lo: int):
    return lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= lo


def _pos(v) -> bool:
    return isinstance(v, numbers.Real) and math.isfinite(v) and v > 0


def _nonneg(v) -> bool:
    return isinstance(v, numbers.Real) and math.isfinite(v) and v >= 0
