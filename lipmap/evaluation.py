"""Mapping metrics M1 and M2 of the LiP-Map paper (appendix "Computation of Evaluation Metrics").

M1 (3D reconstruction metrics), at the line level (100 points sampled uniformly on each line,
endpoints included) and the junction level (the 2 endpoints of each line):

    D_pre = distance of each predicted point to the ground truth
    D_gt  = distance of each ground-truth point to the predicted points
    ACC = mean(D_pre)      COMP = mean(D_gt)
    PREC@t = mean(D_pre <= t)      RECALL@t = mean(D_gt <= t)      F@t = 2 P R / (P + R)

The paper's appendix swaps the names D_pre / D_gt between its ACC/COMP and PREC/RECALL formulas;
we implement the standard meaning above (ACC and PREC look at the prediction, COMP and RECALL at
the ground truth), which is also what the cited works (AirPlanes, NEAT) do.

M2 (LIMAP's metrics): 1000 points per line; ratio_i = fraction of line i's points within tau of
the ground truth; R_tau = sum_i length_i * ratio_i (metres), P_tau = 100 * mean(ratio_i > 0)
(percent of lines with any portion within tau), taus 5 / 10 / 50 mm by default; plus the average
supports (images and 2D lines per track).

Ground truth is a point cloud (PLY / npy / array; 7-Scenes: :func:`gt_from_depth`) or a mesh.
For a mesh:
- D_gt uses points sampled uniformly on the surface (``gt_points_per_m2``, fixed seed);
- D_pre is the EXACT point-to-surface distance (``mesh_distance="exact"``): candidate triangles
  are those of the ``mesh_candidates`` nearest points of a dense surface sample, and the distance
  is the minimum exact point-triangle distance over them. This is exact whenever the nearest
  triangle owns one of those samples: always for the large faces of indoor meshes; on a finely
  tessellated sphere (icosphere level 4, points within 10 cm) 1 of 300 points was off, by 0.02 mm
  (tests/test_evaluation.py). Cost ~1.3 us per distinct candidate triangle. (trimesh.proximity
  needs rtree, which is not a dependency, and loops in Python.) ``mesh_distance="sample"`` uses
  only the dense sample: faster, biased upwards by ~0.2 mm on average, up to ~5 mm.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
from scipy.spatial import cKDTree

from . import logger
from .errors import InputError
from .presets import resolve
from .geometry import sample_segments


@dataclass(frozen=True)
class EvalConfig:
    m1_thresholds: tuple = (0.05,)  # metres
    m1_line_samples: int = 100
    m2_taus_mm: tuple = (5, 10, 50)
    m2_samples: int = 1000
    gt_points_per_m2: float = 10000.0  # mesh -> GT point cloud for COMP / RECALL (1 cm spacing)
    max_gt_points: int = 2_000_000
    mesh_distance: str = "exact"  # "exact" or "sample"
    mesh_samples_per_m2: float = 40000.0  # dense sample for mesh distance queries (5 mm spacing)
    max_mesh_samples: int = 4_000_000
    mesh_candidates: int = 8
    seed: int = 0
    workers: int = -1  # cKDTree query threads


confs = {
    "default": EvalConfig(),
    "fast": EvalConfig(m2_samples=200, mesh_distance="sample", mesh_samples_per_m2=10000.0),
    "paper-1-5-10mm": EvalConfig(m2_taus_mm=(1, 5, 10)),
}


def get_conf(conf=None) -> EvalConfig:
    """An :class:`EvalConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "mapping evaluation", default="default")


# ----------------------------------------------------------------------------------------------
# ground truth
# ----------------------------------------------------------------------------------------------
@dataclass
class GroundTruth:
    """GT points for D_gt and a distance function for D_pre (KD-tree, or exact mesh distance)."""

    points: np.ndarray
    mesh: Optional[object] = None
    conf: EvalConfig = field(default_factory=EvalConfig)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if len(self.points) == 0:
            raise InputError("ground truth has no points")
        self._tree = None
        self._dense = None

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree

    def _dense_sample(self):
        if self._dense is None:
            import trimesh

            c = self.conf
            n = int(min(max(self.mesh.area * c.mesh_samples_per_m2, 1000), c.max_mesh_samples))
            pts, faces = trimesh.sample.sample_surface(self.mesh, n, seed=c.seed + 1)
            # every face gets at least its centroid, so small faces are never missed as candidates
            cen = self.mesh.triangles_center
            pts = np.concatenate([pts, cen])
            faces = np.concatenate([faces, np.arange(len(cen))])
            self._dense = (cKDTree(pts), faces)
        return self._dense

    def distance(self, query: np.ndarray, upper: float = np.inf) -> np.ndarray:
        """Distance of query points (Q, 3) to the ground truth; values above ``upper`` may be
        returned as inf (faster KD-tree queries when only thresholds matter)."""
        query = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        if len(query) == 0:
            return np.zeros(0)
        c = self.conf
        if self.mesh is None:
            d, _ = self.tree.query(query, k=1, distance_upper_bound=upper, workers=c.workers)
            return d
        tree, faces = self._dense_sample()
        if c.mesh_distance == "sample":
            d, _ = tree.query(query, k=1, distance_upper_bound=upper, workers=c.workers)
            return d
        if c.mesh_distance != "exact":
            raise ValueError(f"mesh_distance must be 'exact' or 'sample', got {c.mesh_distance!r}")
        k = max(1, int(c.mesh_candidates))
        # true distance >= nearest-sample distance - (gap between samples), so a query whose
        # nearest sample is beyond upper + margin is beyond upper: it needs no exact refinement
        margin = 4.0 / np.sqrt(c.mesh_samples_per_m2)  # ~4x the mean sample spacing
        ds, idx = tree.query(query, k=k, distance_upper_bound=upper + margin, workers=c.workers)
        ds, idx = ds.reshape(len(query), k), idx.reshape(len(query), k)
        out = np.full(len(query), np.inf)
        todo = np.flatnonzero(np.isfinite(ds[:, 0]))
        if len(todo):
            from trimesh.triangles import closest_point

            tri = self.mesh.triangles
            cand = idx[todo]
            ok = cand < len(faces)
            cand_faces = np.where(ok, faces[np.minimum(cand, len(faces) - 1)], -1)
            best = np.full(len(todo), np.inf)
            for j in range(k):
                sel = np.flatnonzero(cand_faces[:, j] >= 0)
                if j > 0:  # skip faces already tried for this query
                    dup = (cand_faces[sel, :j] == cand_faces[sel, j : j + 1]).any(1)
                    sel = sel[~dup]
                if not len(sel):
                    continue
                q = query[todo[sel]]
                for s in range(0, len(sel), 500_000):
                    ss = slice(s, s + 500_000)
                    cp = closest_point(tri[cand_faces[sel[ss], j]], q[ss])
                    best[sel[ss]] = np.minimum(best[sel[ss]], np.linalg.norm(cp - q[ss], axis=1))
            out[todo] = best
        if np.isfinite(upper):
            out[out > upper] = np.inf
        return out


def load_points(path) -> np.ndarray:
    """(P, 3) points from a PLY/OBJ/... (trimesh), .npy or .npz (key "points" or first array)."""
    path = Path(path)
    if not path.exists():
        raise InputError("ground-truth file is missing", path)
    if path.suffix in (".npy", ".npz"):
        arr = np.load(path)
        if path.suffix == ".npz":
            arr = arr["points"] if "points" in arr.files else arr[arr.files[0]]
        pts = np.asarray(arr, dtype=np.float64)
    else:
        import trimesh

        try:
            geom = trimesh.load(path, process=False)
        except Exception as e:  # trimesh raises many types for bad files
            raise InputError(f"cannot read ground truth: {e}", path) from e
        if isinstance(geom, trimesh.Scene):
            geom = geom.dump(concatenate=True)
        pts = np.asarray(geom.vertices, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InputError(f"ground truth must be a non-empty (P, 3) point set, got {pts.shape}", path)
    return pts


def load_ground_truth(gt, conf: Optional[EvalConfig] = None) -> GroundTruth:
    """A :class:`GroundTruth` from a path (mesh with faces -> mesh GT; otherwise points), a
    trimesh.Trimesh, a (P, 3) array, or a GroundTruth (returned with ``conf`` applied)."""
    conf = conf or EvalConfig()
    if isinstance(gt, GroundTruth):
        return GroundTruth(gt.points, gt.mesh, conf)
    import trimesh

    if isinstance(gt, (str, Path)):
        path = Path(gt)
        if not path.exists():
            raise InputError("ground-truth file is missing", path)
        if path.suffix not in (".npy", ".npz"):
            try:
                geom = trimesh.load(path, process=False)
            except Exception as e:
                raise InputError(f"cannot read ground truth: {e}", path) from e
            if isinstance(geom, trimesh.Scene):
                geom = geom.dump(concatenate=True)
            if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
                return load_ground_truth(geom, conf)
        return GroundTruth(load_points(path), None, conf)
    if isinstance(gt, trimesh.Trimesh):
        if len(gt.faces) == 0:
            return GroundTruth(gt.vertices, None, conf)
        n = int(min(max(gt.area * conf.gt_points_per_m2, 1000), conf.max_gt_points))
        pts, _ = trimesh.sample.sample_surface(gt, n, seed=conf.seed)
        return GroundTruth(pts, gt, conf)
    return GroundTruth(np.asarray(gt, dtype=np.float64), None, conf)


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """One int64 per voxel (21 bits per axis: +-1e6 voxels, i.e. +-10 km at 1 cm)."""
    k = np.floor(points / voxel).astype(np.int64) + (1 << 20)
    if len(k) and (k.min() < 0 or k.max() >= (1 << 21)):
        raise InputError(f"points span more than 2^21 voxels of {voxel} m per axis")
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def _voxel_sums(keys: np.ndarray, values: np.ndarray, counts: np.ndarray):
    """Group rows by key: (unique keys, summed values (K, 3), summed counts (K,))."""
    uk, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    sums = np.stack([np.bincount(inv, values[:, i], len(uk)) for i in range(values.shape[1])], 1)
    return uk, sums, np.bincount(inv, counts, len(uk))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel (deterministic order: sorted voxel keys)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return points
    _, inv, counts = np.unique(_voxel_keys(points, voxel), return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    sums = np.stack([np.bincount(inv, points[:, i], len(counts)) for i in range(3)], 1)
    return sums / counts[:, None]


def gt_from_depth(views: Sequence, voxel: float = 0.01, stride: int = 1, max_depth: float = 10.0) -> np.ndarray:
    """Fuse the registered depth maps of posed views into one voxel-downsampled world point cloud.

    This is the 7-Scenes ground truth for mapping metrics (the dataset has no mesh).

    Args:
        views: :class:`~lipmap.scene.View` with depth and ``cam_from_world``.
        voxel: voxel size in metres (one centroid per occupied voxel).
        stride: use every ``stride``-th pixel in each direction.
        max_depth: ignore depths beyond this (metres).

    Returns:
        **points** :math:`(P, 3)` world coordinates.
    """
    from tqdm import tqdm

    from .geometry import backproject_depth
    from .poses import invert_T

    # per-frame voxel sums (a frame's 300k points shrink ~5x at 1 cm), merged every 32 frames so memory is
    # that of the scene's occupied voxels, not of the frames
    keys_l, sums_l, counts_l = [], [], []
    for i, v in enumerate(tqdm(views, desc="fuse depth", disable=len(views) < 2)):
        depth = v.load_depth()
        if stride > 1:
            d = np.zeros_like(depth)
            d[::stride, ::stride] = depth[::stride, ::stride]
            depth = d
        depth = np.where(depth < max_depth, depth, 0)
        pts, _ = backproject_depth(depth, v.camera)
        if not len(pts):
            continue
        T = invert_T(v.cam_from_world)
        pts = pts @ T[:3, :3].T + T[:3, 3]
        k, s, c = _voxel_sums(_voxel_keys(pts, voxel), pts, np.ones(len(pts)))
        keys_l.append(k)
        sums_l.append(s)
        counts_l.append(c)
        if len(keys_l) >= 32:
            merged = _voxel_sums(np.concatenate(keys_l), np.concatenate(sums_l), np.concatenate(counts_l))
            keys_l, sums_l, counts_l = [merged[0]], [merged[1]], [merged[2]]
    if not keys_l:
        raise InputError("no valid depth in the given views")
    _, sums_all, counts_all = _voxel_sums(np.concatenate(keys_l), np.concatenate(sums_l), np.concatenate(counts_l))
    return sums_all / counts_all[:, None]


def scene_ground_truth(scene, voxel: float = 0.01, max_frames: int = 1000):
    """The mapping ground truth of a :class:`~lipmap.scene.Scene`: its mesh when it has one (synthetic
    scenes), else the depth of its views fused by :func:`gt_from_depth` (7-Scenes): all of them, or every
    k-th when there are more than ``max_frames`` (a 7-Scenes scene has 12,000; 1,000 evenly spread ones
    see the same surfaces)."""
    if getattr(scene, "gt_mesh", None) is not None:
        return scene.gt_mesh
    views = list(scene.mapping) + list(scene.query)
    step = -(-len(views) // max_frames)
    if step > 1:
        logger.info("ground truth: fusing every %dth of %d frames", step, len(views))
    return gt_from_depth(views[::step], voxel=voxel)


def write_points_ply(path, points: np.ndarray) -> Path:
    """Binary PLY point cloud (float32)."""
    from .imageio import atomic_path

    points = np.asarray(points, dtype="<f4").reshape(-1, 3)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n" \
             "property float x\nproperty float y\nproperty float z\nend_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(points.tobytes())
    return Path(path)


# ----------------------------------------------------------------------------------------------
# metrics
# ----------------------------------------------------------------------------------------------
def _prf(d_pre: np.ndarray, d_gt: np.ndarray, thresholds) -> dict:
    out = {"acc": float(np.mean(d_pre)) if len(d_pre) else float("nan"),
           "comp": float(np.mean(d_gt)) if len(d_gt) else float("nan")}
    for t in thresholds:
        p = float(np.mean(d_pre <= t)) if len(d_pre) else 0.0
        r = float(np.mean(d_gt <= t)) if len(d_gt) else 0.0
        out[f"prec@{t:g}"] = p
        out[f"recall@{t:g}"] = r
        out[f"f@{t:g}"] = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return out


def m1_metrics(points_pred: np.ndarray, gt: GroundTruth, thresholds=(0.05,)) -> dict:
    """ACC, COMP, PREC/RECALL/F at each threshold for one predicted point set (P, 3)."""
    points_pred = np.asarray(points_pred, dtype=np.float64).reshape(-1, 3)
    d_pre = gt.distance(points_pred)
    if len(points_pred):
        d_gt, _ = cKDTree(points_pred).query(gt.points, k=1, workers=gt.conf.workers)
    else:
        d_gt = np.full(len(gt.points), np.inf)
    return _prf(d_pre, d_gt, thresholds)


def _sample_distances_thresholded(lines: np.ndarray, gt: GroundTruth, taus: np.ndarray, n: int, stride: int = 8):
    """Distances (L, n) of the n samples per line, exact wherever they decide a ``d <= tau`` test.

    The distance to the GT is 1-Lipschitz along a line, so a sample k steps from a queried one
    differs from it by at most k * step: every ``stride``-th sample is queried, and the others
    only when that bound leaves some threshold undecided (their value is otherwise replaced by
    the queried neighbour's, which gives the same indicator for every tau). Identical indicators
    to querying all samples, ~5x fewer queries.
    """
    L = len(lines)
    pts = sample_segments(lines, n)  # (L, n, 3)
    if n <= 2 * stride:
        return gt.distance(pts.reshape(-1, 3), upper=float(taus.max())).reshape(L, n)
    step = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=-1) / (n - 1)  # (L,)
    coarse = np.unique(np.append(np.arange(0, n, stride), n - 1))
    j = np.arange(n)
    nearest = coarse[np.clip(np.searchsorted(coarse, j), 0, len(coarse) - 1)]
    prev = coarse[np.clip(np.searchsorted(coarse, j) - 1, 0, len(coarse) - 1)]
    nearest = np.where(np.abs(prev - j) < np.abs(nearest - j), prev, nearest)  # (n,)
    off = np.abs(nearest - j)[None, :] * step[:, None]  # (L, n) Lipschitz bound
    upper = float(taus.max() + off.max())
    d_coarse = gt.distance(pts[:, coarse].reshape(-1, 3), upper=upper).reshape(L, len(coarse))
    d = np.empty((L, n))
    d[:, coarse] = d_coarse
    pos = np.searchsorted(coarse, nearest)
    dn = d_coarse[:, pos]  # (L, n): distance of each sample's queried neighbour
    undecided = np.zeros((L, n), dtype=bool)
    for t in taus:
        undecided |= (dn - off <= t) & (dn + off > t)
    undecided[:, coarse] = False
    d[:] = np.where(undecided, np.nan, dn)
    d[:, coarse] = d_coarse
    li, si = np.nonzero(undecided)
    if len(li):
        d[li, si] = gt.distance(pts[li, si], upper=float(taus.max()))
    return d


def m2_metrics(lines: np.ndarray, gt: GroundTruth, taus_mm=(5, 10, 50), n_samples: int = 1000) -> dict:
    """R_tau (metres of line within tau) and P_tau (percent of lines with any point within tau)."""
    lines = np.asarray(lines, dtype=np.float64).reshape(-1, 2, 3)
    out = {}
    if len(lines) == 0:
        for t in taus_mm:
            out[f"R@{t:g}mm"] = 0.0
            out[f"P@{t:g}mm"] = 0.0
        return out
    taus = np.array(taus_mm, dtype=float) / 1000.0
    lengths = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=-1)
    ratios = np.zeros((len(lines), len(taus)))
    # chunks keep memory bounded (1000 samples x 3 x 8 bytes = 24 kB per line)
    chunk = max(1, 2_000_000 // n_samples)
    for s in range(0, len(lines), chunk):
        d = _sample_distances_thresholded(lines[s : s + chunk], gt, taus, n_samples)
        ratios[s : s + chunk] = (d[:, :, None] <= taus).mean(axis=1)
    for j, t in enumerate(taus_mm):
        out[f"R@{t:g}mm"] = float((lengths * ratios[:, j]).sum())
        out[f"P@{t:g}mm"] = float(100.0 * np.mean(ratios[:, j] > 0))
    return out


def evaluate_linemap(
    linemap, gt, conf: Union[None, str, EvalConfig] = None, **overrides
) -> dict:
    """M1 (line and junction level) and M2 of a line map against a GT mesh or point cloud.

    Args:
        linemap: a :class:`~lipmap.linemap.LineMap`, a path to ``linemap.h5`` or (N, 2, 3) lines
            (then no supports are reported).
        gt: mesh/point-cloud path, trimesh.Trimesh, (P, 3) points or :class:`GroundTruth`.
        conf: preset name ("default", "fast", "paper-1-5-10mm") or :class:`EvalConfig`; keyword
            overrides are applied on top (e.g. ``m1_thresholds=(0.02, 0.05)``).

    Returns:
        ``{"n_lines", "total_length", "M1": {"line": {acc, comp, prec@t, recall@t, f@t},
        "junction": {...}}, "M2": {"R@5mm", ..., "P@5mm", ..., "supports_images",
        "supports_lines", "supports_images_median"}, "gt": {"kind", "n_points"}}``; distances in metres, P in percent.
    """
    from .linemap import LineMap

    conf = get_conf(conf)
    if overrides:
        conf = replace(conf, **overrides)
    if isinstance(linemap, (str, Path)):
        linemap = LineMap.load(linemap)
    supports = None
    if isinstance(linemap, LineMap):
        lines, supports = linemap.lines, linemap.supports
    else:
        lines = np.asarray(linemap, dtype=np.float64).reshape(-1, 2, 3)
    gt = load_ground_truth(gt, conf)
    n = len(lines)
    if n == 0:
        logger.warning("Evaluating an empty line map.")
    line_pts = sample_segments(lines, conf.m1_line_samples).reshape(-1, 3)
    junctions = lines.reshape(-1, 3)
    res = {
        "n_lines": int(n),
        "total_length": float(np.linalg.norm(lines[:, 1] - lines[:, 0], axis=-1).sum()),
        "M1": {
            "line": m1_metrics(line_pts, gt, conf.m1_thresholds),
            "junction": m1_metrics(junctions, gt, conf.m1_thresholds),
        },
        "M2": m2_metrics(lines, gt, conf.m2_taus_mm, conf.m2_samples),
        "gt": {"kind": "mesh" if gt.mesh is not None else "points", "n_points": int(len(gt.points)),
               "mesh_distance": conf.mesh_distance if gt.mesh is not None else "kdtree"},
    }
    if supports is not None and len(supports):
        res["M2"]["supports_images"] = float(np.mean(supports[:, 0]))
        res["M2"]["supports_lines"] = float(np.mean(supports[:, 1]))
        res["M2"]["supports_images_median"] = float(np.median(supports[:, 0]))
    else:
        for k in ("supports_images", "supports_lines", "supports_images_median"):
            res["M2"][k] = float("nan")
    return res


def main(linemap_path, gt, out_json, conf: Union[None, str, EvalConfig] = None, overwrite: bool = False) -> Path:
    """Step entry: evaluate ``linemap.h5`` against ``gt`` and write the metrics to ``out_json`` (reused when
    made from the same map, ground truth and settings)."""
    from .artifacts import Stamp, read_stamp, reuse, write_stamp
    from .imageio import write_text_atomic

    out_json = Path(out_json)
    conf = get_conf(conf)
    lm_stamp = read_stamp(linemap_path) if isinstance(linemap_path, (str, Path)) else None
    gt_key = str(Path(gt).resolve()) if isinstance(gt, (str, Path)) else "in-memory"
    stamp = Stamp("map-eval", {"conf": asdict(conf), "gt": gt_key,
                               "linemap": lm_stamp.digest if lm_stamp else str(linemap_path)})
    if reuse(out_json, stamp, overwrite, "map evaluation", replace_stale=True):
        return out_json
    res = evaluate_linemap(linemap_path, gt, conf)
    write_text_atomic(out_json, json.dumps(res, indent=2))
    write_stamp(out_json, stamp)
    logger.info("Line map metrics: %s", format_metrics(res))
    return out_json


def format_metrics(res: dict) -> str:
    """One-line summary: line-level ACC/PREC, R and P at each tau, supports."""
    m1 = res["M1"]["line"]
    parts = [f"{res['n_lines']} lines", f"ACC-L {100 * m1['acc']:.2f} cm", f"COMP-L {100 * m1['comp']:.2f} cm"]
    parts += [f"{k.upper()} {v:.3f}" for k, v in m1.items() if "@" in k]
    parts += [f"{k} {v:.2f}" for k, v in res["M2"].items()]
    return ", ".join(parts)


__all__ = [
    "scene_ground_truth",
    "EvalConfig",
    "confs",
    "GroundTruth",
    "load_points",
    "load_ground_truth",
    "voxel_downsample",
    "gt_from_depth",
    "write_points_ply",
    "m1_metrics",
    "m2_metrics",
    "evaluate_linemap",
    "main",
    "format_metrics",
]
