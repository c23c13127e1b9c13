"""Built-in point pipeline: SIFT convention, matching, pairs, triangulation with known poses, 2D-3D
matches, and the whole chain on real RedKitchen frames."""
from __future__ import annotations

import time

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap.geometry import project_points
from lipmap.imageio import write_color
from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera, View
from localization import hloc_io, points
from localization.points import (
    MatchConfig,
    PairsConfig,
    SiftConfig,
    extract_sift,
    fundamental_from_poses,
    match_features,
    mutual_nn_ratio,
    pairs_from_poses,
    point_matches_for_query,
    point_matches_from_hloc,
    sampson_distance,
    triangulate_map,
)

CAM = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))


def blob_image(centers, size=(240, 200), sigma=4.0):
    """uint8 image of Gaussian blobs centred on pixel INDICES (col, row) - the pixel's centre."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w))
    for cx, cy in centers:
        img += np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def image_view(tmp_path, name, img):
    path = tmp_path / name.replace("/", "_").replace(".png", ".jpg").replace(".jpg", ".png")
    write_color(path, np.repeat(img[..., None], 3, -1))
    cam = Camera(img.shape[1], img.shape[0], (200.0, 200.0, img.shape[1] / 2, img.shape[0] / 2))
    return View(name=name, camera=cam, cam_from_world=np.eye(4), color_path=path)


class TestSift:
    def test_keypoints_colmap_convention(self, tmp_path):
        """Convention pin: a blob centred on pixel index (i, j) is detected at (i + 0.5, j + 0.5),
        i.e. pycolmap returns COLMAP coordinates; the features file holds hloc's (i, j)."""
        centers = [(60, 70), (150, 120), (190, 50)]
        f = points.sift_features(blob_image(centers), SiftConfig(max_keypoints=100))
        for c in centers:
            d = np.linalg.norm(f["keypoints"] - (np.array(c) + 0.5), axis=1)
            assert d.min() < 0.05, (c, d.min())
        assert f["descriptors"].shape == (len(f["keypoints"]), 128)
        np.testing.assert_allclose(np.linalg.norm(f["descriptors"], axis=1), 1.0, rtol=1e-5)

        view = image_view(tmp_path, "seq-01/blobs.png", blob_image(centers))
        h5 = extract_sift([view], tmp_path / "feats.h5", SiftConfig(max_keypoints=100))
        with h5py.File(h5, "r") as fd:
            raw = fd["seq-01/blobs.png"]["keypoints"][()]
            assert fd["seq-01/blobs.png"]["descriptors"].shape[0] == 128
            np.testing.assert_array_equal(fd["seq-01/blobs.png"]["image_size"][()], [240, 200])
        for c in centers:
            assert np.linalg.norm(raw - np.array(c), axis=1).min() < 0.05

    def test_extract_skips_done_images(self, tmp_path):
        rng = np.random.default_rng(0)
        views = [image_view(tmp_path, f"im{i}.png", blob_image(rng.uniform(20, 180, (6, 2)))) for i in range(3)]
        calls = []
        for v in views:
            orig = v.load_color

            def counted(gray=False, _orig=orig, _n=v.name):
                calls.append(_n)
                return _orig(gray=gray)

            object.__setattr__(v, "load_color", counted)
        h5 = tmp_path / "f.h5"
        extract_sift(views[:2], h5, SiftConfig(max_keypoints=50))
        extract_sift(views, h5, SiftConfig(max_keypoints=50))
        assert calls == ["im0.png", "im1.png", "im2.png"]
        assert hloc_io.list_h5_names(h5) == ["im0.png", "im1.png", "im2.png"]
        extract_sift(views[:1], h5, SiftConfig(max_keypoints=50), overwrite=True)
        assert hloc_io.list_h5_names(h5) == ["im0.png"]  # overwrite starts the file afresh

    def test_bad_image(self):
        with pytest.raises(Exception, match="uint8"):
            points.sift_features(np.zeros((10, 10), np.float32), SiftConfig())


