"""Known-answer tests for lipmap.geometry (hand-computed, non-symmetric values so a transpose fails)."""
import numpy as np
import pytest
import torch

from lipmap import geometry as G
from lipmap.errors import InputError
from lipmap.poses import make_T
from lipmap.scene import Camera

CAM = Camera(640, 480, (500.0, 400.0, 320.0, 240.0))  # fx != fy on purpose


def rot_z90():
    return np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


class TestProjectPoints:
    def test_translation(self):
        uv, z = G.project_points(np.array([[0.3, 0.4, 1.0]]), make_T(np.eye(3), [0.1, -0.2, 1.0]), CAM)
        # x_cam = (0.4, 0.2, 2.0)
        np.testing.assert_allclose(uv, [[420.0, 280.0]])
        np.testing.assert_allclose(z, [2.0])

    def test_rotation_not_transposed(self):
        # x_cam = R x = (-2, 1, 4); the transpose would give (2, -1, 4) -> u = 570
        uv, z = G.project_points(np.array([1.0, 2.0, 4.0]), make_T(rot_z90(), np.zeros(3)), CAM)
        np.testing.assert_allclose(uv, [70.0, 340.0])
        assert z == pytest.approx(4.0)

    def test_k_matrix_and_vector_inputs(self):
        p = np.array([[0.3, -0.1, 2.0], [1.0, 2.0, 5.0]])
        T = make_T(rot_z90(), [0.1, 0.2, 0.3])
        uv0, _ = G.project_points(p, T, CAM)
        uv1, _ = G.project_points(p, T, CAM.K)
        uv2, _ = G.project_points(p, T, np.array(CAM.params))
        np.testing.assert_allclose(uv0, uv1)
        np.testing.assert_allclose(uv0, uv2)

    def test_torch_matches_numpy_and_has_grad(self):
        p = np.array([[0.3, -0.1, 2.0], [1.0, 2.0, 5.0]])
        T = make_T(rot_z90(), [0.1, 0.2, 0.3])
        uv_np, z_np = G.project_points(p, T, CAM)
        pt = torch.tensor(p, requires_grad=True)
        uv_t, z_t = G.project_points(pt, T, CAM)
        np.testing.assert_allclose(uv_t.detach().numpy(), uv_np)
        uv_t.sum().backward()
        assert torch.isfinite(pt.grad).all()

    def test_bad_shape(self):
        with pytest.raises(InputError):
            G.project_points(np.zeros((3, 2)), np.eye(4), CAM)


class TestUnprojectPoints:
    def test_known_answer(self):
        # (420, 280) at z = 2: x = (420 - 320) / 500 * 2 = 0.4, y = (280 - 240) / 400 * 2 = 0.2 (fx != fy)
        np.testing.assert_allclose(G.unproject_points(np.array([[420.0, 280.0]]), 2.0, CAM), [[0.4, 0.2, 2.0]])

    def test_inverts_project_cam_points(self):
        p = np.array([[0.3, -0.1, 2.0], [1.0, 2.0, 5.0]])
        uv, z = G.project_cam_points(p, CAM)
        np.testing.assert_allclose(G.unproject_points(uv, z, CAM), p)

    def test_bad_shape(self):
        with pytest.raises(InputError):
            G.unproject_points(np.zeros((3, 3)), 1.0, CAM)


