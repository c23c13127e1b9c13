"""The per-query API with what hloc and LIMAP users bring: any COLMAP camera, their own line matches, a starting pose,
a match budget, and settings checked before any work. Public names only."""
from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from lipmap import InputError
from lipmap.linemap import LineMap
from lipmap.poses import make_T, pose_errors
from localization import (LineRescueConfig, LocalizationConfig, Localizer, PointLinePoseConfig,
                          estimate_pose_point_line)
from localization.cameras import as_query_camera
from localization.hypotheses import HypothesisConfig

W, H, F, CX, CY = 640, 480, 525.0, 320.0, 240.0
PINHOLE = {"model": "PINHOLE", "width": W, "height": H, "params": [F, F, CX, CY]}
K_RADIAL = 0.08  # about 9 px at the image corners


def _scene(seed=0, n_pts=80, n_lines=60):
    """A camera, 3D points and map lines in front of it, and their exact pinhole observations."""
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_euler("xyz", rng.uniform(-10, 10, 3), degrees=True).as_matrix(), rng.uniform(-0.3, 0.3, 3))
    Tinv = np.linalg.inv(T)

    def world(Xc):
        return Xc @ Tinv[:3, :3].T + Tinv[:3, 3]

    X = world(np.c_[rng.uniform(-1.5, 1.5, (n_pts, 2)), rng.uniform(2, 5, n_pts)])
    a = np.c_[rng.uniform(-1.2, 1.2, (n_lines, 2)), rng.uniform(2, 4, n_lines)]
    ends = np.stack([world(a), world(a + rng.normal(0, 0.4, (n_lines, 3)))], 1)
    return T, X, ends


def _pinhole(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * F + [CX, CY]


def _observe(T, X, ends, rng, noise=0.3):
    """Pinhole keypoints and segments (shortened by a tenth at each end, as a detector cuts them), with noise."""
    p2d = _pinhole(T, X) + rng.normal(0, noise, (len(X), 2))
    l2 = np.concatenate([_pinhole(T, ends[:, 0]), _pinhole(T, ends[:, 1])], 1)
    d = l2[:, 2:] - l2[:, :2]
    return p2d, np.concatenate([l2[:, :2] + 0.1 * d, l2[:, 2:] - 0.1 * d], 1) + rng.normal(0, noise, l2.shape)


def _distort(radial, pix):
    """Pinhole pixels (N, 2) as the same rays' pixels in ``radial``."""
    rays = np.c_[(pix[:, 0] - CX) / F, (pix[:, 1] - CY) / F, np.ones(len(pix))]
    return np.asarray(radial.img_from_cam(rays, check_cheirality=False))


def _cm(T, U):
    return 100 * pose_errors(T, U)[0]


def _localizer(ends, **conf) -> Localizer:
    return Localizer(LineMap(ends), LocalizationConfig(**conf))


class TestCameraModels:
    def test_simple_radial_gives_the_pinhole_poses_on_the_same_undistorted_data(self):
        T, X, ends = _scene(0)
        p2d, l2 = _observe(T, X, ends, np.random.default_rng(1))
        radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[F, CX, CY, K_RADIAL])
        p2d_d = _distort(radial, p2d)
        l2_d = _distort(radial, l2.reshape(-1, 2)).reshape(-1, 4)
        assert np.abs(p2d_d - p2d).max() > 3  # the distortion matters at these pixels
        loc = _localizer(ends)
        ref = loc.localize(PINHOLE, p2d, X, lines2d=l2)
        for cam in (radial, {"model": "SIMPLE_RADIAL", "width": W, "height": H, "params": [F, CX, CY, K_RADIAL]}):
            res = loc.localize(cam, p2d_d, X, lines2d=l2_d)
            for a, b in ((res.point, ref.point), (res.point_line, ref.point_line)):
                assert a.success and b.success
                assert _cm(a.cam_from_world, b.cam_from_world) < 1e-3  # the same pose, up to the undistortion's rounding
            assert res.used_lines and len(res.line_matches) == len(ref.line_matches)
            np.testing.assert_allclose(res.lines2d, l2, atol=1e-6)  # the segments in the pinhole camera
        assert _cm(ref.point_line.cam_from_world, T) < 1.0
        # the distorted pixels taken for a pinhole camera's: a worse pose
        naive = loc.localize(PINHOLE, p2d_d, X, lines2d=l2_d)
        assert _cm(naive.point.cam_from_world, T) > 3 * _cm(ref.point.cam_from_world, T)

    def test_pinhole_models_and_bad_cameras(self):
        simple = as_query_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=W, height=H, params=[F, CX, CY]))
        assert not simple.distorted and simple.pinhole.params == (F, F, CX, CY)
        opencv = as_query_camera({"model": "OPENCV", "width": W, "height": H, "params": [F, 530, CX, CY, 0.1, 0, 0, 0]})
        assert opencv.distorted and opencv.pinhole.params == (F, 530.0, CX, CY)
        with pytest.raises(InputError, match="takes f, cx, cy, k"):
            as_query_camera({"model": "SIMPLE_RADIAL", "width": W, "height": H, "params": [F, CX, CY]})
        with pytest.raises(InputError, match="model, width, height"):
            as_query_camera({"params": [F]})
        with pytest.raises(InputError, match="cannot use"):
            as_query_camera("pinhole")

    def test_an_image_is_undistorted_before_its_lines_are_detected(self):
        """A grid drawn straight in the pinhole camera, seen through the radial camera, is straight again."""
        import cv2

        img = np.zeros((H, W), np.uint8)
        for x in range(40, W, 80):
            cv2.line(img, (x, 0), (x, H - 1), 255, 3)
        radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[F, CX, CY, K_RADIAL])
        # the radial camera's image: each of its pixels looks up the pinhole pixel of the same ray
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        xn = np.asarray(radial.cam_from_img(np.c_[u.ravel(), v.ravel()]))
        mx = (F * xn[:, 0] + CX - 0.5).reshape(H, W).astype(np.float32)
        my = (F * xn[:, 1] + CY - 0.5).reshape(H, W).astype(np.float32)
        seen = cv2.remap(img, mx, my, cv2.INTER_LINEAR)
        back = as_query_camera(radial).undistort_image(seen)

        def centres(im, x0):  # per row (10-470), the intensity centroid of the line drawn at x0 + 0.5 (COLMAP pixels)
            win = im[10:470, x0 - 8:x0 + 20].astype(float)
            return (win * np.arange(x0 - 8, x0 + 20)).sum(1) / win.sum(1) + 0.5

        x = 520  # far from the centre, where the distortion bends the line
        assert np.ptp(centres(seen, x)) > 2
        assert np.ptp(centres(back, x)) < 0.3 and abs(np.median(centres(back, x)) - (x + 0.5)) < 0.2