class TestMatching:
    def test_mutual_nn_ratio(self):
        rng = np.random.default_rng(0)
        d0 = rng.normal(size=(50, 32))
        d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
        perm = rng.permutation(50)
        d1 = d0[perm] + rng.normal(0, 0.01, (50, 32))
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        m0, s0 = mutual_nn_ratio(d0, d1)
        np.testing.assert_array_equal(perm[m0], np.arange(50))  # d1[m0[i]] is d0[i]
        assert np.all(s0 > 0.99)
        # an ambiguous twin fails the ratio test
        d1b = np.concatenate([d1, d1[:1] + 1e-4])
        d1b /= np.linalg.norm(d1b, axis=1, keepdims=True)
        m0b, _ = mutual_nn_ratio(d0, d1b)
        assert m0b[perm[0]] == -1 and (m0b >= 0).sum() == 49
        # without the ratio test the twin is matched, and mutual-ness still holds
        m0c, _ = mutual_nn_ratio(d0, d1b, MatchConfig(ratio=1.0))
        assert (m0c >= 0).sum() == 50

    def test_mutual_check(self):
        d0 = np.array([[1.0, 0], [0.96, 0.28]])  # both closest to d1[0]
        d1 = np.array([[0.99, 0.141], [-1.0, 0]])
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        m0, _ = mutual_nn_ratio(d0, d1, MatchConfig(ratio=1.0, mutual=True))
        assert (m0 >= 0).sum() == 1
        m0, _ = mutual_nn_ratio(d0, d1, MatchConfig(ratio=1.0, mutual=False))
        assert m0.tolist() == [0, 0]

    def test_match_features_file(self, tmp_path):
        rng = np.random.default_rng(1)
        feats = tmp_path / "f.h5"
        desc = {n: rng.normal(size=(20, 8)) for n in ("a/x.png", "b/y.png", "c/z.png")}
        with h5py.File(feats, "w") as fd:
            for n, d in desc.items():
                hloc_io.write_features(fd, n, rng.uniform(0, 100, (20, 2)), d)
        out = tmp_path / "m.h5"
        match_features([("a/x.png", "b/y.png"), ("b/y.png", "a/x.png")], feats, out)
        with h5py.File(out, "r") as fd:
            assert list(fd.keys()) == ["a-x.png"] and list(fd["a-x.png"].keys()) == ["b-y.png"]
            assert fd["a-x.png/b-y.png/matches0"].dtype == np.int32
        before = out.stat().st_mtime_ns
        match_features([("b/y.png", "a/x.png")], feats, out)  # already there, reversed: skipped
        assert out.stat().st_mtime_ns == before
        match_features([("a/x.png", "c/z.png")], feats, out)
        m, _ = hloc_io.read_matches(out, "c/z.png", "a/x.png")  # stored as (a, c): read reversed
        m0, _ = mutual_nn_ratio(desc["a/x.png"] / np.linalg.norm(desc["a/x.png"], axis=1, keepdims=True),
                                desc["c/z.png"] / np.linalg.norm(desc["c/z.png"], axis=1, keepdims=True))
        np.testing.assert_array_equal(m, np.stack([m0[m0 >= 0], np.flatnonzero(m0 >= 0)], 1))
        with pytest.raises(Exception, match="no group"):
            match_features([("a/x.png", "d/w.png")], feats, out)