class TestProjectSegments:
    def test_clip_partly_behind(self):
        # camera frame: (0,0,2) -> (1,0,-2); near = 1 crosses at t = 0.25 -> (0.25, 0, 1)
        seg = np.array([[[0.0, 0.0, 2.0], [1.0, 0.0, -2.0]]])
        s2, valid = G.project_segments(seg, np.eye(4), CAM, near=1.0)
        assert valid.tolist() == [True]
        np.testing.assert_allclose(s2[0], [[320.0, 240.0], [445.0, 240.0]])

    def test_clip_second_endpoint_in_front(self):
        seg = np.array([[[1.0, 0.0, -2.0], [0.0, 0.0, 2.0]]])
        s2, valid = G.project_segments(seg, np.eye(4), CAM, near=1.0)
        np.testing.assert_allclose(s2[0], [[445.0, 240.0], [320.0, 240.0]])

    def test_wholly_behind_is_invalid(self):
        seg = np.array([[[0.0, 0.0, -1.0], [1.0, 0.0, -2.0]], [[0.0, 0.0, 1.0], [0.2, 0.0, 2.0]]])
        s2, valid = G.project_segments(seg, np.eye(4), CAM)
        assert valid.tolist() == [False, True]
        assert np.isnan(s2[0]).all()
        np.testing.assert_allclose(s2[1], [[320.0, 240.0], [370.0, 240.0]])

    def test_torch(self):
        seg = torch.tensor([[[0.0, 0.0, 2.0], [1.0, 0.0, -2.0]]], dtype=torch.float64)
        s2, valid = G.project_segments(seg, np.eye(4), CAM, near=1.0)
        np.testing.assert_allclose(s2[0].numpy(), [[320.0, 240.0], [445.0, 240.0]])

    def test_clip_to_image(self):
        s = np.array([[[-10.0, 10.0], [30.0, 50.0]], [[-5.0, -5.0], [-1.0, -1.0]], [[5.0, 5.0], [6.0, 7.0]]])
        out, valid = G.clip_segments_to_image(s, 100, 40)
        assert valid.tolist() == [True, False, True]
        np.testing.assert_allclose(out[0], [[0.0, 20.0], [20.0, 40.0]])
        np.testing.assert_allclose(out[2], s[2])

    def test_segments_in_image_agrees_with_clipping(self):
        rng = np.random.default_rng(0)
        s = rng.uniform(-60, 160, (20000, 2, 2))
        s[:2000, 1] = s[:2000, 0]  # points
        s[2000:3000, :, 0] = rng.choice([0.0, 100.0, -1.0, 101.0], (1000, 1))  # vertical, on or beside the borders
        s[3000:4000, :, 1] = rng.choice([0.0, 40.0, -1.0, 41.0], (1000, 1))  # horizontal
        s[4000:4100] = np.nan
        _, valid = G.clip_segments_to_image(np.nan_to_num(s, nan=-1e9), 100, 40)
        inside = G.segments_in_image(s, 100, 40)
        assert 0.2 < inside.mean() < 0.8 and not inside[4000:4100].any()
        np.testing.assert_array_equal(inside, valid)


