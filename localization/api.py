"""Localize one query against a line map: the per-query API (hloc's ``QueryLocalizer``, LIMAP's
``pl_estimate_absolute_pose``).

    from localization import Localizer

    loc = Localizer.from_linemap("out/redkitchen/linemap.h5")          # once per map
    res = loc.localize(camera, p2d, p3d, image="query.png")            # or lines2d=(L, 4) segments
    res.point.cam_from_world, res.point_line.cam_from_world           # (4, 4) or None
    res.point_line.inliers, res.line_matches.lines3d, res.timings

    res = loc.localize(camera, p2d, p3d, lines2d=L, initial=T)         # a starting pose for weak queries
    res = loc.localize(camera, p2d, p3d, line_matches=(l2d, l3d))      # your own 2D-3D line matches

Any COLMAP camera model: with distortion, keypoints, segments and the image are undistorted into the pinhole camera
of the same focal lengths and principal point (:mod:`localization.cameras`). Pixel coordinates are COLMAP's (pixel
centre at +0.5): add 0.5 to hloc's keypoints (``hloc_io.read_keypoints`` does). Poses are ``cam_from_world``. The
benchmark (:func:`localization.pipeline.run_eval`) runs the same call, :func:`localization.query.localize_matches`,
for every query of a scene.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Union

import numpy as np

from lipmap import InputError

from .cameras import as_query_camera
from .config import LocalizationConfig, check_config
from .estimate import PointLinePoseConfig, pnpl_pose, subsample_matches
from .points import PointMatches
from .query import given_line_matches, localize_matches, make_line_query


@dataclass
class PoseEstimate:
    """One method's pose of a query.

    Attributes:
        success: whether the method found a pose.
        cam_from_world: :math:`(4, 4)` or None.
        inliers: :math:`(N,)` bool over the point matches.
        reason: why there is no pose (or None).
        line_inliers: :math:`(M,)` bool over the line matches (point+line poses; empty otherwise).
    """

    success: bool
    cam_from_world: Optional[np.ndarray]
    inliers: np.ndarray
    reason: Optional[str] = None
    line_inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


@dataclass
class LineMatches:
    """The 2D-3D line matches the point+line pose rests on (the last line round's; empty when no round gave it).

    Attributes:
        lines2d: :math:`(M, 2, 2)` query segments (COLMAP pixels of the pinhole camera).
        lines3d: :math:`(M, 2, 3)` their map lines' endpoints (world).
        query_idx: :math:`(M,)` index of each segment in the query's lines.
        line_idx: :math:`(M,)` index of each map line in the line map (-1 for given matches without ids).
        inliers: :math:`(M,)` bool, PnPL line inliers.
    """

    lines2d: np.ndarray
    lines3d: np.ndarray
    query_idx: np.ndarray
    line_idx: np.ndarray
    inliers: np.ndarray

    def __len__(self) -> int:
        return len(self.line_idx)


@dataclass
class QueryResult:
    """What :meth:`Localizer.localize` returns.

    Attributes:
        point: the point-only pose (PoseLib RANSAC + refinement over the point matches).
        point_line: the point+line pose; the point-only one when no line round succeeded (``used_lines`` False).
        line_matches: :class:`LineMatches` (empty when no line round gave the pose).
        used_lines, rescued: whether lines refined the pose, and whether the line rescue gave its start (a weak
            point-only pose: fewer inliers than ``LineRescueConfig.weak_inliers``).
        lines2d: :math:`(L, 4)` the query's segments (detected or given; undistorted), COLMAP pixels.
        point_matches: the point matches used (after ``max_point_matches``; undistorted).
        timings: milliseconds, always numbers: ``point``, ``line_stage`` (rescue included), ``rescue``,
            ``detect_lines``, ``total``.
        record: the benchmark's record of this query (what ``results.json`` stores per query).
    """

    point: PoseEstimate
    point_line: PoseEstimate
    line_matches: LineMatches
    used_lines: bool
    rescued: bool
    lines2d: np.ndarray
    point_matches: PointMatches
    timings: dict = field(default_factory=dict)
    record: dict = field(default_factory=dict)


class Localizer:
    """A line map loaded once, and the localization settings; :meth:`localize` answers one query at a time."""

    def __init__(self, linemap, conf: Optional[LocalizationConfig] = None, line_detector=None):
        """
        Args:
            linemap: :class:`lipmap.linemap.LineMap`.
            conf: :class:`~localization.config.LocalizationConfig` (defaults: the benchmark's), checked first
                (:func:`~localization.config.check_config`). Every per-query field acts as in the benchmark,
                ``max_point_matches`` included; ``points``, ``retrieval``, ``num_retrieved`` and ``map_method`` say how
                ``run_eval`` makes the point matches and the map that a Localizer is handed, so one config serves
                both; ``line_rescue.prior_views`` needs retrieved images a Localizer does not have and is refused
                (pass their poses as ``initial``).
            line_detector: the 2D line detector for queries given as images (a ``lipmap.lines2d`` preset name or
                config; default: the one the mapping preset of ``conf`` uses, as the benchmark does).
        """
        from lipmap.lines2d import get_conf as lines_conf
        from lipmap.mapping.pipeline import get_conf as map_conf

        self.conf = check_config(conf or LocalizationConfig())
        if self.conf.line_rescue.prior_views:
            raise InputError("LocalizationConfig.line_rescue.prior_views needs the retrieved database images, which a "
                             "Localizer does not have: pass their poses as localize(..., initial=[T1, T2, ...])")
        self.linemap = linemap
        self.lq = make_line_query(linemap, self.conf, linemap.metadata.get("path", "line map"))
        self.line_detector = lines_conf(line_detector if line_detector is not None else map_conf(self.conf.mapping).lines)

    @classmethod
    def from_linemap(cls, path: Union[str, Path], conf: Optional[LocalizationConfig] = None, **kw) -> "Localizer":
        """Load ``linemap.h5`` (or a LIMAP ``finaltracks/`` folder) once."""
        from lipmap.linemap import LineMap

        path = Path(path)
        return cls(LineMap.from_limap(path) if path.is_dir() else LineMap.load(path), conf, **kw)

    def detect_lines(self, image, camera=None) -> np.ndarray:
        """:math:`(L, 4)` segments (COLMAP pixels) of an image (a path, or an 8-bit grey or RGB array); with a
        distorted ``camera``, of the image undistorted into its pinhole camera."""
        from lipmap.imageio import read_color
        from lipmap.lines2d import detect_lines_image

        img = read_color(image, gray=True) if isinstance(image, (str, Path)) else np.asarray(image)
        if camera is not None:
            img = as_query_camera(camera).undistort_image(img)
        return detect_lines_image(img, self.line_detector)[0]

    def localize(self, camera, points2d: np.ndarray, points3d: np.ndarray, lines2d: Optional[np.ndarray] = None,
                 image=None, name: str = "query", cam_from_world_gt: Optional[np.ndarray] = None,
                 initial: Optional[np.ndarray] = None, line_matches=None) -> QueryResult:
        """Point-only and point+line poses of one query. Never raises for a hard query: a failure is a result.

        Args:
            camera: the query's camera, any COLMAP model (:func:`localization.cameras.as_query_camera`).
            points2d: :math:`(N, 2)` keypoints, COLMAP pixels (N may be 0).
            points3d: :math:`(N, 3)` their 3D points (world).
            lines2d: :math:`(L, 4)` the query's segments (x1, y1, x2, y2; COLMAP pixels), or None with ``image``.
            image: the query image (path or array), its lines detected with :attr:`line_detector`.
            name: the query's name: in the record, and it seeds the draw of ``conf.max_point_matches``.
            cam_from_world_gt: optional ground truth: the record then counts the line matches it confirms.
            initial: a starting pose :math:`(4, 4)` (or several, :math:`(K, 4, 4)`) for the lines of a query whose
                points give no trustworthy pose (fewer inliers than ``LineRescueConfig.weak_inliers``): a prior, the
                previous frame's pose, the retrieved images' poses. A strong point-only pose starts the lines itself.
            line_matches: your own 2D-3D line matches, ``(lines2d (M, 4), lines3d (M, 2, 3))`` or
                ``(lines2d, lines3d (K, 2, 3), line_ids (M,))``: the line query is skipped and one PnPL RANSAC over
                the points and these lines gives the point+line pose (LIMAP's ``pl_estimate_absolute_pose``).

        Returns:
            :class:`QueryResult`.
        """
        qcam = as_query_camera(camera)
        camera = qcam.pinhole
        p2d = np.asarray(points2d, dtype=np.float64).reshape(-1, 2)
        p3d = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
        if len(p2d) != len(p3d):
            raise InputError(f"{len(p2d)} 2D points for {len(p3d)} 3D points")
        priors = _poses(initial, "initial")
        given = None
        if line_matches is not None:
            given = given_line_matches(*line_matches) if isinstance(line_matches, (tuple, list)) else \
                given_line_matches(line_matches["lines2d"], line_matches["lines3d"], line_matches.get("line_ids"))
            given["lines2d"] = qcam.undistort_segments(given["lines2d"])
        t_detect = 0.0
        if lines2d is None:
            if image is not None:
                t = time.perf_counter()
                lines2d = self.detect_lines(image, qcam)
                t_detect = (time.perf_counter() - t) * 1000
            elif given is not None:
                lines2d = given["lines2d"].reshape(-1, 4)
            else:
                raise InputError("give the query's lines2d, its image or line_matches")
        else:
            lines2d = qcam.undistort_segments(np.asarray(lines2d, dtype=np.float64).reshape(-1, 4))
        lines2d = np.asarray(lines2d, dtype=np.float64).reshape(-1, 4)
        n = len(p2d)
        pm = PointMatches(qcam.undistort_points(p2d), p3d, np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64))
        c = self.conf
        t0 = time.perf_counter()
        pm = pm.subset(subsample_matches(n, c.max_point_matches, c.seed if c.match_seed is None else c.match_seed, name))
        rec, detail = localize_matches(pm, lines2d, camera, self.lq, c, name, priors=priors, line_matches=given,
                                       cam_from_world_gt=cam_from_world_gt, t0=t0)
        total = (time.perf_counter() - t0) * 1000
        p, pl = rec["point"], rec["point+line"]
        m = detail["line_matches"] or {"lines2d": np.zeros((0, 2, 2)), "lines3d": np.zeros((0, 2, 3)),
                                       "query_idx": np.zeros(0, np.int64), "line_idx": np.zeros(0, np.int64)}
        return QueryResult(
            point=_pose(p, detail["point_inliers"]),
            point_line=_pose(pl, detail["point_line_inliers"], detail["line_inliers"]),
            line_matches=LineMatches(np.asarray(m["lines2d"]).reshape(-1, 2, 2), np.asarray(m["lines3d"]).reshape(-1, 2, 3),
                                     np.asarray(m["query_idx"]), np.asarray(m["line_idx"]), detail["line_inliers"]),
            used_lines=bool(pl.get("used_lines", False)), rescued=bool(pl.get("rescued", False)), lines2d=lines2d,
            point_matches=pm,
            timings={"point": float(p.get("ms", 0.0)), "line_stage": float(pl.get("line_stage_ms", 0.0)),
                     "rescue": float(pl.get("rescue_ms", 0.0)), "detect_lines": t_detect, "total": total + t_detect},
            record=rec)


def estimate_pose_point_line(lines3d, line_ids, lines2d, points3d, points2d, camera, initial=None,
                             conf: Optional[PointLinePoseConfig] = None, seed: int = 0) -> tuple:
    """Pose from matched 2D-3D lines and points, in the shape of LIMAP's ``pl_estimate_absolute_pose`` (PoseLib's
    PnPL LO-RANSAC and refinement; its minimal solvers mix points and lines, so a few of each suffice).

    Args:
        lines3d: :math:`(K, 2, 3)` 3D segments (world).
        line_ids: :math:`(M,)` the 3D segment of each 2D segment (LIMAP's ``l3d_ids``), or None when ``lines3d`` has
            one row per 2D segment.
        lines2d: :math:`(M, 4)` or :math:`(M, 2, 2)` matched query segments, COLMAP pixels.
        points3d: :math:`(N, 3)`; points2d: :math:`(N, 2)` COLMAP pixels (N may be 0).
        camera: any COLMAP camera model (distorted inputs are undistorted first).
        initial: :math:`(4, 4)` cam_from_world to seed RANSAC with (LIMAP's ``campose``).
        conf: :class:`~localization.estimate.PointLinePoseConfig` (thresholds, iterations).

    Returns:
        (:class:`PoseEstimate` with ``inliers`` over the points and ``line_inliers`` over the lines, statistics
        dict: ``n_inliers``, ``n_line_inliers``, ``n_lines``).
    """
    qcam = as_query_camera(camera)
    m = given_line_matches(lines2d, lines3d, line_ids)
    p2d = qcam.undistort_points(points2d)
    p3d = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
    if len(p2d) != len(p3d):
        raise InputError(f"{len(p2d)} 2D points for {len(p3d)} 3D points")
    conf = replace(conf or PointLinePoseConfig(), seed=seed)
    init = _poses(initial, "initial")
    r = pnpl_pose(p2d, p3d, qcam.undistort_segments(m["lines2d"]), m["lines3d"], qcam.pinhole,
                  initial=init[0] if init else None, conf=conf)
    ok = bool(r["success"])
    est = PoseEstimate(ok, r["cam_from_world"] if ok else None, np.asarray(r["inliers"], bool), r.get("reason"),
                       np.asarray(r["line_inliers"], bool))
    return est, {"n_inliers": int(r["n_inliers"]), "n_line_inliers": int(r["n_line_inliers"]), "n_lines": int(r["n_lines"])}


def _poses(T, what: str) -> list:
    """None, one (4, 4) pose or several (K, 4, 4) as a list of finite (4, 4) arrays."""
    if T is None:
        return []
    A = np.asarray(T, dtype=np.float64)
    if A.shape == (4, 4):
        A = A[None]
    if A.ndim != 3 or A.shape[1:] != (4, 4) or not np.isfinite(A).all():
        raise InputError(f"{what} must be a finite (4, 4) cam_from_world or (K, 4, 4) of them, got shape {A.shape}")
    return list(A)


def _pose(r: dict, inliers: np.ndarray, line_inliers: Optional[np.ndarray] = None) -> PoseEstimate:
    T = r.get("cam_from_world")
    ok = bool(r.get("success"))
    li = np.zeros(0, bool) if line_inliers is None else np.asarray(line_inliers, bool)
    return PoseEstimate(ok, np.asarray(T, dtype=float) if (ok and T is not None) else None,
                        np.asarray(inliers, bool) if ok else np.zeros(len(inliers), bool), r.get("reason"), li)
