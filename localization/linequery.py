"""Query a line map with an initial pose: 2D-3D line matches for one query image.

Two ways, selectable (``LineQueryConfig.method``):
- ``raycast`` (the paper's): cast the rays of each query line's 1-pixel region against the map's
  planes, take the hit plane's best edge, and look up the 3D line that edge belongs to; a vote over
  the region's pixels picks the line. Occlusion is handled by construction (first hit).
- ``projection``: project the map's lines with the initial pose, keep those not occluded by the
  planes (when the map has planes), and match each query line to the projected line that is closest
  in angle and perpendicular distance with enough overlap.
Both finish with the same geometric check (angle, distance) so their outputs are comparable.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lipmap import geometry as geo
from lipmap import logger
from lipmap.mapping.assign import PlaneRaycaster, best_edges, line_regions, pixel_rays_world, visible_lines


LINE_QUERY_METHODS = ("projection", "raycast")


@dataclass
class LineQueryConfig:
    method: str = "projection"  # one of LINE_QUERY_METHODS
    max_angle_deg: float = 2.0  # query line vs projected 3D line, with the INITIAL pose
    max_dist_px: float = 4.0  # max distance of the query endpoints to the projected 3D line
    min_overlap: float = 0.3  # overlap of the projected 3D line on the query line (projection method)
    min_length_px: float = 20.0  # query lines shorter than this are not used
    min_votes: float = 0.5  # raycast: share of the resolved pixels of a region that must agree on the line
    min_pixels: int = 3  # raycast: and at least this many pixels
    # raycast: region half-width. The paper's 1 px assumes a near-exact pose; with an initial pose a
    # few pixels off, a 1-px region can fall wholly on the far side of the edge and miss its plane.
    region_radius: float = 3.0
    occlusion_tol: float = 0.05  # m, projection method's visibility test against the planes
    # map lines seen in fewer mapping images (by the track test) are not queried; 0: all, also those no image verifies
    # (leaving those out gains where queries are far from the mapping views; docs/localization.md,
    # `-verified-lines` variants)
    min_support: int = 1
    one_to_one: bool = True  # a map line matches at most one query line (its best), as a point matches one keypoint
    min_margin: float = 6.0  # projection: drop a query line whose runner-up map line scores within this of its best (0: off)
    # projection: a runner-up within this (m, both endpoints to the best's 3D line, and 5 deg) is the same physical
    # line mapped twice (neighbouring patch edges, an edge and an on-plane line), so it does not make the match
    # ambiguous (0: every runner-up counts; docs/localization.md, `-dup` variants)
    margin_dup_3d: float = 0.03
    # projection: keep each query line's k best map lines (k > 1 turns the margin off: RANSAC picks among them)
    max_candidates: int = 1


def match_score(dist_px: np.ndarray, angle_rad: np.ndarray, conf: LineQueryConfig) -> np.ndarray:
    """Lower is better: the distance in px plus the angle as a share of the gate's, weighted so that a line at
    the angle gate scores like one 10 px off (the ranking of candidates and the ``min_margin`` test use it)."""
    return dist_px + 10 * np.degrees(angle_rad) / max(conf.max_angle_deg, 1e-9)


class LineQuery:
    """Holds a line map's lines, planes and raycaster; ``match`` answers one query."""

    def __init__(self, lines3d: np.ndarray, corners: np.ndarray | None = None, edge_line: np.ndarray | None = None,
                 supports: np.ndarray | None = None):
        self.lines = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
        s = np.full(len(self.lines), np.iinfo(np.int32).max) if supports is None else np.asarray(supports)
        self.support = s[:, 0] if s.ndim == 2 else s.reshape(len(self.lines))  # images per line (LineMap.supports)
        self.corners = None if corners is None or len(corners) == 0 else np.asarray(corners, dtype=float)
        self.edge_line = None if edge_line is None else np.asarray(edge_line, dtype=np.int64)
        self.caster = PlaneRaycaster(self.corners) if self.corners is not None else None

    def scoring_lines(self, n: int, min_support: int = 0) -> np.ndarray:
        """The ``n`` longest map lines seen in at least ``min_support`` mapping images (N, 2, 3), computed once
        (:func:`localization.hypotheses.scoring_lines`)."""
        from .hypotheses import scoring_lines

        cache = self.__dict__.setdefault("_scoring", {})
        if (n, min_support) not in cache:
            cache[n, min_support] = scoring_lines(self.lines[self.support >= min_support], n)
        return cache[n, min_support]

    def dominant_directions(self, n: int, min_support: int, k: int, tol_deg: float) -> np.ndarray:
        """The ``k`` dominant directions (K, 3) of :meth:`scoring_lines` (``n``, ``min_support``), computed once
        (:func:`localization.hypotheses.dominant_directions`)."""
        from .hypotheses import dominant_directions

        cache = self.__dict__.setdefault("_directions", {})
        key = (n, min_support, k, tol_deg)
        if key not in cache:
            cache[key] = dominant_directions(self.scoring_lines(n, min_support), k, tol_deg)
        return cache[key]

    @classmethod
    def from_linemap(cls, linemap) -> "LineQuery":
        """A map without any track (lines imported bare) has unknown supports, not zero: every line is queried."""
        planes = linemap.planes or {}
        supports = linemap.supports
        if len(linemap) and not supports[:, 0].any():
            logger.warning("No line of the map has a track (imported without tracks, or none verified), so supports "
                           "tell the lines nothing: min_support is not applied and every line is queried.")
            supports = None
        return cls(linemap.lines, planes.get("corners"), planes.get("edge_line"), supports)

    def match(self, lines2d: np.ndarray, cam_from_world: np.ndarray, camera, conf: LineQueryConfig,
              visible: np.ndarray | None = None) -> dict:
        """2D-3D line matches for a query.

        Args:
            lines2d: :math:`(N, 4)` query segments (COLMAP pixels of ``camera``).
            cam_from_world: :math:`(4, 4)` initial pose.
            visible: the map lines to consider (projection method; default: :meth:`visible_lines` from this
                pose). A refinement loop computes them once: a pose a few cm off sees the same lines.

        Returns:
            dict with ``query_idx`` (M,), ``line_idx`` (M,), ``lines2d`` (M, 2, 2), ``lines3d`` (M, 2, 3),
            ``angle`` (M,) rad and ``dist`` (M,) px under the initial pose.
        """
        lines2d = np.asarray(lines2d, dtype=float).reshape(-1, 4)
        keep = np.linalg.norm(lines2d[:, 2:] - lines2d[:, :2], axis=1) >= conf.min_length_px
        qidx = np.flatnonzero(keep)
        if len(qidx) == 0 or len(self.lines) == 0:
            return _empty()
        if conf.method == "raycast":
            if self.caster is None or self.edge_line is None:
                raise ValueError("the raycast line query needs a line map with planes (lipmap maps have them)")
            cand_q, cand_l = self._raycast(lines2d[qidx], cam_from_world, camera, conf)
            cand_q = qidx[cand_q]
        elif conf.method == "projection":
            cand_q, cand_l = self._projection(lines2d[qidx], cam_from_world, camera, conf, visible)
            cand_q = qidx[cand_q]
        else:
            raise ValueError(f"unknown line query method {conf.method!r}")
        return self._verify(lines2d, cand_q, cand_l, cam_from_world, camera, conf)

    def _raycast(self, q, T, camera, conf):
        pix, li = line_regions(q, camera.width, camera.height, radius=conf.region_radius)
        o, d = pixel_rays_world(pix, T, camera)
        plane, _ = self.caster.first_hit(o, d)
        hit = plane >= 0
        pix, li, plane = pix[hit], li[hit], plane[hit]
        edge, _, _, _ = best_edges(self.corners, plane, q[li], T, camera)
        line3d = self.edge_line[plane, edge]
        ok = line3d >= 0
        ok[ok] &= self.support[line3d[ok]] >= conf.min_support
        # About half of a region lies on the far side of the edge and hits another surface, so the
        # vote counts only pixels that resolved to some map line.
        resolved = np.bincount(li[ok], minlength=len(q)).astype(float)
        out_q, out_l = [], []
        if ok.any():
            pairs, counts = np.unique(np.stack([li[ok], line3d[ok]], 1), axis=0, return_counts=True)
            order = np.lexsort((-counts, pairs[:, 0]))
            pairs, counts = pairs[order], counts[order]
            first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
            for (qi, l3), c in zip(pairs[first], counts[first]):
                if c >= max(conf.min_votes * resolved[qi], conf.min_pixels):
                    out_q.append(qi)
                    out_l.append(l3)
        return np.array(out_q, dtype=np.int64), np.array(out_l, dtype=np.int64)

    def visible_lines(self, T, camera, tol: float) -> np.ndarray:
        """Indices of map lines in front of the camera, inside the image, and not hidden by the planes."""
        return visible_lines(self.lines, T, camera, self.caster, tol)

    def _projection(self, q, T, camera, conf, visible=None):
        vis = self.visible_lines(T, camera, conf.occlusion_tol) if visible is None else np.asarray(visible, dtype=np.int64)
        vis = vis[self.support[vis] >= conf.min_support]
        if len(vis) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        proj, _ = geo.project_segments(self.lines[vis], T, camera)
        qs = geo.as_segments2d(q)
        # Two cheap tests over all pairs (a query has ~300 lines, a view ~1,000-3,000 map lines), as float32 matrix
        # products: the angle, and the query line's midpoint within the gate of the projected infinite line (its unit
        # normal), which both endpoints being within it implies (one product instead of one per endpoint). About 1 %
        # of the pairs are left; they get the exact tests in float64.
        dq = qs[:, 1] - qs[:, 0]
        dp = proj[:, 1] - proj[:, 0]
        dq = dq / np.maximum(np.linalg.norm(dq, axis=1, keepdims=True), 1e-9)
        lp = np.maximum(np.linalg.norm(dp, axis=1, keepdims=True), 1e-9)
        dp = dp / lp
        nrm = np.stack([-dp[:, 1], dp[:, 0]], 1)  # (P, 2) unit normals of the projected lines
        off = (nrm * proj[:, 0]).sum(1)
        cos_gate = np.cos(np.radians(conf.max_angle_deg))
        with np.errstate(invalid="ignore"):  # NaN projections (behind the camera) pass no test
            # gates a hair wider than the float64 ones below, which decide
            # one (Q, P) buffer for both products, worked in place: fresh matrices cost a third of the time
            mid32 = (0.5 * (qs[:, 0] + qs[:, 1])).astype(np.float32)
            buf = mid32 @ nrm.T.astype(np.float32)
            buf -= off.astype(np.float32)
            m = np.abs(buf, out=buf) <= np.float32(conf.max_dist_px + 1e-3)
            np.matmul(dq.astype(np.float32), dp.T.astype(np.float32), out=buf)
            m &= np.abs(buf, out=buf) >= np.float32(cos_gate - 1e-5)
        qi, pj = np.divmod(np.flatnonzero(m), m.shape[1])  # np.nonzero's (qi, pj) order, 10x faster on (Q, P)
        cos = np.abs((dq[qi] * dp[pj]).sum(1))
        d0 = np.abs((qs[qi, 0] * nrm[pj]).sum(1) - off[pj])
        d1 = np.abs((qs[qi, 1] * nrm[pj]).sum(1) - off[pj])
        dist = np.maximum(d0, d1)
        near = (cos >= cos_gate) & (dist <= conf.max_dist_px)
        qi, pj, dist, cos = qi[near], pj[near], dist[near], cos[near]
        if len(qi) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        with np.errstate(invalid="ignore"):
            ov = geo.overlap_ratio(proj[pj], qs[qi])  # overlap of the projected line on the query line
        ok = ov >= conf.min_overlap
        qi, pj, dist = qi[ok], pj[ok], dist[ok]
        ang = np.arccos(np.clip(cos[ok], -1.0, 1.0))
        score = match_score(dist, ang, conf)
        order = np.lexsort((score, qi))  # best candidate first within each query line
        qi, pj, score = qi[order], pj[order], score[order]
        first = np.r_[True, qi[1:] != qi[:-1]] if len(qi) else np.zeros(0, bool)
        if conf.max_candidates > 1:
            rank = np.arange(len(qi)) - np.searchsorted(qi, qi)  # 0 for each query line's best candidate
            keep = rank < conf.max_candidates
            return qi[keep], vis[pj[keep]]
        if conf.min_margin > 0 and len(qi):
            # a runner-up about as good as the best makes the query line ambiguous (parallel edges a few px apart)
            starts = np.flatnonzero(first)
            rival = np.where(first, np.inf, score)
            if conf.margin_dup_3d > 0 and not first.all():
                best = np.searchsorted(qi, qi)  # each candidate's query line's best (qi is sorted)
                # only a runner-up within the margin can make its line ambiguous: the 3D test is for those alone
                c = np.flatnonzero(~first & (score - score[best] < conf.min_margin))
                rival[c[_same_line_3d(self.lines[vis[pj[c]]], self.lines[vis[pj[best[c]]]], conf.margin_dup_3d)]] = np.inf
            ok = np.minimum.reduceat(rival, starts) - score[starts] >= conf.min_margin
            first[starts[~ok]] = False
        return qi[first], vis[pj[first]]

    def _verify(self, lines2d, cand_q, cand_l, T, camera, conf):
        if len(cand_q) == 0:
            return _empty()
        proj, valid = geo.project_segments(self.lines[cand_l], T, camera)
        qs = geo.as_segments2d(lines2d[cand_q])
        with np.errstate(invalid="ignore"):
            ang = geo.angle_distance(qs, proj)
            dist = geo.perpendicular_distance(qs, proj, "max")
        ok = valid & (ang <= np.radians(conf.max_angle_deg)) & (dist <= conf.max_dist_px)
        if conf.one_to_one and ok.any():
            score = np.where(ok, match_score(dist, ang, conf), np.inf)
            order = np.lexsort((score, cand_l))  # best query line first for each map line
            first = np.r_[True, cand_l[order][1:] != cand_l[order][:-1]]
            keep = np.zeros_like(ok)
            keep[order[first]] = True
            ok &= keep
        return {
            "query_idx": cand_q[ok],
            "line_idx": cand_l[ok],
            "lines2d": qs[ok],
            "lines3d": self.lines[cand_l[ok]],
            "angle": ang[ok],
            "dist": dist[ok],
        }