class TestSegmentMeasures:
    def test_angle(self):
        a = np.array([0.0, 0.0, 10.0, 0.0])
        c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
        b = np.array([1.0, 1.0, 1.0 + 3 * c, 1.0 + 3 * s])
        assert G.angle_distance(a, b) == pytest.approx(np.pi / 6)
        # undirected: reversing b or taking the 150 deg line gives the same
        assert G.angle_distance(a, b[[2, 3, 0, 1]]) == pytest.approx(np.pi / 6)
        assert G.angle_distance(a, [0, 0, -c, s]) == pytest.approx(np.pi / 6)
        assert G.angle_distance(a, [0, 0, 0, 5]) == pytest.approx(np.pi / 2)
        assert G.angle_distance(a, [3, 3, 7, 3]) == 0.0

    def test_perpendicular_distance_not_symmetric(self):
        a = np.array([[0.0, 1.0], [4.0, 3.0]])
        b = np.array([[0.0, 0.0], [10.0, 0.0]])
        np.testing.assert_allclose(G.perpendicular_distance(a, b, reduce=None), [1.0, 3.0])
        assert G.perpendicular_distance(a, b) == pytest.approx(3.0)
        assert G.perpendicular_distance(a, b, "mean") == pytest.approx(2.0)
        # swapped roles: (0,0) and (10,0) to the line through (0,1),(4,3)
        np.testing.assert_allclose(G.perpendicular_distance(b, a, None), [4 / np.sqrt(20), 24 / np.sqrt(20)])

    def test_overlap_ratio_not_symmetric(self):
        a = np.array([2.0, 5.0, 8.0, 1.0])
        b = np.array([0.0, 0.0, 4.0, 0.0])
        assert G.overlap_ratio(a, b) == pytest.approx(0.5)  # x in [2, 8] within [0, 4] -> 2 / 4
        assert G.overlap_ratio(b, a) == pytest.approx(24 / 52)
        assert G.overlap_ratio([10, 0, 12, 0], b) == 0.0
        assert G.overlap_ratio([-1, 3, 9, 3], b) == 1.0

    def test_point_segment_distance(self):
        seg = np.array([[0.0, 0.0], [4.0, 0.0]])
        np.testing.assert_allclose(G.point_segment_distance(np.array([[5.0, 3.0], [2.0, -3.0]]), seg), [np.sqrt(10), 3.0])
        seg3 = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
        assert G.point_segment_distance(np.array([1.0, 1.0, 1.0]), seg3) == pytest.approx(np.sqrt(2))
        assert G.point_segment_distance(np.array([0.0, 3.0, -4.0]), seg3) == pytest.approx(5.0)

    def test_pairwise_matches_elementwise(self):
        rng = np.random.default_rng(0)
        a = rng.uniform(0, 100, (3, 4))
        b = rng.uniform(0, 100, (5, 2, 2))
        for pair, elem in (
            (G.pairwise_angle_distance, G.angle_distance),
            (G.pairwise_perpendicular_distance, G.perpendicular_distance),
            (G.pairwise_overlap_ratio, G.overlap_ratio),
        ):
            M = pair(a, b)
            assert M.shape == (3, 5)
            for i in range(3):
                for j in range(5):
                    assert M[i, j] == pytest.approx(elem(a[i], b[j]))

    def test_match_segments_2d(self):
        det = np.array([[0.0, 0.0, 100.0, 0.0], [0.0, 50.0, 0.0, 150.0]])
        proj = np.array(
            [
                [10.0, 1.0, 60.0, 1.0],  # parallel, 1 px away, overlap 0.5 -> match det 0
                [10.0, 3.0, 60.0, 3.0],  # 3 px away
                [10.0, 1.0, 60.0, 3.0],  # angle 0.04 rad
                [95.0, 1.0, 140.0, 1.0],  # overlap 0.05
                [0.5, 60.0, 0.5, 200.0],  # det 1: overlap 0.9
            ]
        )
        m = G.match_segments_2d(proj, det)
        assert m.tolist() == [[True, False], [False, False], [False, False], [False, False], [False, True]]
        assert G.match_segments_2d(proj, np.zeros((0, 4))).shape == (5, 0)

    def test_align_endpoints(self):
        a = np.array([[[5.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [5.0, 0.0]]])
        b = np.array([[0.0, 0.1], [5.0, 0.1]])
        out = G.align_endpoints(a, b)
        np.testing.assert_allclose(out[0], [[0, 0], [5, 0]])
        np.testing.assert_allclose(out[1], [[0, 0], [5, 0]])


class TestTorchMeasures:
    def test_values_match_numpy(self):
        rng = np.random.default_rng(1)
        a = rng.uniform(0, 50, (6, 2, 2))
        b = rng.uniform(0, 50, (6, 2, 2))
        for f in (G.angle_distance, G.perpendicular_distance, G.overlap_ratio, G.endpoint_distance):
            np.testing.assert_allclose(f(torch.tensor(a), torch.tensor(b)).numpy(), f(a, b), rtol=1e-10)
        p = rng.uniform(0, 50, (6, 2))
        np.testing.assert_allclose(
            G.point_segment_distance(torch.tensor(p), torch.tensor(b)).numpy(), G.point_segment_distance(p, b)
        )

    def test_gradcheck(self):
        rng = np.random.default_rng(2)
        a = torch.tensor(rng.uniform(0, 50, (4, 2, 2)), requires_grad=True)
        b = torch.tensor(rng.uniform(0, 50, (4, 2, 2)))
        assert torch.autograd.gradcheck(lambda x: G.angle_distance(x, b), (a,))
        assert torch.autograd.gradcheck(lambda x: G.perpendicular_distance(x, b, "mean"), (a,))
        assert torch.autograd.gradcheck(lambda x: G.endpoint_distance(x, b), (a,))

    def test_align_and_project_segments_torch(self):
        a = torch.tensor([[[5.0, 0.0], [0.0, 0.0]]], dtype=torch.float64)
        b = torch.tensor([[0.0, 0.1], [5.0, 0.1]], dtype=torch.float64)
        np.testing.assert_allclose(G.align_endpoints(a, b)[0].numpy(), [[0, 0], [5, 0]])
        seg = torch.tensor([[[0.1, 0.2, 2.0], [0.5, -0.3, 3.0]]], dtype=torch.float64, requires_grad=True)
        T = make_T(rot_z90(), [0.1, 0.2, 0.3])
        assert torch.autograd.gradcheck(lambda s: G.project_segments(s, T, CAM)[0], (seg,))

    def test_zero_angle_gradient_finite(self):
        a = torch.tensor([[0.0, 0.0], [10.0, 0.0]], requires_grad=True)
        b = torch.tensor([[0.0, 1.0], [10.0, 1.0]])
        G.angle_distance(a, b).backward()
        assert torch.isfinite(a.grad).all()


class Test3D:
    def test_point_line_distance_3d(self):
        seg = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 2.0]])  # the line x = y = 1 (infinite)
        np.testing.assert_allclose(G.point_line_distance(np.array([[4.0, 5.0, 10.0], [1.0, 0.0, -3.0]]), seg), [5.0, 1.0])

    def test_sample_segments(self):
        s = np.array([[[0.0, 0.0, 0.0], [2.0, 4.0, 6.0]]])
        np.testing.assert_allclose(G.sample_segments(s, 3)[0], [[0, 0, 0], [1, 2, 3], [2, 4, 6]])
        assert G.sample_segments(np.zeros((4, 5, 2, 3)), 7).shape == (4, 5, 7, 3)

    def test_segment_to_segment_distance(self):
        a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
        b = np.array([[0.0, 0.1, 0.0], [1.0, 0.1, 0.0]])
        assert G.segment_to_segment_distance(a, b) == pytest.approx(0.1)
        # b shorter: a's samples beyond b's end are farther; directed distance not symmetric
        c = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
        d_ac = G.segment_to_segment_distance(a, c, n_samples=3, reduce="max")
        assert d_ac == pytest.approx(0.5)
        assert G.segment_to_segment_distance(c, a, n_samples=3, reduce="max") == pytest.approx(0.0)
        assert G.segment_to_segment_distance(c, a, n_samples=3, reduce="max", symmetric=True) == pytest.approx(0.5)
        pair = G.segment_to_segment_distance(np.stack([a, c])[:, None], np.stack([a, b, c])[None])
        assert pair.shape == (2, 3)

    def test_fit_segment(self):
        t = np.linspace(-1, 2, 20)
        pts = np.array([1.0, 2.0, 3.0]) + t[:, None] * np.array([0.0, 0.6, 0.8])
        seg = G.fit_segment(pts[::-1])
        ends = sorted([tuple(np.round(seg[0], 9)), tuple(np.round(seg[1], 9))])
        np.testing.assert_allclose(ends, sorted([(1.0, 1.4, 2.2), (1.0, 3.2, 4.6)]), atol=1e-9)
        _, d, rms = G.fit_line(pts)
        assert abs(abs(d @ [0, 0.6, 0.8]) - 1) < 1e-12 and rms < 1e-12

    def test_closest_point_params(self):
        s, t = G.closest_point_params([0, 0, 0], [1, 0, 0], [2, -1, 1], [0, 1, 0])
        assert (s, t) == (pytest.approx(2.0), pytest.approx(1.0))

    def test_ray_plane(self):
        t = G.ray_plane_intersection(np.zeros(3), np.array([0.0, 0.0, 2.0]), [0, 0, 3.0], [0, 0, 1.0])
        assert t == pytest.approx(1.5)
        t = G.ray_plane_intersection(np.zeros((2, 3)), np.array([[1.0, 0, 0], [0, 0, -1.0]]), [0, 0, 3.0], [0, 0, 1.0])
        assert np.isinf(t[0]) and t[1] == pytest.approx(-3.0)
        tt = G.ray_plane_intersection(torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), [0, 0, 3.0], [0, 0, 1.0])
        assert float(tt) == pytest.approx(1.5)
