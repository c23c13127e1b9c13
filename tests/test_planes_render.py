"""Fast plane renderer (the default backend: Warp for float32 where installed, torch otherwise) vs. a brute-force
all-pairs oracle (values, and its hand-derived gradients against autograd), lambda schedule, edge cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lipmap.planes import Planes, lambda_schedule, rasterize_planes, render_planes
from lipmap.geometry import ray_plane_intersection
from lipmap.planes.primitives import (MAX_HITS, NEAR, R_MAX, R_MIN, SPLAT_MARGIN, TRANSMITTANCE_EPS, WEIGHT_EPS,
                                     quat_to_rotmat)
from lipmap.scene import Camera

INTR = (60.0, 60.0, 32.0, 24.0)
W, H = 64, 48


def render_all_pairs(center, quat, radii, cam_from_world, intrinsics, width, height, lam, max_hits=MAX_HITS, near=NEAR):
    """The paper's appendix A literally, as the oracle of the renderers: every pixel ray against every plane, the
    ``max_hits`` nearest intersections with splat weight > WEIGHT_EPS composited front to back, differentiated by
    autograd. O(pixels x planes): for test scenes only. Written apart from the renderer's own arithmetic (matrix
    products, :func:`lipmap.geometry.ray_plane_intersection`), so it checks it rather than repeats it.

    Returns depth (H, W), normal (H, W, 3) facing the camera, alpha (H, W).
    """
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    dev, dt = center.device, center.dtype
    T = cam_from_world.to(device=dev, dtype=dt)
    c = center @ T[:3, :3].T + T[:3, 3]  # (K, 3) camera frame
    Rc = T[:3, :3] @ quat_to_rotmat(quat)  # (K, 3, 3): columns X, Y, normal
    ax, ay, n = Rc[..., 0], Rc[..., 1], Rc[..., 2]
    n = torch.where(((n * c).sum(-1) > 0)[:, None], -n, n)  # facing the camera
    r = radii.clamp(R_MIN, R_MAX)
    u = (torch.arange(width, device=dev, dtype=dt) + 0.5 - cx) / fx
    v = (torch.arange(height, device=dev, dtype=dt) + 0.5 - cy) / fy
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    d = torch.stack([uu, vv, torch.ones_like(uu)], -1).reshape(-1, 1, 3)  # (P, 1, 3), z = 1: t is the depth
    t = ray_plane_intersection(torch.zeros_like(d), d, c[None], n[None])  # (P, K)
    finite = torch.isfinite(t)
    t = torch.where(finite, t, torch.zeros_like(t))  # keeps NaN out of the backward pass
    p = t[..., None] * d - c[None]
    px, py = (p * ax[None]).sum(-1), (p * ay[None]).sum(-1)

    def axis_weight(x, r_pos, r_neg):  # 1 inside [-r_neg, r_pos], 2 sigmoid(lam (r - |x|)) outside
        z = lam * (torch.where(x > 0, r_pos, r_neg) - x.abs())
        return torch.where(z >= 0, torch.ones_like(z), 2 * torch.sigmoid(z))

    w = torch.minimum(axis_weight(px, r[:, 0], r[:, 1]), axis_weight(py, r[:, 2], r[:, 3]))
    valid = finite & (t > near) & (w > WEIGHT_EPS)
    key = torch.where(valid, t, torch.full_like(t, float("inf"))).detach()
    k = min(max_hits, key.shape[1])
    key_sel, idx = torch.topk(key, k, dim=1, largest=False, sorted=True)
    ok = torch.isfinite(key_sel)
    w_sel = torch.where(ok, w.gather(1, idx), torch.zeros_like(key_sel))
    t_sel = torch.where(ok, t.gather(1, idx), torch.zeros_like(key_sel))
    n_sel = n[idx]
    P = d.shape[0]
    depth, alpha = torch.zeros(P, device=dev, dtype=dt), torch.zeros(P, device=dev, dtype=dt)
    normal, trans = torch.zeros(P, 3, device=dev, dtype=dt), torch.ones(P, device=dev, dtype=dt)
    for j in range(k):
        wj = torch.where(ok[:, j] & (trans.detach() >= TRANSMITTANCE_EPS), w_sel[:, j], torch.zeros_like(trans))
        contrib = trans * wj
        depth = depth + contrib * t_sel[:, j]
        normal = normal + contrib[:, None] * n_sel[:, j]
        alpha = alpha + contrib
        trans = trans * (1 - wj)
    return depth.reshape(height, width), normal.reshape(height, width, 3), alpha.reshape(height, width)


def random_planes(K, seed=1, dtype=torch.float64):
    """Planes 1-3 m in front of a camera at the origin, roughly facing it, random sizes (overlaps)."""
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(K, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.5, 2.0]) + torch.tensor([-1, -0.75, 1.0])
    nrm = torch.randn(K, 3, generator=g, dtype=torch.float64) * 0.4 + torch.tensor([0, 0, -1.0])
    p = Planes.from_normals(c.numpy(), nrm.numpy(), np.ones(K), dtype=dtype)
    radii = (torch.rand(K, 4, generator=g, dtype=torch.float64) * 0.25 + 0.02).to(dtype)
    return Planes(p.center, p.quat, radii)


def occlusion_scene(dtype=torch.float64):
    """A big back wall, a smaller plane in front of it (occlusion), two partially overlapping tilted
    planes, and a plane seen at a grazing angle; all straddle pixel edges so the fall-off matters."""
    centers = [[0, 0, 3.0], [0.2, 0.1, 2.0], [-0.5, -0.3, 1.5], [-0.35, -0.2, 1.6], [0.6, -0.4, 2.5]]
    normals = [[0, 0, -1.0], [0.1, 0.05, -1], [0.3, 0.2, -1], [-0.2, 0.3, -1], [1.0, 0.0, -0.3]]
    radii = [[2.0, 2.0, 2.0, 2.0], [0.3, 0.2, 0.25, 0.35], [0.2, 0.25, 0.15, 0.2], [0.22, 0.1, 0.2, 0.18], [0.3, 0.2, 0.3, 0.2]]
    p = Planes.from_normals(np.array(centers), np.array(normals), np.ones(5), dtype=dtype)
    return Planes(p.center, p.quat, torch.tensor(radii, dtype=dtype).clamp(max=0.5))


def _both(planes, lam, T=None, tile_size=8):
    T = torch.eye(4, dtype=planes.dtype) if T is None else T
    P1 = [t.clone().requires_grad_() for t in planes.tensors()]
    P2 = [t.clone().requires_grad_() for t in planes.tensors()]
    out = rasterize_planes(*P1, T, INTR, W, H, lam, tile_size=tile_size)
    ref = render_all_pairs(*P2, T, INTR, W, H, lam)
    return P1, P2, out, ref


class TestAgreementWithTwin:
    @pytest.mark.parametrize("lam", [36.8, 300.0, 1500.0])
    @pytest.mark.parametrize("scene", ["random", "occlusion"])
    def test_values_and_gradients_float64(self, lam, scene):
        planes = random_planes(60) if scene == "random" else occlusion_scene()
        P1, P2, out, (d2, n2, a2) = _both(planes, lam)
        assert out.n_pairs > 0
        # identical arithmetic on the selected pairs: agreement to float64 round-off
        torch.testing.assert_close(out.depth, d2, atol=1e-10, rtol=0)
        torch.testing.assert_close(out.normal, n2, atol=1e-10, rtol=0)
        torch.testing.assert_close(out.alpha, a2, atol=1e-10, rtol=0)
        g = torch.Generator().manual_seed(0)
        v_depth = torch.randn(d2.shape, generator=g, dtype=d2.dtype)
        v_normal = torch.randn(n2.shape, generator=g, dtype=d2.dtype)
        g1 = torch.autograd.grad((out.depth * v_depth).sum() + (out.normal * v_normal).sum(), P1)
        g2 = torch.autograd.grad((d2 * v_depth).sum() + (n2 * v_normal).sum(), P2)
        for a, b, name in zip(g1, g2, ("center", "quat", "radii")):
            assert b.abs().max() > 0, name
            torch.testing.assert_close(a, b, atol=1e-9 * max(1.0, float(b.abs().max())), rtol=1e-9, msg=name)

    def test_float32_gradients(self):
        planes = random_planes(60, dtype=torch.float32)
        P1, P2, out, (d2, n2, a2) = _both(planes, 300.0)
        torch.testing.assert_close(out.depth, d2, atol=1e-5, rtol=0)
        g = torch.Generator().manual_seed(0)
        v_depth, v_normal = torch.randn(d2.shape, generator=g), torch.randn(n2.shape, generator=g)
        g1 = torch.autograd.grad((out.depth * v_depth).sum() + (out.normal * v_normal).sum(), P1)
        g2 = torch.autograd.grad((d2 * v_depth).sum() + (n2 * v_normal).sum(), P2)
        for a, b in zip(g1, g2):
            # float32 sums in a different order: relative to the largest gradient entry
            assert float((a - b).abs().max()) <= 1e-5 * float(b.abs().max())

    @pytest.mark.parametrize("tile_size", [4, 8, 16, 32])
    def test_tile_size_does_not_change_result(self, tile_size):
        planes = random_planes(40, seed=3)
        _, _, out, (d2, n2, a2) = _both(planes, 300.0, tile_size=tile_size)
        torch.testing.assert_close(out.depth, d2, atol=1e-10, rtol=0)

    def test_chunked_selection(self, monkeypatch):
        """A tiny evaluation budget (many chunks per tile group) gives the same hits."""
        import lipmap.planes.select as S

        planes = random_planes(60)
        a = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), INTR, W, H, 36.8)
        monkeypatch.setattr(S, "_EVAL_BUDGET_CPU", 500)
        b = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), INTR, W, H, 36.8)
        assert torch.equal(a.hits, b.hits)
        torch.testing.assert_close(a.depth, b.depth, atol=0, rtol=0)

    def test_posed_camera(self):
        """Same scene seen through a non-trivial cam_from_world (planes moved by its inverse)."""
        from lipmap.poses import T_from_qt, invert_T

        planes = random_planes(30, seed=5)
        T = T_from_qt(np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3]), np.array([0.3, -0.1, 0.2]))
        Ti = torch.tensor(invert_T(T))
        from lipmap.planes.primitives import quat_to_rotmat
        from lipmap.planes.primitives import rotmat_to_quat

        c = planes.center @ Ti[:3, :3].T + Ti[:3, 3]
        q = torch.tensor(rotmat_to_quat((Ti[:3, :3] @ quat_to_rotmat(planes.quat)).numpy()))
        moved = Planes(c, q, planes.radii)
        out0 = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), INTR, W, H, 300.0)
        out1 = rasterize_planes(*moved.tensors(), torch.tensor(T), INTR, W, H, 300.0)
        torch.testing.assert_close(out0.depth, out1.depth, atol=1e-9, rtol=0)
        torch.testing.assert_close(out0.normal, out1.normal, atol=1e-9, rtol=0)


class TestKnownAnswers:
    def test_fronto_parallel_plane_depth_and_normal(self):
        cam = Camera(W, H, INTR)
        p = Planes.from_normals([[0, 0, 2.0]], [[0, 0, 1.0]], [0.5], dtype=torch.float64)  # normal away from camera
        out = render_planes(p, cam, np.eye(4), lam=1500.0)
        inside = out.alpha > 0.999
        # at 2 m, 0.5 m radius covers 15 px either side of the centre
        assert int(inside.sum()) == 30 * 30
        assert torch.allclose(out.depth[inside], torch.tensor(2.0, dtype=torch.float64))
        # the rendered normal faces the camera even though R z points away
        assert torch.allclose(out.normal[inside], torch.tensor([0, 0, -1.0], dtype=torch.float64))

    def test_splat_falloff(self):
        """Weight 2 sigmoid(lam (r - |p|)) outside: exactly WEIGHT_EPS at SPLAT_MARGIN / lam."""
        assert math.isclose(2 / (1 + math.exp(SPLAT_MARGIN)), WEIGHT_EPS, rel_tol=1e-9)

    def test_occlusion_front_plane_wins(self):
        planes = occlusion_scene()
        out = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), INTR, W, H, 1500.0)
        # the pixel at the front plane's centre: depth ~2 m (front), not 3 m (wall)
        u = int(60 * 0.2 / 2.0 + 32)
        v = int(60 * 0.1 / 2.0 + 24)
        assert abs(float(out.depth[v, u]) - 2.0) < 0.05
        assert int(out.hits[v, u, 0]) == 1
        assert float(out.alpha[v, u]) == pytest.approx(1.0)



def reference_rule_hits(center, quat, radii, intrinsics, width, height, lam, max_hits, near=NEAR):
    """The reference rasterizer's hit rule (``renderCUDA``) pixel by pixel, camera at the origin: planes walked in
    order of their centres' depth, a hit taken when it is valid and no nearer than the last one taken, until
    ``max_hits`` are taken or the transmittance falls below TRANSMITTANCE_EPS. Lists of plane indices per pixel."""
    fx, fy, cx, cy = intrinsics
    c = center.double()
    R = quat_to_rotmat(quat.double())
    n = R[..., 2]
    n = torch.where(((n * c).sum(-1) > 0)[:, None], -n, n)
    r = radii.double().clamp(R_MIN, R_MAX)
    order = sorted(range(len(c)), key=lambda k: (float(c[k, 2]), k))
    out = []
    for y in range(height):
        for x in range(width):
            d = torch.tensor([(x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1.0], dtype=torch.float64)
            taken, last, T = [], 0.0, 1.0
            for k in order:
                if len(taken) == max_hits or T < TRANSMITTANCE_EPS:
                    break
                t = float(ray_plane_intersection(torch.zeros(3, dtype=torch.float64), d, c[k], n[k]))
                if not (near < t < math.inf) or t < last:
                    continue
                p = t * d - c[k]
                px, py = float(p @ R[k, :, 0]), float(p @ R[k, :, 1])
                zx = lam * ((r[k, 0] if px > 0 else r[k, 1]) - abs(px))
                zy = lam * ((r[k, 2] if py > 0 else r[k, 3]) - abs(py))
                z = float(min(zx, zy))
                w = 1.0 if z >= 0 else 2.0 / (1.0 + math.exp(min(-z, 700.0)))
                if not w > WEIGHT_EPS:
                    continue
                taken.append(k)
                last, T = t, T * (1 - w)
            out.append(taken)
    return out


class TestReferenceHitRule:
    """``hit_rule="reference"``: the reference rasterizer's selection, torch backend."""

    def test_against_a_pixel_by_pixel_walk(self):
        g = torch.Generator().manual_seed(7)  # 25 planes at random slants, overlapping
        c = torch.rand(25, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.5, 2.0]) + torch.tensor([-1, -0.75, 1.0])
        nrm = torch.randn(25, 3, generator=g, dtype=torch.float64) + torch.tensor([0, 0, -1.0])
        p = Planes.from_normals(c.numpy(), nrm.numpy(), np.ones(25), dtype=torch.float64)
        planes = Planes(p.center, p.quat, torch.rand(25, 4, generator=g, dtype=torch.float64) * 0.4 + 0.1)
        w, h = 24, 18
        intr = (22.5, 22.5, 12.0, 9.0)
        out = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), intr, w, h, 300.0,
                               max_hits=5, backend="torch", hit_rule="reference")
        want = reference_rule_hits(*planes.tensors(), intr, w, h, 300.0, 5)
        got = [[int(k) for k in row if k >= 0] for row in out.hits.reshape(-1, 5)]
        assert got == want
        # the rule matters on this scene: some pixel's hits differ from the nearest ones
        near_hits = rasterize_planes(*planes.tensors(), torch.eye(4, dtype=torch.float64), intr, w, h, 300.0,
                                     max_hits=5, backend="torch")
        assert not torch.equal(near_hits.hits, out.hits)

    def test_a_nearer_hit_behind_a_taken_one_is_skipped(self):
        """A slanted plane whose centre is nearer than a fronto-parallel one it crosses: where the slanted plane's hit
        lies behind the other, the reference rule still renders it (the other's nearer hit comes later in its walk and
        is skipped); the nearest-hit rule renders the other."""
        a = math.radians(50)
        p = Planes.from_normals([[0, 0, 2.0], [0, 0, 2.1]], [[math.sin(a), 0, -math.cos(a)], [0, 0, -1.0]],
                                [0.5, 0.5], dtype=torch.float64)
        args = (*p.tensors(), torch.eye(4, dtype=torch.float64), INTR, W, H, 1500.0)
        ref = rasterize_planes(*args, backend="torch", hit_rule="reference")
        near_ = rasterize_planes(*args, backend="torch")
        y = H // 2
        u = (37 + 0.5 - INTR[2]) / INTR[0]  # the slanted plane z = 2 + x tan(a), met at t = 2 cos a / (cos a - u sin a)
        t_slanted = 2 * math.cos(a) / (math.cos(a) - u * math.sin(a))
        assert t_slanted > 2.1
        assert ref.hits[y, 37].tolist()[:2] == [0, -1] and float(ref.depth[y, 37]) == pytest.approx(t_slanted)
        assert near_.hits[y, 37].tolist()[:2] == [1, -1] and float(near_.depth[y, 37]) == pytest.approx(2.1)
        # where the slanted plane is in front, both rules agree
        assert int(ref.hits[y, 25, 0]) == 0 and torch.equal(ref.hits[y, 25], near_.hits[y, 25])
        torch.testing.assert_close(ref.depth[y, 25], near_.depth[y, 25])

    def test_gradients_flow(self):
        planes = random_planes(20, seed=2)
        P = [t.clone().requires_grad_() for t in planes.tensors()]
        out = rasterize_planes(*P, torch.eye(4, dtype=torch.float64), INTR, W, H, 300.0, backend="torch",
                               hit_rule="reference")
        g = torch.autograd.grad(out.depth.sum(), P)
        assert all(torch.isfinite(x).all() for x in g) and float(g[0].abs().max()) > 0

    def test_a_bad_rule_is_refused(self):
        from lipmap.errors import InputError
        from lipmap.planes.config import PlaneOptConfig

        planes = random_planes(5, dtype=torch.float32)
        with pytest.raises(InputError, match="hit rule"):
            rasterize_planes(*planes.tensors(), torch.eye(4), INTR, W, H, 300.0, hit_rule="first")
        with pytest.raises(InputError, match="hit rule"):
            PlaneOptConfig.preset("fast", hit_rule="first")