class TestStartsAndMatches:
    def test_an_initial_pose_starts_the_lines_where_points_give_none(self):
        T, X, ends = _scene(2)
        rng = np.random.default_rng(3)
        p2d, l2 = _observe(T, X, ends, rng)
        near = make_T(Rotation.from_euler("y", 2, degrees=True).as_matrix() @ T[:3, :3], T[:3, 3] + [0.05, 0, 0])
        loc = _localizer(ends)
        for n in (0, 2):  # no pose from points alone
            bare = loc.localize(PINHOLE, p2d[:n], X[:n], lines2d=l2)
            assert not bare.point.success and not bare.point_line.success
            res = loc.localize(PINHOLE, p2d[:n], X[:n], lines2d=l2, initial=near)
            assert res.point_line.success and res.used_lines and res.rescued
            assert _cm(res.point_line.cam_from_world, T) < 1.0
            assert res.point_line.inliers.shape == (n,)
        with pytest.raises(InputError, match="initial"):
            loc.localize(PINHOLE, p2d, X, lines2d=l2, initial=np.eye(3))

    def test_own_line_matches_skip_the_line_query(self):
        T, X, ends = _scene(4)
        rng = np.random.default_rng(5)
        p2d, l2 = _observe(T, X, ends, rng)
        bad = rng.permutation(len(ends))[:10]  # ten wrong matches among sixty
        l3 = ends.copy()
        l3[bad] = ends[np.roll(bad, 1)]
        loc = _localizer(ends)
        res = loc.localize(PINHOLE, p2d[:6], X[:6], line_matches=(l2, l3))
        assert res.used_lines and not res.rescued and len(res.line_matches) == len(ends)
        assert _cm(res.point_line.cam_from_world, T) < 1.0
        assert not res.line_matches.inliers[bad].any() and res.line_matches.inliers.sum() >= 45
        assert (res.line_matches.line_idx == -1).all()
        # LIMAP's shape: the 3D lines once, and an index per 2D segment
        ids = np.arange(len(ends))[::-1]
        res2 = loc.localize(PINHOLE, p2d[:6], X[:6], line_matches=(l2[::-1], ends, ids))
        np.testing.assert_array_equal(res2.line_matches.line_idx, ids)
        assert _cm(res2.point_line.cam_from_world, T) < 1.0
        with pytest.raises(InputError, match="line_ids"):
            loc.localize(PINHOLE, p2d, X, line_matches=(l2, ends, np.arange(len(ends)) + 1))

    def test_estimate_pose_point_line_in_limaps_shape(self):
        T, X, ends = _scene(6)
        p2d, l2 = _observe(T, X, ends, np.random.default_rng(7))
        ids = np.arange(len(ends))
        for n in (0, 1, 2, 20):  # PoseLib's minimal solvers mix points and lines: a few of each suffice
            est, stats = estimate_pose_point_line(ends, ids, l2, X[:n], p2d[:n], PINHOLE)
            assert est.success and _cm(est.cam_from_world, T) < 1.0, n
            assert est.inliers.shape == (n,) and est.line_inliers.shape == (len(ends),)
            assert stats["n_line_inliers"] == est.line_inliers.sum() > 50
        radial = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[F, CX, CY, K_RADIAL])
        est_d, _ = estimate_pose_point_line(ends, None, _distort(radial, l2.reshape(-1, 2)).reshape(-1, 4), X[:2],
                                            _distort(radial, p2d[:2]), radial, conf=PointLinePoseConfig(max_line_error=2))
        assert est_d.success and _cm(est_d.cam_from_world, T) < 1.0


    def test_a_query_its_points_hold_skips_ransac_in_the_narrowing_rounds(self, monkeypatch):
        import localization.query as Q

        T, X, ends = _scene(10, n_pts=300)
        p2d, l2 = _observe(T, X, ends, np.random.default_rng(11))
        calls, ransac = [], Q.pnpl_pose
        monkeypatch.setattr(Q, "pnpl_pose", lambda *a, **k: calls.append(1) or ransac(*a, **k))
        strong = _localizer(ends, strong_inliers=100).localize(PINHOLE, p2d, X, lines2d=l2)
        assert not calls and strong.used_lines and len(strong.line_matches) > 40
        weak = _localizer(ends, strong_inliers=301).localize(PINHOLE, p2d, X, lines2d=l2)  # above its inliers
        assert len(calls) == 3 and weak.used_lines  # one RANSAC per narrowing round
        assert _cm(strong.point_line.cam_from_world, T) < 0.5
        assert _cm(strong.point_line.cam_from_world, weak.point_line.cam_from_world) < 0.1


