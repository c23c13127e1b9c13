"""A COLMAP point model of the mapping images with their KNOWN poses: matches verified by the poses' epipolar
geometry, then pycolmap's triangulator with the poses held fixed."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from tqdm import tqdm

from lipmap import logger
from lipmap.errors import InputError

from .. import hloc_io
from .config import TriangulationConfig
from .features import colmap_quiet


def sampson_distance(x0: np.ndarray, x1: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Sampson distance in pixels of correspondences (N, 2) <-> (N, 2) under x1^T F x0 = 0."""
    h0 = np.concatenate([x0, np.ones((len(x0), 1))], 1)
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    Fx0 = h0 @ F.T
    Ftx1 = h1 @ F
    num = np.sum(h1 * Fx0, 1) ** 2
    den = Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2 + Ftx1[:, 0] ** 2 + Ftx1[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-18))


def fundamental_from_poses(cam0_from_world, cam1_from_world, K0: np.ndarray, K1: np.ndarray) -> np.ndarray:
    """F with x1^T F x0 = 0 from two known poses and intrinsics (pixel conventions must agree)."""
    from lipmap.poses import invert_T

    T = cam1_from_world @ invert_T(cam0_from_world)  # cam1_from_cam0
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K1).T @ (tx @ R) @ np.linalg.inv(K0)


def triangulate_map(
    mapping_views: Sequence,
    features_h5,
    pairs,
    matches_h5,
    sfm_dir,
    conf: Optional[TriangulationConfig] = None,
    overwrite: bool = False,
) -> Path:
    """Triangulate matched SIFT features with the KNOWN mapping poses into a COLMAP model.

    Builds a pycolmap.Reconstruction holding the known cameras and poses (COLMAP 4: one trivial
    rig per camera, one trivial frame per image), a COLMAP database with the keypoints and the
    matches that pass the epipolar check against the known relative pose, and runs
    ``pycolmap.triangulate_points`` (COLMAP's point_triangulator: poses and intrinsics stay fixed,
    bundle adjustment refines the points only). This is what hloc's ``triangulation.py`` does,
    with the geometric verification done from the known poses instead of RANSAC.

    Args:
        mapping_views: posed :class:`lipmap.scene.View` objects (names as in the h5 files).
        features_h5, matches_h5: hloc files; pairs: pairs file or list of (name0, name1).
        sfm_dir: output folder (cameras/images/points3D/rigs/frames .bin, plus database.db).

    Returns:
        ``sfm_dir``; skipped when it already holds a model, unless ``overwrite``.
    """
    conf = conf or TriangulationConfig()
    sfm_dir = Path(sfm_dir)
    if not overwrite and (sfm_dir / "points3D.bin").exists() and (sfm_dir / "images.bin").exists():
        logger.info("Skipping triangulation: %s exists.", sfm_dir)
        return sfm_dir
    unique_pairs = _unique_pairs(_checked_pairs(mapping_views, pairs))
    _triangulate_atomically(sfm_dir, mapping_views, features_h5, unique_pairs, matches_h5, conf)
    return sfm_dir


def _checked_pairs(mapping_views: Sequence, pairs) -> list:
    """The pairs as tuples (read from a pairs file or given); InputError if they name an unknown or unposed view."""
    pairs_path = Path(pairs) if isinstance(pairs, (str, Path)) else None
    pairs = hloc_io.read_pairs(pairs_path) if pairs_path is not None else [tuple(p) for p in pairs]
    by_name = {v.name: v for v in mapping_views}
    for a, b in pairs:
        for n in (a, b):
            if n not in by_name:
                raise InputError(f"paired image {n!r} is not one of the mapping views", pairs_path)
    for v in mapping_views:
        if v.cam_from_world is None:
            raise InputError(f"mapping view {v.name} has no pose; triangulation needs known poses")
    return pairs


def _unique_pairs(pairs: list) -> list:
    """The pairs in order without self-pairs and repeats in either order."""
    seen, unique_pairs = set(), []
    for a, b in pairs:  # a pair listed twice (or reversed) would violate the database's unique key
        if a != b and (a, b) not in seen and (b, a) not in seen:
            seen.add((a, b))
            unique_pairs.append((a, b))
    return unique_pairs


