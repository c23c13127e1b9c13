"""Initial pose from 2D-3D points (PoseLib): known answers, pixel-convention pin, bad queries, seeding, and accuracy
against pycolmap's ``estimate_and_refine_absolute_pose`` (hloc's localize_sfm) on the same matches."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import benchmark_module
from lipmap.geometry import project_points
from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera
from localization.estimate import PointPoseConfig, adaptive_loss_scale, estimate_pose_points, subsample_matches

PINNED = [59, 567, 593, 650, 806]  # numpy default_rng (PCG64); changes only if numpy changes it
CAM = Camera(640, 480, (525.0, 525.0, 320.0, 240.0))
HLOC_FIXTURE = Path(__file__).parent / "data" / "hloc_7scenes"
BENCH = benchmark_module("point_pose_vs_pycolmap.py")
OLD = BENCH.OLD  # the former default: PoseLib's binding Cauchy scale, 0.5 x 12 px


def synthetic(n=300, noise=0.0, outlier_frac=0.0, seed=0):
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), rng.normal(0, 0.5, 3))
    # points in front of the camera, 1-4 m away, spread over the image
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(1, 4, n)
    pc = np.stack([(uv[:, 0] - 320) / 525 * z, (uv[:, 1] - 240) / 525 * z, z], 1)
    Tinv = np.linalg.inv(T)
    X = pc @ Tinv[:3, :3].T + Tinv[:3, 3]
    p2d, depth = project_points(X, T, CAM)  # COLMAP convention, same as Camera's cx/cy
    assert np.all(depth > 0)
    p2d = p2d + rng.normal(0, noise, p2d.shape)
    n_out = int(outlier_frac * n)
    out_idx = rng.choice(n, n_out, replace=False)
    p2d[out_idx] = rng.uniform([0, 0], [640, 480], (n_out, 2))
    is_out = np.zeros(n, bool)
    is_out[out_idx] = True
    return p2d, X, T, is_out


def sift_like(seed, noise, n=300, near=0.2, far=0.3):
    """Matches as NN-mutual SIFT gives them: ``noise`` px Gaussian inliers, a fraction ``near`` of mismatches
    2-10 px off (inside a 12 px RANSAC threshold) and ``far`` gross outliers. Returns p2d, p3d, cam_from_world."""
    p2d, X, T, _ = synthetic(n=n, noise=noise, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    k = rng.permutation(n)
    a, b = int(near * n), int((near + far) * n)
    ang, r = rng.uniform(0, 2 * np.pi, a), rng.uniform(2, 10, a)
    p2d[k[:a]] += np.stack([np.cos(ang), np.sin(ang)], 1) * r[:, None]
    p2d[k[a:b]] = rng.uniform([0, 0], [640, 480], (b - a, 2))
    return p2d, X, T


def pycolmap_hloc(p2d, p3d, camera, seed=0):
    """pycolmap.estimate_and_refine_absolute_pose with hloc's localize_sfm options (RANSAC 12 px), seeded."""
    return BENCH.pycolmap_hloc(p2d, p3d, camera, seed)[0]


