"""Localize one query against a line map: the per-query API (hloc's ``QueryLocalizer``, LIMAP's
``pl_estimate_absolute_pose``).

    from localization import Localizer

    loc = Localizer.from_linemap("out/redkitchen/linemap.h5")          # once per map
    res = loc.localize(camera, p2d, p3d, image="query.png")            # or lines2d=(L, 4) segments
    res.point.cam_from_world, res.point_line.cam_from_world           # (4, 4) or None
    res.point_line.inliers, res.line_matches.lines3d, res.timings

Pixel coordinates are COLMAP's (pixel centre at +0.5): add 0.5 to hloc's keypoints (``hloc_io.read_keypoints``
does). Poses are ``cam_from_world``. The benchmark (:func:`localization.pipeline.run_eval`) runs the same call,
:func:`localization.pipeline.localize_matches`, for every query of a scene.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from lipmap import InputError
from lipmap.scene import Camera

from .pipeline import LocalizationConfig, localize_matches
from .points import PointMatches


@dataclass
class PoseEstimate:
    """One method's pose of a query.

    Attributes:
        success: whether the method found a pose.
        cam_from_world: :math:`(4, 4)` or None.
        inliers: :math:`(N,)` bool over the point matches.
        reason: why there is no pose (or None).
    """

    success: bool
    cam_from_world: Optional[np.ndarray]
    inliers: np.ndarray
    reason: Optional[str] = None

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


@dataclass
class LineMatches:
    """The 2D-3D line matches the point+line pose rests on (the last line round's).

    Attributes:
        lines2d: :math:`(M, 2, 2)` query segments (COLMAP pixels).
        lines3d: :math:`(M, 2, 3)` their map lines' endpoints (world).
        query_idx: :math:`(M,)` index of each segment in the query's lines.
        line_idx: :math:`(M,)` index of each map line in the line map.
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
        line_matches: :class:`LineMatches` (empty when no line round ran).
        used_lines, rescued: whether lines refined the pose, and whether the line rescue gave its start (a weak
            point-only pose: fewer inliers than ``LineRescueConfig.weak_inliers``).
        lines2d: :math:`(L, 4)` the query's segments (detected or given).
        timings: milliseconds: ``point``, ``line_stage`` (rescue included), ``rescue``, ``detect_lines``, ``total``.
        record: the benchmark's record of this query (what ``results.json`` stores per query).
    """

    point: PoseEstimate
    point_line: PoseEstimate
    line_matches: LineMatches
    used_lines: bool
    rescued: bool
    lines2d: np.ndarray
    timings: dict = field(default_factory=dict)
    record: dict = field(default_factory=dict)


def as_camera(camera) -> Camera:
    """A PINHOLE :class:`~lipmap.scene.Camera` from itself, a PoseLib/COLMAP dict (``model``, ``width``, ``height``,
    ``params``) or a ``pycolmap.Camera``."""
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, dict):
        return Camera(int(camera["width"]), int(camera["height"]), tuple(camera["params"]), camera.get("model", "PINHOLE"))
    if all(hasattr(camera, a) for a in ("width", "height", "params")):  # pycolmap.Camera
        model = getattr(camera, "model", "PINHOLE")
        name = getattr(model, "name", str(model))
        return Camera(int(camera.width), int(camera.height), tuple(np.asarray(camera.params).tolist()), name)
    raise InputError(f"cannot use {type(camera).__name__} as a camera: give lipmap.scene.Camera, a dict with model, "
                     "width, height, params, or a pycolmap.Camera")


class Localizer:
    """A line map loaded once, and the localization settings; :meth:`localize` answers one query at a time."""

    def __init__(self, linemap, conf: Optional[LocalizationConfig] = None, line_detector=None):
        """
        Args:
            linemap: :class:`lipmap.linemap.LineMap`.
            conf: :class:`~localization.pipeline.LocalizationConfig` (defaults: the benchmark's).
            line_detector: the 2D line detector for queries given as images (a ``lipmap.lines2d`` preset name or
                config; default: the one the mapping preset of ``conf`` uses, as the benchmark does).
        """
        from lipmap.lines2d import get_conf as lines_conf
        from lipmap.mapping.pipeline import get_conf as map_conf

        from .pipeline import _line_query

        self.conf = conf or LocalizationConfig()
        self.linemap = linemap
        self.lq = _line_query(linemap, self.conf, {"path": linemap.metadata.get("path", "line map")})
        self.line_detector = lines_conf(line_detector if line_detector is not None else map_conf(self.conf.mapping).lines)

    @classmethod
    def from_linemap(cls, path: Union[str, Path], conf: Optional[LocalizationConfig] = None, **kw) -> "Localizer":
        """Load ``linemap.h5`` (or a LIMAP ``finaltracks/`` folder) once."""
        from lipmap.linemap import LineMap

        path = Path(path)
        return cls(LineMap.from_limap(path) if path.is_dir() else LineMap.load(path), conf, **kw)

    def detect_lines(self, image) -> np.ndarray:
        """:math:`(L, 4)` segments (COLMAP pixels) of an image (a path, or an 8-bit grey or RGB array)."""
        from lipmap.imageio import read_color
        from lipmap.lines2d import detect_lines_image

        img = read_color(image, gray=True) if isinstance(image, (str, Path)) else np.asarray(image)
        return detect_lines_image(img, self.line_detector)[0]

    def localize(self, camera, points2d: np.ndarray, points3d: np.ndarray, lines2d: Optional[np.ndarray] = None,
                 image=None, name: str = "query", cam_from_world_gt: Optional[np.ndarray] = None) -> QueryResult:
        """Point-only and point+line poses of one query. Never raises for a hard query: a failure is a result.

        Args:
            camera: the query's PINHOLE camera (:func:`as_camera`).
            points2d: :math:`(N, 2)` keypoints, COLMAP pixels.
            points3d: :math:`(N, 3)` their 3D points (world).
            lines2d: :math:`(L, 4)` the query's segments (x1, y1, x2, y2; COLMAP pixels), or None with ``image``.
            image: the query image (path or array), its lines detected with :attr:`line_detector`.
            name: the query's name (in the record; seeds nothing).
            cam_from_world_gt: optional ground truth: the record then counts the line matches it confirms.

        Returns:
            :class:`QueryResult`.
        """
        camera = as_camera(camera)
        p2d = np.asarray(points2d, dtype=np.float64).reshape(-1, 2)
        p3d = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
        if len(p2d) != len(p3d):
            raise InputError(f"{len(p2d)} 2D points for {len(p3d)} 3D points")
        t_detect = 0.0
        if lines2d is None:
            if image is None:
                raise InputError("give the query's lines2d or its image")
            t = time.perf_counter()
            lines2d = self.detect_lines(image)
            t_detect = (time.perf_counter() - t) * 1000
        lines2d = np.asarray(lines2d, dtype=np.float64).reshape(-1, 4)
        n = len(p2d)
        pm = PointMatches(p2d, p3d, np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64))
        t0 = time.perf_counter()
        rec, detail = localize_matches(pm, lines2d, camera, self.lq, self.conf, name, cam_from_world_gt=cam_from_world_gt,
                                       t0=t0)
        total = (time.perf_counter() - t0) * 1000
        p, pl = rec["point"], rec["point+line"]
        m = detail["line_matches"]
        if m is None:
            m = {"lines2d": np.zeros((0, 2, 2)), "lines3d": np.zeros((0, 2, 3)), "query_idx": np.zeros(0, np.int64),
                 "line_idx": np.zeros(0, np.int64)}
        return QueryResult(
            point=_pose(p, detail["point_inliers"]),
            point_line=_pose(pl, detail["point_line_inliers"]),
            line_matches=LineMatches(np.asarray(m["lines2d"]).reshape(-1, 2, 2), np.asarray(m["lines3d"]).reshape(-1, 2, 3),
                                     np.asarray(m["query_idx"]), np.asarray(m["line_idx"]), detail["line_inliers"]),
            used_lines=bool(pl.get("used_lines", False)), rescued=bool(pl.get("rescued", False)), lines2d=lines2d,
            timings={"point": p.get("ms"), "line_stage": pl.get("line_stage_ms"), "rescue": pl.get("rescue_ms"),
                     "detect_lines": t_detect, "total": total + t_detect},
            record=rec)


def _pose(r: dict, inliers: np.ndarray) -> PoseEstimate:
    T = r.get("cam_from_world")
    ok = bool(r.get("success"))
    return PoseEstimate(ok, np.asarray(T, dtype=float) if (ok and T is not None) else None,
                        np.asarray(inliers, bool) if ok else np.zeros(len(inliers), bool), r.get("reason"))