class TestConfig:
    def test_the_match_budget_is_honoured_and_seeded_by_the_query_name(self):
        T, X, ends = _scene(8)
        p2d, l2 = _observe(T, X, ends, np.random.default_rng(9))
        loc = _localizer(ends, max_point_matches=10)
        a = loc.localize(PINHOLE, p2d, X, lines2d=l2, name="q1")
        b = loc.localize(PINHOLE, p2d, X, lines2d=l2, name="q1")
        c = loc.localize(PINHOLE, p2d, X, lines2d=l2, name="q2")
        assert len(a.point_matches) == 10 and a.point.inliers.shape == (10,) and a.record["point"]["n_matches"] == 10
        np.testing.assert_array_equal(a.point_matches.p3d, b.point_matches.p3d)
        assert not np.array_equal(a.point_matches.p3d, c.point_matches.p3d)

    @pytest.mark.parametrize("conf, field", [
        (LocalizationConfig(num_retrieved=0), "num_retrieved"),
        (LocalizationConfig(line_rescue=LineRescueConfig(prior_views=2)), "prior_views"),
        (LocalizationConfig(seed=-1), "seed"),
        (LocalizationConfig(max_point_matches=-3), "max_point_matches"),
        (LocalizationConfig(line_rescue=LineRescueConfig(max_point_error=0)), "max_point_error"),
        (LocalizationConfig(max_line_step=(0.3,)), "max_line_step"),
        (LocalizationConfig(strong_gates=()), "strong_gates"),
        (LocalizationConfig(line_rescue=LineRescueConfig(gates=())), "line_rescue.gates"),
        (LocalizationConfig(line_rescue=LineRescueConfig(solver="refine", refine_gates=())), "line_rescue.refine_gates"),
        (LocalizationConfig(point_line_pose=PointLinePoseConfig(refine_step_tol=0)), "refine_step_tol"),
        (LocalizationConfig(strong_inliers=-1), "strong_inliers"),
        (LocalizationConfig(line_rescue=LineRescueConfig(threads=0)), "line_rescue.threads"),
        (LocalizationConfig(line_rescue=LineRescueConfig(hypotheses=HypothesisConfig(angle_bins=65))), "angle_bins"),
    ])
    def test_a_field_a_localizer_cannot_honour_is_refused(self, conf, field):
        _, _, ends = _scene(0)
        with pytest.raises(InputError, match=field):
            Localizer(LineMap(ends), conf)

    def test_a_failed_query_has_numbers_for_timings_and_no_line_matches(self):
        T, X, ends = _scene(10)
        p2d, l2 = _observe(T, X, ends, np.random.default_rng(11))
        loc = _localizer(ends)
        for res in (loc.localize(PINHOLE, p2d[:3], X[:3], lines2d=l2[:0]),  # no pose at all
                    loc.localize(PINHOLE, p2d, X, lines2d=l2[:, [1, 0, 3, 2]] + [200, 0, 200, 0])):  # no line fits
            assert all(isinstance(v, float) for v in res.timings.values()), res.timings
            assert len(res.line_matches) == 0 and not res.used_lines
        assert res.point.success and np.allclose(res.point_line.cam_from_world, res.point.cam_from_world)