def _rig(n=6, seed=0):
    """Cameras on an arc looking at a cloud of points ~3 m away."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.5, -1, 2.5], [1.5, 1, 4.0], (400, 3))
    views = []
    for i in range(n):
        R = Rotation.from_rotvec([0, (i - n / 2) * 0.06, 0]).as_matrix() @ Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix()
        C = np.array([(i - n / 2) * 0.15, rng.normal(0, 0.02), 0.0])
        views.append(View(name=f"seq-01/frame-{i:06d}.color.png", camera=CAM, cam_from_world=make_T(R, -R @ C), color_path=None))
    return X, views


class TestGeometry:
    def test_sampson_zero_on_true_correspondences(self):
        X, views = _rig()
        a, b = views[0], views[3]
        xa, _ = project_points(X, a.cam_from_world, CAM)
        xb, _ = project_points(X, b.cam_from_world, CAM)
        F = fundamental_from_poses(a.cam_from_world, b.cam_from_world, CAM.K, CAM.K)
        assert sampson_distance(xa, xb, F).max() < 1e-6
        # a shift along the epipolar line's normal of 3 px reads as ~3 px
        line = np.concatenate([xa, np.ones((len(xa), 1))], 1) @ F.T
        nrm = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
        d = sampson_distance(xa, xb + 3 * nrm, F)
        assert np.all(d > 1.4) and np.all(d < 3.1)  # Sampson splits the error over both images

    def test_pairs_from_poses(self, tmp_path):
        _, views = _rig(n=8)
        away = views[0].cam_from_world.copy()
        away = make_T(Rotation.from_rotvec([0, np.pi, 0]).as_matrix() @ away[:3, :3], away[:3, 3])
        views.append(View(name="seq-01/away.color.png", camera=CAM, cam_from_world=away, color_path=None))
        pairs = pairs_from_poses(views, tmp_path / "pairs.txt", PairsConfig(num_neighbors=2))
        assert hloc_io.read_pairs(tmp_path / "pairs.txt") == pairs
        assert all("away" not in a + b for a, b in pairs)  # faces the other way: no overlap
        idx = {v.name: i for i, v in enumerate(views)}
        gaps = [abs(idx[a] - idx[b]) for a, b in pairs]
        assert max(gaps) <= 2 and len(pairs) >= 8  # neighbours along the arc
        assert len(set(pairs)) == len(pairs) and all(idx[a] < idx[b] for a, b in pairs)


def _synthetic_files(tmp_path, noise=0.3, outliers=30, seed=0):
    """Features + matches of a synthetic rig in hloc's layout; keypoint order shuffled per image."""
    rng = np.random.default_rng(seed)
    X, views = _rig(seed=seed)
    feats, matches = tmp_path / "feats.h5", tmp_path / "matches.h5"
    order = {}
    with h5py.File(feats, "w") as fd:
        for v in views:
            uv, _ = project_points(X, v.cam_from_world, CAM)
            perm = rng.permutation(len(X))  # keypoint k of this image is point perm[k]
            order[v.name] = perm
            hloc_io.write_features(fd, v.name, uv[perm] + rng.normal(0, noise, uv.shape), np.zeros((len(X), 2)))
    pairs = [(a.name, b.name) for i, a in enumerate(views) for b in views[i + 1 :]]
    with h5py.File(matches, "w") as fd:
        for a, b in pairs:
            inv_b = np.argsort(order[b])
            m0 = inv_b[order[a]].astype(np.int32)  # keypoint of b seeing the same point
            bad = rng.choice(len(X), outliers, replace=False)
            m0[bad] = rng.integers(0, len(X), outliers)  # wrong matches
            hloc_io.write_matches(fd, a, b, m0, np.ones(len(X)))
    return X, views, feats, matches, pairs, order


