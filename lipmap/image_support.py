"""How much of each 3D line the images show: the share of its visible length, in every mapping view that sees it,
that lies along a detected 2D segment.

M1 and M2 measure a line map against the scene's surface. A line that runs past the structure it belongs to, across
a wall, stays within a few cm of that surface along its whole length and counts as precise there; its images show
nothing beyond the structure's end. This measure looks at the images instead, and does not depend on the map's own
tracks: each line is sampled in 3D; in each view, a sample is visible when it projects inside the image, in front of
the camera and not behind the view's sensor depth (:func:`lipmap.mapping.extract.visible_mask`); a line with at least
``min_visible`` visible samples is seen there, and a visible sample is shown when it lies within ``max_px`` of a
detection of that view whose direction is within ``max_angle_deg`` of the line's projection.
"""
from __future__ import annotations

import numpy as np

from . import geometry as geo
from .mapping.extract import visible_mask


def image_support(lines, views, lines_by_view: dict, depth_by_view=None, max_px: float = 2.0,
                  max_angle_deg: float = 1.0, samples: int = 32, min_visible: int = 8, occlusion_tol: float = 0.05) -> dict:
    """The share of each line's visible length that the detections of the views seeing it show.

    Args:
        lines: :math:`(L, 2, 3)` world segments, or a :class:`~lipmap.linemap.LineMap`.
        views: the mapping views (``name``, ``camera``, ``cam_from_world``); those without detections are skipped.
        lines_by_view: {view name: (M, 4) detected segments}.
        depth_by_view: {view name: (H, W) sensor depth, 0 = unknown} for the occlusion test (None: no test).

    Returns:
        dict with **per_line** :math:`(L,)` (mean over the views that see the line of the shown share of its visible
        samples; NaN for a line no view sees), **views** :math:`(L,)` (how many views see it) and **shown** (the mean
        of ``per_line`` weighted by 3D length).
    """
    lines = np.asarray(getattr(lines, "lines", lines), dtype=float).reshape(-1, 2, 3)
    pts3 = geo.sample_segments(lines, samples)  # (L, S, 3)
    total, count = np.zeros(len(lines)), np.zeros(len(lines), np.int64)
    cos_min = np.cos(np.radians(max_angle_deg))
    depth_by_view = depth_by_view or {}
    for v in views:
        if v.name not in lines_by_view or not len(lines):
            continue
        det = geo.as_segments2d(np.asarray(lines_by_view[v.name], dtype=float).reshape(-1, 4))
        vis = visible_mask(pts3.reshape(-1, 3), v, depth_by_view.get(v.name), occlusion_tol).reshape(len(lines), -1)
        seen = np.flatnonzero(vis.sum(1) >= min_visible)
        if not len(seen):
            continue
        uv, _ = geo.project_points(pts3[seen].reshape(-1, 3), v.cam_from_world, v.camera)
        uv = uv.reshape(len(seen), samples, 2)
        shown = np.zeros((len(seen), samples), bool)
        vs = vis[seen]
        if len(det):
            rows = np.arange(len(seen))
            dp = uv[rows, samples - 1 - vs[:, ::-1].argmax(1)] - uv[rows, vs.argmax(1)]  # last - first visible sample
            dd = det[:, 1] - det[:, 0]
            norms = np.linalg.norm(dp, axis=1)[:, None] * np.linalg.norm(dd, axis=1)[None]
            cos = np.abs(dp @ dd.T) / np.maximum(norms, 1e-12)
            for i in range(len(seen)):
                cand = np.flatnonzero(cos[i] >= cos_min)
                if len(cand):
                    shown[i] = geo.point_segment_distance(uv[i][:, None], det[cand][None]).min(1) <= max_px
        total[seen] += (shown & vs).sum(1) / vs.sum(1)
        count[seen] += 1
    per_line = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    length = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    use = np.isfinite(per_line)
    shown = float((per_line[use] * length[use]).sum() / max(length[use].sum(), 1e-12)) if use.any() else float("nan")
    return {"per_line": per_line, "views": count, "shown": shown}