class TestEstimatePosePoints:
    def test_known_answer_noise_outliers(self):
        p2d, X, T, is_out = synthetic(n=400, noise=0.5, outlier_frac=0.3)
        r = estimate_pose_points(p2d, X, CAM)
        assert r["success"]
        dt, dr = pose_errors(T, r["cam_from_world"])
        assert dt < 0.01 and dr < 0.1, (dt, dr)
        # the inlier mask finds the outliers (a random outlier can land within 12 px: allow a few)
        assert (r["inliers"] & is_out).sum() <= 0.05 * is_out.sum()
        assert r["inliers"][~is_out].mean() > 0.99
        assert r["n_inliers"] == r["inliers"].sum()

    def test_pose_is_cam_from_world(self):
        p2d, X, T, _ = synthetic(n=50)
        r = estimate_pose_points(p2d, X, CAM)
        np.testing.assert_allclose(r["cam_from_world"], T, atol=1e-6)

    def test_pixel_convention(self):
        """Convention pin: PoseLib's PINHOLE is u = fx x/z + cx, so 2D points must be in the
        intrinsics' (COLMAP) convention; hloc-origin points (0.5 px off) bias the pose."""
        p2d, X, T, _ = synthetic(n=200)
        good = pose_errors(T, estimate_pose_points(p2d, X, CAM)["cam_from_world"])
        shifted = pose_errors(T, estimate_pose_points(p2d - 0.5, X, CAM)["cam_from_world"])
        assert good[0] < 1e-6 and good[1] < 1e-5
        assert shifted[1] > 0.02  # ~0.5 px / 525 px = 0.055 deg of rotation
        assert shifted[0] > 1000 * good[0]

    def test_camera_dict_equals_camera(self):
        p2d, X, _, _ = synthetic(n=100, noise=1.0, outlier_frac=0.2, seed=4)
        a = estimate_pose_points(p2d, X, CAM)
        b = estimate_pose_points(p2d, X, CAM.to_dict())
        np.testing.assert_array_equal(a["cam_from_world"], b["cam_from_world"])

    def test_seeded_deterministic(self):
        p2d, X, _, _ = synthetic(n=200, noise=2.0, outlier_frac=0.5, seed=2)
        conf = PointPoseConfig(seed=7)
        a = estimate_pose_points(p2d, X, CAM, conf)
        b = estimate_pose_points(p2d, X, CAM, conf)
        np.testing.assert_array_equal(a["cam_from_world"], b["cam_from_world"])
        np.testing.assert_array_equal(a["inliers"], b["inliers"])

    @pytest.mark.parametrize("n", [0, 1, 3])
    def test_too_few_matches(self, n):
        p2d, X, _, _ = synthetic(n=10)
        r = estimate_pose_points(p2d[:n], X[:n], CAM)
        assert r["success"] is False and r["cam_from_world"] is None
        assert r["inliers"].shape == (n,) and r["n_inliers"] == 0

    def test_nan_and_garbage_do_not_raise(self):
        p2d, X, _, _ = synthetic(n=10)
        p2d[:8] = np.nan
        assert estimate_pose_points(p2d, X, CAM)["success"] is False
        rng = np.random.default_rng(0)
        r = estimate_pose_points(rng.uniform(0, 640, (30, 2)), rng.normal(size=(30, 3)), CAM, PointPoseConfig(min_inliers=12))
        assert r["inliers"].shape == (30,)  # garbage: whatever PoseLib says, no exception

    def test_threshold_is_used(self):
        p2d, X, T, _ = synthetic(n=200, noise=3.0, seed=5)
        tight = estimate_pose_points(p2d, X, CAM, PointPoseConfig(max_reproj_error=1.0))
        loose = estimate_pose_points(p2d, X, CAM, PointPoseConfig(max_reproj_error=12.0))
        assert tight["n_inliers"] < 0.6 * loose["n_inliers"]


class TestAsAccurateAsPycolmap:
    """The point-only pose is at least as accurate as the call hloc's localize_sfm makes, on the same matches.

    The former default (Cauchy scale 6 px, PoseLib's) let the 2-12 px mismatches pull the pose; a fixed 1 px (COLMAP's)
    down-weights real inliers when the noise is above 1 px. Margins are on medians over scenes or queries, far above
    what another float ordering can change.
    """

    @pytest.mark.parametrize("noise, vs_colmap, old_worse", [(0.3, 1.05, 2.0), (1.0, 1.05, 1.1), (2.0, 0.95, None)])
    def test_synthetic_sift_like(self, noise, vs_colmap, old_worse):
        """Geometric mean over 40 scenes of the per-scene error ratios (measured at 0.3, 1, 2 px: new / pycolmap
        1.0, 0.995, 0.85 - a fixed 1 px gives 1.0 at 2 px; old / new 3.1, 1.25, 0.96)."""
        to_colmap, old_to_new = [], []
        for seed in range(40):
            p2d, X, T = sift_like(seed, noise)
            new = pose_errors(T, estimate_pose_points(p2d, X, CAM)["cam_from_world"])[0]
            old = pose_errors(T, estimate_pose_points(p2d, X, CAM, OLD)["cam_from_world"])[0]
            colmap = pose_errors(T, pycolmap_hloc(p2d, X, CAM))[0]
            to_colmap.append(np.log(new / colmap))
            old_to_new.append(np.log(old / new))
        assert np.exp(np.mean(to_colmap)) <= vs_colmap, np.exp(np.mean(to_colmap))
        if old_worse is not None:  # where the former default lost
            assert np.exp(np.mean(old_to_new)) >= old_worse, np.exp(np.mean(old_to_new))

    def test_hloc_fixture(self):
        """On files hloc wrote (SIFT + NN-mutual, tests/data/hloc_7scenes), read as the benchmark reads them: as
        accurate as pycolmap's call (3 seeds) and hloc's own results_sparse.txt; the former default was 4x worse
        (medians over the 4 queries, measured 0.44 / 0.46 / 0.44 / 2.1 cm)."""
        from localization.hloc_io import read_results

        out = HLOC_FIXTURE / "hloc_outputs" / "7scenes" / "room-s0"
        pairs = HLOC_FIXTURE / "datasets" / "7scenes" / "7scenes_densevlad_retrieval_top_10" / "room-s0_top10.txt"
        inputs = BENCH.find_inputs(out, pairs)
        assert (inputs["sfm"].name, inputs["features"].name) == ("sfm_sift+NN-mutual", "feats-sift.h5")
        assert inputs["matches"].name == "feats-sift_matches-NN-mutual_room-s0_top10.h5"
        matches = BENCH.load_matches(inputs)
        cameras = BENCH.read_cameras(out, None)
        gt = BENCH.read_ground_truth(HLOC_FIXTURE / "datasets" / "7scenes" / "room-s0", list(matches))
        hloc = read_results(out / "results_sparse.txt")
        assert sorted(matches) == sorted(hloc) and len(matches) == 4
        err = {"new": [], "old": [], "colmap": [], "hloc": []}
        for q, pm in matches.items():
            cam = cameras[q]
            assert cam.params == (262.5, 262.5, 160.0, 120.0)
            err["new"].append(pose_errors(gt[q], estimate_pose_points(pm.p2d, pm.p3d, cam)["cam_from_world"])[0])
            err["old"].append(pose_errors(gt[q], estimate_pose_points(pm.p2d, pm.p3d, cam, OLD)["cam_from_world"])[0])
            err["colmap"] += [pose_errors(gt[q], pycolmap_hloc(pm.p2d, pm.p3d, cam, s))[0] for s in range(3)]
            err["hloc"].append(pose_errors(gt[q], hloc[q])[0])
        med = {k: float(np.median(v)) for k, v in err.items()}
        assert med["new"] <= 1.05 * med["colmap"] and med["new"] <= 1.05 * med["hloc"], med
        assert med["old"] >= 2 * med["new"], med