class TestTriangulation:
    @pytest.mark.parametrize("noise, tol_median, tol_99", [(0.0, 1e-5, 1e-3), (0.3, 0.015, 0.05)])
    def test_known_poses_recover_points(self, tmp_path, noise, tol_median, tol_99):
        """Exact keypoints give exact points (float32 storage aside): no pixel-origin bias between
        features.h5, the database and the model; 0.3 px noise at ~3 m gives mm-level points."""
        X, views, feats, matches, pairs, order = _synthetic_files(tmp_path, noise=noise)
        sfm = triangulate_map(views, feats, pairs, matches, tmp_path / "sfm")
        rec = hloc_io.read_sfm(sfm)
        assert rec.num_points3D() > 0.9 * len(X)
        # poses untouched
        for v in views:
            im = rec.find_image_with_name(v.name)
            np.testing.assert_allclose(im.cam_from_world().matrix(), v.cam_from_world[:3], atol=1e-9)
        errs = []
        for p in rec.points3D.values():
            el = p.track.elements[0]
            name = rec.images[el.image_id].name
            errs.append(np.linalg.norm(p.xyz - X[order[name][el.point2D_idx]]))
        errs = np.array(errs)
        assert np.median(errs) < tol_median and np.percentile(errs, 99) < tol_99
        stats = points.model_stats(sfm)
        assert stats["mean_reproj_error"] < max(2 * noise, 0.05) and stats["mean_track_length"] > 5
        assert (sfm / "points3D.bin").exists() and (sfm / "rigs.bin").exists()

    def test_skip_and_resume(self, tmp_path):
        _, views, feats, matches, pairs, _ = _synthetic_files(tmp_path)
        sfm = triangulate_map(views, feats, pairs, matches, tmp_path / "sfm")
        t = (sfm / "points3D.bin").stat().st_mtime_ns
        triangulate_map(views, feats, pairs, matches, sfm)
        assert (sfm / "points3D.bin").stat().st_mtime_ns == t

    def test_deterministic(self, tmp_path):
        _, views, feats, matches, pairs, _ = _synthetic_files(tmp_path)
        xyz = []
        for k in range(2):
            rec = hloc_io.read_sfm(triangulate_map(views, feats, pairs, matches, tmp_path / f"sfm{k}"))
            xyz.append(np.array(sorted(tuple(p.xyz) for p in rec.points3D.values())))
        np.testing.assert_array_equal(xyz[0], xyz[1])

    def test_unknown_image_in_pairs(self, tmp_path):
        _, views, feats, matches, pairs, _ = _synthetic_files(tmp_path)
        with pytest.raises(Exception, match="not one of the mapping views"):
            triangulate_map(views[:-1], feats, pairs, matches, tmp_path / "sfm")

    def test_point_matches_for_query(self, tmp_path):
        """A query seeing the synthetic points through two db images gets the right 3D points."""
        X, views, feats, matches, pairs, order = _synthetic_files(tmp_path, noise=0.0, outliers=0)
        sfm = triangulate_map(views, feats, pairs, matches, tmp_path / "sfm")
        q = View(name="seq-02/q.color.png", camera=CAM, cam_from_world=views[2].cam_from_world, color_path=None)
        uv, _ = project_points(X, q.cam_from_world, CAM)
        with h5py.File(feats, "a") as fd:
            hloc_io.write_features(fd, q.name, uv, np.zeros((len(X), 2)))
        qm = tmp_path / "qm.h5"
        with h5py.File(qm, "w") as fd:
            for db in (views[1].name, views[4].name):
                hloc_io.write_matches(fd, q.name, db, np.argsort(order[db]).astype(np.int32), np.ones(len(X)))
        pm = point_matches_for_query(q.name, [views[1].name, views[4].name], feats, qm, sfm)
        assert len(pm) > 0.9 * len(X)
        np.testing.assert_allclose(pm.p3d, X[pm.keypoint_idx], atol=0.01)
        np.testing.assert_allclose(pm.p2d, uv[pm.keypoint_idx], atol=1e-3)  # float32 storage
        assert len(np.unique(pm.keypoint_idx)) == len(pm)  # same 3D point via two images: kept once


# ----------------------------------------------------------------------------------------------
# real data
# ----------------------------------------------------------------------------------------------