def _same_line_3d(a: np.ndarray, b: np.ndarray, tol: float, max_angle_deg: float = 5.0) -> np.ndarray:
    """Whether 3D segments a (M, 2, 3) lie on b's lines (M, 2, 3): both endpoints within ``tol`` of b's infinite
    line and the directions within ``max_angle_deg``."""
    da, db = a[:, 1] - a[:, 0], b[:, 1] - b[:, 0]
    cos = np.abs((da * db).sum(1)) / np.maximum(np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1), 1e-12)
    near = geo.point_line_distance(a, b[:, None]).max(1) <= tol
    return near & (cos >= np.cos(np.radians(max_angle_deg)))


def correct_line_matches(lines2d: np.ndarray, lines3d: np.ndarray, cam_from_world_gt: np.ndarray, camera,
                         max_dist_px: float = 2.0, max_angle_deg: float = 1.0) -> np.ndarray:
    """Which 2D-3D line matches are right under the ground-truth pose.

    A match is correct when the 3D line, projected with ``cam_from_world_gt``, lies within ``max_dist_px``
    (both detection endpoints to the projected infinite line) and ``max_angle_deg`` of the detection.

    Args:
        lines2d: :math:`(M, 2, 2)` detections (COLMAP pixels); lines3d: :math:`(M, 2, 3)` their matched map lines.

    Returns:
        :math:`(M,)` bool.
    """
    lines2d = np.asarray(lines2d, dtype=float).reshape(-1, 2, 2)
    if len(lines2d) == 0 or cam_from_world_gt is None:
        return np.zeros(len(lines2d), bool)
    proj, valid = geo.project_segments(np.asarray(lines3d, dtype=float).reshape(-1, 2, 3), cam_from_world_gt, camera)
    with np.errstate(invalid="ignore"):
        ang = geo.angle_distance(lines2d, proj)
        dist = geo.perpendicular_distance(lines2d, proj, "max")
    return valid & (ang <= np.radians(max_angle_deg)) & (dist <= max_dist_px)


def _empty() -> dict:
    return {
        "query_idx": np.zeros(0, np.int64),
        "line_idx": np.zeros(0, np.int64),
        "lines2d": np.zeros((0, 2, 2)),
        "lines3d": np.zeros((0, 2, 3)),
        "angle": np.zeros(0),
        "dist": np.zeros(0),
    }
