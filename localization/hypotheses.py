"""Line-verified pose hypotheses for a query with too few point matches to trust its RANSAC pose.

With ten 2D-3D point matches, a wrong P3P pose often explains as many of them as the right one at RANSAC's
12 px threshold, and RANSAC keeps whichever it met first. The map's lines can tell them apart. Every P3P pose
of every triple of matches is scored by how many map lines it projects onto detected lines of the same
direction; the detections are looked up through one mask per direction bin of the pixels near them. The best few
poses then start the wide-gate line rescue (:func:`localization.pipeline.rescue_pose`).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import cv2
import numpy as np

from lipmap import geometry as geo



@dataclass
class HypothesisConfig:
    max_triples: int = 200  # triples of point matches solved (all when fewer; a seeded sample otherwise)
    max_point_error: float = 12.0  # px: point inliers of a hypothesis (as the point-only RANSAC)
    max_hypotheses: int = 60  # the hypotheses with the most point inliers are scored by lines
    n_map_lines: int = 1500  # the longest map lines score them
    min_support: int = 1  # of those seen in at least this many mapping images
    samples: int = 5  # per map line
    max_dist_px: float = 3.0  # a sample agrees within this of a detection of its direction
    angle_bins: int = 8  # direction bins over 180 deg; a detection also counts in the bin next to its angle
    min_agree: float = 0.8  # share of a line's samples that must agree
    keep: int = 3  # best hypotheses handed on
    # a first pass scores every hypothesis with the ``coarse_lines`` longest lines and only its ``coarse_keep`` best go
    # on to all ``n_map_lines`` (the scoring is the cost of this step); 0: one pass
    coarse_lines: int = 300
    coarse_keep: int = 10
    min_length_px: float = 20.0  # shorter detections and projections are left out (as the line query)
    box_margin: float = 0.5  # m: a hypothesis' camera lies within the map lines' box grown by this


def _bearings(p2d: np.ndarray, camera) -> np.ndarray:
    x = geo.unproject_points(p2d, 1.0, camera)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def p3p_hypotheses(p2d: np.ndarray, p3d: np.ndarray, camera, conf: HypothesisConfig, seed: int = 0):
    """Every P3P pose of (a seeded sample of) the triples of matches, with its point inliers.

    Returns:
        poses :math:`(H, 4, 4)` cam_from_world, inliers :math:`(H,)` counts over all matches.
    """
    import poselib

    n = len(p2d)
    if n < 3:
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64)
    triples = np.array(list(combinations(range(n), 3))) if n <= 40 else None
    rng = np.random.default_rng(seed)
    if triples is None or len(triples) > conf.max_triples:
        triples = np.array([rng.choice(n, 3, replace=False) for _ in range(conf.max_triples)])
    x = _bearings(p2d, camera)
    poses = []
    for tri in triples:
        for pose in poselib.p3p(x[tri], p3d[tri]):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = pose.R, pose.t
            poses.append(T)
    if not poses:
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64)
    poses = np.array(poses)
    Xc = p3d @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
    uv, z = geo.project_cam_points(Xc, camera)
    err = np.linalg.norm(uv - p2d[None], axis=-1)
    inliers = ((z > 0) & (err <= conf.max_point_error)).sum(1)
    return poses, inliers


class LineEvidence:
    """The detected lines of one query as per-direction masks of the pixels near them."""

    def __init__(self, lines2d: np.ndarray, camera, conf: HypothesisConfig):
        self.camera, self.conf = camera, conf
        L = np.asarray(lines2d, dtype=float).reshape(-1, 4)
        L = L[np.linalg.norm(L[:, 2:] - L[:, :2], axis=1) >= conf.min_length_px]
        B = conf.angle_bins
        width = np.pi / B
        ang = np.mod(np.arctan2(L[:, 3] - L[:, 1], L[:, 2] - L[:, 0]), np.pi)
        own = np.floor(ang / width).astype(int) % B
        frac = ang / width - np.floor(ang / width)
        nxt = np.where(frac >= 0.5, own + 1, own - 1) % B  # the neighbour bin nearest to the line's angle
        # OpenCV's thick line of width 2 * ceil(d) - 1 covers the pixels within d of the segment (and a sliver
        # more; tests/test_line_rescue.py checks against exact distances): 15x cheaper than a distance transform
        self.near = np.zeros((B, camera.height, camera.width), np.uint8)
        # COLMAP pixels: the centre of pixel (i, j) is (j + 0.5, i + 0.5); 4 fractional bits keep sub-pixel ends
        pts = np.round((L.reshape(-1, 2, 2) - 0.5) * 16).astype(np.int32)
        thick = max(1, 2 * int(np.ceil(conf.max_dist_px)) - 1)
        for b in range(B):
            sel = np.flatnonzero((own == b) | (nxt == b))
            if len(sel):
                cv2.polylines(self.near[b], list(pts[sel]), False, 1, thick, cv2.LINE_8, 4)

    def score(self, poses: np.ndarray, lines3d: np.ndarray) -> np.ndarray:
        """:math:`(H,)` number of ``lines3d`` :math:`(L, 2, 3)` that each pose :math:`(H, 4, 4)` lays on detections."""
        c, cam = self.conf, self.camera
        L = len(lines3d)
        if L == 0 or len(poses) == 0:
            return np.zeros(len(poses), np.int64)
        t = np.linspace(0.1, 0.9, c.samples)
        pts = lines3d[:, None, 0] + t[None, :, None] * (lines3d[:, None, 1] - lines3d[:, None, 0])  # (L, S, 3)
        allp = np.concatenate([lines3d, pts], 1).reshape(-1, 3)  # endpoints first, then the samples
        # one float32 product with K [R | t] per pose: pixels to within 1e-3 px, the cost of this function
        Xh = np.concatenate([allp, np.ones((len(allp), 1))], 1).astype(np.float32)
        uvw = Xh @ geo.projection_matrices(poses, cam).astype(np.float32).transpose(0, 2, 1)  # (H, P, 3)
        z = uvw[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[..., 0] / z, uvw[..., 1] / z
        u, v, z = (a.reshape(len(poses), L, 2 + c.samples) for a in (u, v, z))
        ang = np.mod(np.arctan2(v[..., 1] - v[..., 0], u[..., 1] - u[..., 0]), np.pi)
        b = (np.floor(ang / (np.pi / c.angle_bins)).astype(np.int64) % c.angle_bins)  # (H, L)
        us, vs, zs = u[..., 2:], v[..., 2:], z[..., 2:]
        ok = (zs > 0) & (z[..., :2] > 0).all(-1, keepdims=True) & (us >= 0) & (us < cam.width) & (vs >= 0) & (vs < cam.height)
        flat = (b[..., None] * cam.height + np.where(ok, vs, 0).astype(np.int64)) * cam.width + np.where(ok, us, 0).astype(np.int64)
        near = self.near.reshape(-1)[flat].astype(bool)
        agree = (ok & near).mean(-1) >= c.min_agree  # (H, L)
        # a pose far from the scene sees it small: short projections land on detections by chance
        long_enough = np.hypot(u[..., 1] - u[..., 0], v[..., 1] - v[..., 0]) >= c.min_length_px
        return (agree & long_enough).sum(1)


def scoring_lines(lines3d: np.ndarray, n: int) -> np.ndarray:
    """The ``n`` longest of ``lines3d`` (N, 2, 3): long lines are the ones a wrong pose does not lay on detections
    by chance."""
    lines3d = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    length = np.linalg.norm(lines3d[:, 1] - lines3d[:, 0], axis=1)
    return lines3d[np.sort(np.argsort(-length, kind="stable")[:n])]


def line_verified_poses(p2d: np.ndarray, p3d: np.ndarray, lines2d: np.ndarray, map_lines: np.ndarray, camera,
                        conf: HypothesisConfig, seed: int = 0) -> list:
    """The ``conf.keep`` P3P poses of the point matches that the most map lines agree with, best first.

    Args:
        p2d: (N, 2) COLMAP pixels; p3d: (N, 3) world points; lines2d: (M, 4) query detections;
        map_lines: (L, 2, 3) the lines that score (:func:`scoring_lines`).

    Returns:
        list of (4, 4) cam_from_world.
    """
    p2d = np.asarray(p2d, dtype=float).reshape(-1, 2)
    p3d = np.asarray(p3d, dtype=float).reshape(-1, 3)
    poses, inl = p3p_hypotheses(p2d, p3d, camera, conf, seed)
    if len(poses) == 0:
        return []
    # the camera must stand within the map (its lines' box, with a margin)
    lo, hi = map_lines.reshape(-1, 3).min(0) - conf.box_margin, map_lines.reshape(-1, 3).max(0) + conf.box_margin
    C = -np.einsum("hji,hj->hi", poses[:, :3, :3], poses[:, :3, 3])
    inside = np.all((C >= lo) & (C <= hi), axis=1)
    poses, inl = poses[inside], inl[inside]
    top = np.argsort(-inl, kind="stable")[: conf.max_hypotheses]
    poses, inl = poses[top], inl[top]
    evidence = LineEvidence(lines2d, camera, conf)
    if 0 < conf.coarse_lines < len(map_lines) and conf.coarse_keep < len(poses):
        coarse = evidence.score(poses, scoring_lines(map_lines, conf.coarse_lines))
        first = np.lexsort((-inl, -coarse))[: conf.coarse_keep]
        poses, inl = poses[first], inl[first]
    score = evidence.score(poses, map_lines)
    order = np.lexsort((-inl, -score))[: conf.keep]
    return [poses[i] for i in order if score[i] > 0]