class TestLambdaSchedule:
    def test_values(self):
        assert lambda_schedule(0, 6000) == pytest.approx(5 * 20 / math.e)
        assert lambda_schedule(600, 6000) == pytest.approx(100.0)
        assert lambda_schedule(6000, 6000) == 1500.0
        assert lambda_schedule(0, 5) == pytest.approx(5 * 20 / math.e)  # max_iters // 10 == 0 guarded


class TestBadInput:
    def test_all_planes_culled(self):
        p = Planes.from_normals([[0, 0, -2.0], [0, 0, 1e-3]], [[0, 0, 1.0], [0, 0, 1.0]], [0.1, 0.1])
        P = [t.clone().requires_grad_() for t in p.tensors()]
        out = rasterize_planes(*P, torch.eye(4), INTR, W, H, 300.0)
        assert out.n_pairs == 0
        assert float(out.alpha.detach().abs().max()) == 0 and float(out.depth.detach().abs().max()) == 0
        (out.depth.sum() + out.normal.sum()).backward()  # a graph without pairs still back-propagates
        assert all(float(t.grad.abs().max()) == 0 for t in P)

    def test_no_planes(self):
        p = Planes.empty()
        out = rasterize_planes(*p.tensors(), torch.eye(4), INTR, W, H, 300.0)
        assert out.depth.shape == (H, W) and out.n_pairs == 0

    def test_nan_and_degenerate_planes_are_ignored(self):
        good = random_planes(20, dtype=torch.float32)
        c, q, r = (t.clone() for t in good.tensors())
        c[0] = float("nan")
        q[1] = 0.0
        r[2] = -0.3  # clamped to R_MIN in use: tiny, but finite
        r[3, 1] = float("nan")
        P = [t.requires_grad_() for t in (c, q, r)]
        out = rasterize_planes(*P, torch.eye(4), INTR, W, H, 300.0)
        assert torch.isfinite(out.depth).all() and torch.isfinite(out.normal).all()
        hit = out.hits[out.hits >= 0]
        assert not torch.isin(hit, torch.tensor([0, 3])).any()
        (out.depth.sum() + out.normal.sum()).backward()
        for t in P:
            assert torch.isfinite(t.grad).all()

    def test_bad_shapes(self):
        from lipmap.errors import InputError

        with pytest.raises(InputError):
            rasterize_planes(torch.zeros(3, 2), torch.zeros(3, 4), torch.zeros(3, 4), torch.eye(4), INTR, W, H, 10.0)
        with pytest.raises(InputError):
            rasterize_planes(torch.zeros(3, 3), torch.zeros(3, 4), torch.zeros(3, 4), torch.eye(3), INTR, W, H, 10.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_cuda_matches_cpu(backend):
    planes = random_planes(60, dtype=torch.float32)
    T = torch.eye(4)
    out_c = rasterize_planes(*planes.tensors(), T, INTR, W, H, 300.0, backend=backend)
    pc = planes.to("cuda")
    out_g = rasterize_planes(*pc.tensors(), T.cuda(), INTR, W, H, 300.0, backend=backend)
    torch.testing.assert_close(out_g.depth.cpu(), out_c.depth, atol=1e-4, rtol=0)
    # the GPU contracts multiply-adds (FMA) where the CPU rounds twice: a near-tie may order differently, rarely
    assert float((out_g.hits.cpu() == out_c.hits).float().mean()) > 0.999