class TestAdaptiveLossScale:
    def test_follows_the_noise(self):
        """Median reprojection error of Gaussian inliers = sigma sqrt(2 ln 2) (Rayleigh median)."""
        import poselib

        p2d, X, T, _ = synthetic(n=2000, noise=1.0, seed=3)
        pose = poselib.CameraPose()
        pose.R, pose.t = T[:3, :3], T[:3, 3]
        scale = adaptive_loss_scale(pose, p2d, X, CAM.to_dict(), PointPoseConfig())
        assert scale == pytest.approx(np.sqrt(2 * np.log(2)), rel=0.1)
        exact = adaptive_loss_scale(pose, synthetic(n=50, seed=3)[0], X[:50], CAM.to_dict(), PointPoseConfig())
        assert exact == PointPoseConfig().min_loss_scale
        far = adaptive_loss_scale(pose, p2d + 30.0, X, CAM.to_dict(), PointPoseConfig())
        assert far == 0.5 * PointPoseConfig().max_reproj_error

    def test_reported_and_fixed_scale_skips_it(self):
        p2d, X, _, _ = synthetic(n=200, noise=1.0, outlier_frac=0.2, seed=6)
        adaptive = estimate_pose_points(p2d, X, CAM)
        assert 0.5 < adaptive["info"]["loss_scale"] < 3.0
        assert "loss_scale" not in estimate_pose_points(p2d, X, CAM, OLD)["info"]


class TestSubsampleMatches:
    def test_deterministic_per_query(self):
        a = subsample_matches(500, 30, seed=0, query_name="seq-02/frame-000005.color.png")
        b = subsample_matches(500, 30, seed=0, query_name="seq-02/frame-000005.color.png")
        np.testing.assert_array_equal(a, b)
        assert len(a) == 30 and len(np.unique(a)) == 30 and np.all(np.diff(a) > 0) and a.max() < 500

    def test_depends_on_seed_and_name(self):
        base = subsample_matches(500, 30, 0, "q1")
        assert not np.array_equal(base, subsample_matches(500, 30, 1, "q1"))
        assert not np.array_equal(base, subsample_matches(500, 30, 0, "q2"))

    def test_all_when_enough(self):
        np.testing.assert_array_equal(subsample_matches(20, 30, 0, "q"), np.arange(20))
        np.testing.assert_array_equal(subsample_matches(20, None, 0, "q"), np.arange(20))
        assert len(subsample_matches(20, 0, 0, "q")) == 0

    def test_pinned_values(self):
        """Stable across runs and Python processes (no salted hash): pin a value."""
        idx = subsample_matches(1000, 5, 0, "seq-02/frame-000005.color.png")
        assert idx.tolist() == PINNED