def _triangulate_atomically(sfm_dir: Path, mapping_views: Sequence, features_h5, pairs: list, matches_h5,
                            conf: TriangulationConfig):
    """Triangulate in a temporary folder renamed to ``sfm_dir`` at the end (never a partial model); log the model."""
    import shutil

    tmp = sfm_dir.parent / f".{sfm_dir.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    t0 = time.time()
    try:
        rec = _triangulate_into(tmp, mapping_views, features_h5, pairs, matches_h5, conf)
        if sfm_dir.exists():
            shutil.rmtree(sfm_dir)
        tmp.rename(sfm_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info(
        "Triangulated %d points (mean track %.2f, mean reprojection error %.2f px) in %.1f s.",
        rec.num_points3D(),
        rec.compute_mean_track_length() if rec.num_points3D() else 0.0,
        rec.compute_mean_reprojection_error() if rec.num_points3D() else 0.0,
        time.time() - t0,
    )


def _triangulation_options(conf: TriangulationConfig):
    """COLMAP's triangulator options from ``conf``, with the intrinsics held fixed."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.extract_colors = False  # COLMAP 4.2's point_triangulator reads colours anyway; .jpg vs .png names only warn
    opts.random_seed = conf.seed
    opts.num_threads = conf.num_threads
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    tri = opts.triangulation
    tri.min_angle = conf.min_angle_deg
    tri.complete_max_reproj_error = conf.max_reproj_error
    tri.merge_max_reproj_error = conf.max_reproj_error
    tri.ignore_two_view_tracks = conf.ignore_two_view_tracks
    tri.random_seed = conf.seed
    return opts


def _triangulate_into(tmp: Path, mapping_views: Sequence, features_h5, pairs: list, matches_h5,
                      conf: TriangulationConfig):
    """Write the database and the triangulated model's files into ``tmp``; returns the model."""
    import pycolmap

    rec = _reconstruction_and_database(mapping_views, features_h5, pairs, matches_h5, tmp / "database.db", conf)
    opts = _triangulation_options(conf)
    pycolmap.set_random_seed(conf.seed)
    model_dir = tmp / "model"
    model_dir.mkdir()
    with colmap_quiet():
        rec = pycolmap.triangulate_points(rec, tmp / "database.db", tmp, model_dir, clear_points=True, options=opts)
    # hloc's layout: the model files beside database.db
    for f in model_dir.iterdir():
        f.rename(tmp / f.name)
    model_dir.rmdir()
    return rec


def _reconstruction_and_database(mapping_views, features_h5, pairs, matches_h5, db_path, conf: TriangulationConfig):
    """The known-pose Reconstruction (no points) and a COLMAP database of keypoints + verified matches."""
    import pycolmap

    by_name = {v.name: v for v in mapping_views}
    rec = pycolmap.Reconstruction()
    cam_ids: dict = {}
    image_ids: dict[str, int] = {}
    kps: dict[str, np.ndarray] = {}
    db = pycolmap.Database.open(str(db_path))
    try:
        for v in mapping_views:
            if v.camera not in cam_ids:
                cam_ids[v.camera] = len(cam_ids) + 1
                cam = v.camera.to_pycolmap(camera_id=cam_ids[v.camera])
                rec.add_camera_with_trivial_rig(cam)
                db.write_camera(cam, use_camera_id=True)
            image_id = len(image_ids) + 1
            image_ids[v.name] = image_id
            R, t = v.cam_from_world[:3, :3], v.cam_from_world[:3, 3]
            image = pycolmap.Image(name=v.name, camera_id=cam_ids[v.camera], image_id=image_id)
            rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
            db.write_image(pycolmap.Image(name=v.name, camera_id=cam_ids[v.camera], image_id=image_id), use_image_id=True)
            kps[v.name] = hloc_io.read_keypoints(features_h5, v.name)  # COLMAP convention already
            db.write_keypoints(image_id, kps[v.name].astype(np.float32))

        n_raw = n_ver = n_pairs = 0
        with hloc_io.open_h5(matches_h5) as mfd:
            for a, b in tqdm(pairs, desc="verify", disable=len(pairs) < 500):
                matches, _ = hloc_io.read_matches_from(mfd, a, b, matches_h5)
                if len(matches) and (matches[:, 0].max() >= len(kps[a]) or matches[:, 1].max() >= len(kps[b])):
                    raise InputError(f"matches of ({a}, {b}) index beyond the keypoints in {features_h5}", matches_h5)
                va, vb = by_name[a], by_name[b]
                F = fundamental_from_poses(va.cam_from_world, vb.cam_from_world, va.camera.K, vb.camera.K)
                err = sampson_distance(kps[a][matches[:, 0]], kps[b][matches[:, 1]], F) if len(matches) else np.zeros(0)
                inl = matches[err <= conf.max_epipolar_error]
                n_raw += len(matches)
                if len(inl) < conf.min_inliers:
                    continue
                ia, ib = image_ids[a], image_ids[b]
                if ia > ib:  # COLMAP stores a pair with the smaller image id first
                    ia, ib, matches, inl, va, vb = ib, ia, matches[:, ::-1], inl[:, ::-1], vb, va
                db.write_matches(ia, ib, np.ascontiguousarray(matches, dtype=np.uint32))
                tvg = pycolmap.TwoViewGeometry()
                tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                tvg.inlier_matches = np.ascontiguousarray(inl, dtype=np.uint32)
                T = vb.cam_from_world @ np.linalg.inv(va.cam_from_world)
                tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
                db.write_two_view_geometry(ia, ib, tvg)
                n_ver += len(inl)
                n_pairs += 1
    finally:
        db.close()
    logger.info("Verified %d / %d matches with the known poses; %d / %d pairs kept.", n_ver, n_raw, n_pairs, len(pairs))
    return rec


def model_stats(sfm_dir_or_rec) -> dict:
    """Number of 3D points, mean track length, mean / median reprojection error (px) of a model."""
    rec = hloc_io.read_sfm(sfm_dir_or_rec) if isinstance(sfm_dir_or_rec, (str, Path)) else sfm_dir_or_rec
    errs = np.array([p.error for p in rec.points3D.values()])
    return {
        "num_points3D": int(rec.num_points3D()),
        "mean_track_length": float(rec.compute_mean_track_length()) if len(errs) else 0.0,
        "mean_reproj_error": float(errs.mean()) if len(errs) else float("nan"),
        "median_reproj_error": float(np.median(errs)) if len(errs) else float("nan"),
    }