def _localize(scene_mapping, scene_query, out, conf, retrieval_conf=None):
    from localization.estimate import estimate_pose_points
    from localization.points.retrieval import retrieval_recall

    t = time.time()
    built = points.build_point_map(scene_mapping, out, conf)
    t_map = time.time() - t
    q = points.match_queries(scene_query, [v.name for v in scene_mapping], built["features"], out, conf, retrieval_conf)
    model = hloc_io.ModelIndex(hloc_io.read_sfm(built["sfm"]))
    rows = []
    for v in scene_query:
        t0 = time.time()
        pm = point_matches_from_hloc(v.name, None, built["features"], q["matches"], q["pairs"], model=model)
        t1 = time.time()
        r = estimate_pose_points(pm.p2d, pm.p3d, v.camera)
        t2 = time.time()
        err = pose_errors(v.cam_from_world, r["cam_from_world"]) if r["success"] else (np.inf, np.inf)
        rows.append({"name": v.name, "dt": err[0], "dr": err[1], "n": len(pm), "inl": r["n_inliers"], "t2d3d": t1 - t0, "tpose": t2 - t1})
    recall = retrieval_recall(q["pairs"], {v.name: v.cam_from_world for v in scene_query}, {v.name: v.cam_from_world for v in scene_mapping})
    return built, q, rows, recall, t_map


def test_redkitchen_subset(redkitchen_root, tmp_path):
    """15 mapping + 5 queries at 1024 keypoints: most queries within 5 cm / 2 deg."""
    from lipmap.datasets import load_scene
    from localization.points.retrieval import RetrievalConfig

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    mapping = scene.mapping[:45:3]  # frames 0, 30, ..., 420
    queries = [scene.query[i] for i in (0, 9, 18, 27, 36)]  # frames 5, 95, 185, 275, 365
    built, _, rows, recall, _ = _localize(
        mapping, queries, tmp_path, points.confs["sift-n1024-fast"], RetrievalConfig(num_words=16, num_retrieved=5)
    )
    stats = points.model_stats(built["sfm"])
    assert stats["num_points3D"] > 500 and stats["mean_reproj_error"] < 2.0
    good = [r for r in rows if r["dt"] < 0.05 and r["dr"] < 2.0]
    assert len(good) >= 4, rows
    assert recall["recall@5"] >= 0.8


@pytest.mark.slow
def test_redkitchen_full(redkitchen_root, tmp_path):
    """All 50 queries, 4096 SIFT: every query within 5 cm / 5 deg (README: point-only does this)."""
    from lipmap.datasets import load_scene

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    t = time.time()
    built, q, rows, recall, t_map = _localize(scene.mapping, scene.query, tmp_path, points.confs["sift-n4096"])
    dt = np.array([r["dt"] for r in rows])
    dr = np.array([r["dr"] for r in rows])
    within = np.mean((dt < 0.05) & (dr < 5))
    stats = points.model_stats(built["sfm"])
    nq = len(rows)
    print(
        f"\nRedKitchen mini, sift-n4096: model {stats}; mapping {built['timings']} ({t_map:.1f} s)\n"
        f"queries: {q['timings']} for {nq} queries -> per query extract {q['timings']['extract'] / nq:.3f} s, "
        f"retrieval {q['timings']['retrieval'] / nq:.3f} s, match {q['timings']['match'] / nq:.3f} s, "
        f"2D-3D {np.mean([r['t2d3d'] for r in rows]):.4f} s, pose {np.mean([r['tpose'] for r in rows]):.4f} s\n"
        f"median {np.median(dt) * 100:.2f} cm / {np.median(dr):.3f} deg, within 5cm/5deg {within * 100:.0f}%, "
        f"max {dt.max() * 100:.2f} cm / {dr.max():.3f} deg; matches median {np.median([r['n'] for r in rows]):.0f}, "
        f"inliers median {np.median([r['inl'] for r in rows]):.0f}\n"
        f"retrieval recall (pose-nearest mapping frame in top-k): "
        f"{ {k: v for k, v in recall.items() if k != 'per_query'} }; total {time.time() - t:.1f} s"
    )
    assert within == 1.0
    assert np.median(dt) < 0.02 and np.median(dr) < 1.0
    assert recall["recall@10"] >= 0.95
