"""Plane optimization: convergence on a known wall, prune/split index map, extra_loss hook, bad input,
and the end-to-end quality figures (synthetic; real RedKitchen when ../shared/data is there)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from lipmap.planes import Planes, rasterize_planes
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.structure import PlaneIndexMap, prune_and_split
from lipmap.planes.targets import ViewTarget
from lipmap.planes.train import optimize_planes
from lipmap.poses import make_T
from lipmap.scene import Camera

CAM = Camera(64, 48, (56.0, 56.0, 32.0, 24.0))


def wall_targets(n=4, z=2.0, valid=True):
    """Views of the wall z = const (world) from small sideways offsets."""
    out = []
    for i in range(n):
        T = make_T(np.eye(3), np.array([0.1 * (i - n / 2), 0.05 * (i % 2), 0.0]))
        depth = torch.full((48, 64), z if valid else 0.0)
        normal = torch.zeros(48, 64, 3)
        normal[..., 2] = -1 if valid else 0
        out.append(ViewTarget(None, CAM, torch.tensor(T, dtype=torch.float32), depth, normal, depth > 0, normal.norm(dim=-1) > 0.5))
    return out


def noisy_wall_planes(K=12, seed=0, facing_camera=False):
    """Planes near the wall z = 2, their normals +z (away from the cameras of :func:`wall_targets`), or towards them."""
    rng = np.random.default_rng(seed)
    c = np.stack([rng.uniform(-0.8, 0.8, K), rng.uniform(-0.6, 0.6, K), 2.0 + rng.normal(0, 0.08, K)], 1)
    n = np.array([0, 0, 1.0]) + rng.normal(0, 0.15, (K, 3))
    return Planes.from_normals(c, -n if facing_camera else n, np.full(K, 0.12))


def small_conf(**kw):
    return PlaneOptConfig.preset("fast", progress=False, downscale=1, **kw)


class TestOptimize:
    def test_converges_on_a_wall(self):
        planes, hist = optimize_planes(wall_targets(), noisy_wall_planes(), small_conf(epochs=60))
        assert hist["depth"][-1] < 0.2 * hist["depth"][0]
        assert abs(float(planes.normal[:, 2].abs().min())) > 0.99
        out = rasterize_planes(*planes.tensors(), torch.eye(4), CAM.params, 64, 48, 1500.0)
        covered = out.alpha > 0.99
        assert float(covered.float().mean()) > 0.9
        assert float((out.depth[covered] - 2.0).abs().median()) < 0.01

    def test_seeded(self):
        a, _ = optimize_planes(wall_targets(), noisy_wall_planes(), small_conf(epochs=2, seed=3))
        b, _ = optimize_planes(wall_targets(), noisy_wall_planes(), small_conf(epochs=2, seed=3))
        for x, y in zip(a.tensors(), b.tensors()):
            assert torch.equal(x, y)

    def test_extra_loss_hook_and_restructure_callback(self):
        calls, maps = [], []

        def extra(view, planes, iteration, render, target):
            calls.append((iteration, render is not None and tuple(target.depth.shape) == tuple(render.alpha.shape),
                          planes.center.requires_grad))
            return 0.0 * planes.center.sum()

        optimize_planes(wall_targets(2), noisy_wall_planes(), small_conf(epochs=2), extra_loss=extra, on_restructure=maps.append)
        assert [c[0] for c in calls] == [0, 1, 2, 3]
        assert all(c[1] and c[2] for c in calls)
        assert len(maps) == 3 and all(isinstance(m, PlaneIndexMap) for m in maps)

        def extra3(view, planes, iteration, render):  # one fixed signature: a callback without ``target`` is refused
            return planes.radii.sum() * 0

        with pytest.raises(TypeError):
            optimize_planes(wall_targets(1), noisy_wall_planes(), small_conf(epochs=1), extra_loss=extra3)


class TestPruneSplit:
    def test_index_map(self):
        p = Planes.from_normals(np.random.rand(5, 3), np.tile([0, 0, 1.0], (5, 1)), np.full(5, 0.1))
        p.radii[1] = 1e-3  # pruned: radius <= 1.25e-3
        seen = torch.tensor([True, True, True, False, True])  # 3 pruned: unseen
        g = torch.tensor([[0.0, 0.0], [0, 0], [0.5, 0.0], [0, 0], [0.5, 0.5]])
        new, m = prune_and_split(p, seen=seen, radii_grad=g, split_threshold=0.2)
        assert m.n_pruned == 2 and m.n_unseen == 1 and m.n_split == 2
        assert len(new) == 1 + 2 + 4
        assert sorted(m.parent.tolist()) == [0, 2, 2, 4, 4, 4, 4]
        o2n = m.old_to_new()
        assert (o2n[1] == -1).all() and (o2n[3] == -1).all()
        assert (o2n[4] >= 0).all() and (o2n[2] >= 0).sum() == 2
        for old in range(5):
            for j in o2n[old][o2n[old] >= 0].tolist():
                assert int(m.parent[j]) == old
        # children tile their parent: total area kept
        area = lambda q: float((q.radii[:, 0] + q.radii[:, 1]) @ (q.radii[:, 2] + q.radii[:, 3]))
        assert area(new[m.parent == 4]) == pytest.approx(area(p[4:5]), rel=1e-5)

    def test_max_planes(self):
        p = Planes.from_normals(np.random.rand(4, 3), np.tile([0, 0, 1.0], (4, 1)), np.full(4, 0.1))
        g = torch.tensor([[1.0, 1.0], [2.0, 0], [0.5, 0.5], [0.3, 0]])
        new, m = prune_and_split(p, radii_grad=g, split_threshold=0.2, max_planes=8)
        assert len(new) <= 8 and m.n_split >= 1
        assert 1 in m.parent.tolist() and m.parent.tolist().count(1) == 2  # highest gradient went first


class TestBadInput:
    def test_views_without_depth_are_skipped(self):
        targets = wall_targets(2) + wall_targets(2, valid=False)
        planes, hist = optimize_planes(targets, noisy_wall_planes(), small_conf(epochs=2))
        assert sum(hist["skipped"]) == 4  # 2 empty views x 2 epochs
        for t in planes.tensors():
            assert torch.isfinite(t).all()

    def test_degenerate_planes_dropped_and_no_nan(self):
        p = noisy_wall_planes()
        c, q, r = (t.clone() for t in p.tensors())
        c[0] = float("nan")
        r[1] = 0.0
        r[2, 0] = -0.1
        q[3] = 0.0
        maps = []
        planes, _ = optimize_planes(wall_targets(), Planes(c, q, r), small_conf(epochs=2), on_restructure=maps.append)
        assert maps[0].n_pruned == 4
        for t in planes.tensors():
            assert torch.isfinite(t).all()
        assert float(planes.radii.min()) > 1.25e-3

    def test_all_planes_culled(self):
        behind = Planes.from_normals([[0, 0, -2.0]], [[0, 0, 1.0]], [0.2])
        planes, hist = optimize_planes(wall_targets(2), behind, small_conf(epochs=1, prune_unseen=False))
        assert hist["skipped"] == [2]
        torch.testing.assert_close(planes.center, behind.center)

    def test_non_finite_loss_skips_the_step_on_the_device(self):
        """A non-finite loss leaves parameters, Adam's moments and its step count as they were, without the host
        reading the loss: the fused Adam skips the step (its found_inf)."""
        from lipmap.planes.optimizer import _apply_step, _make_optimizer

        params = [t.clone().requires_grad_() for t in noisy_wall_planes().tensors()]
        opt = _make_optimizer(params, small_conf(epochs=1))
        assert opt.defaults["fused"]
        loss = lambda: sum((p ** 2).sum() for p in params)  # noqa: E731
        _apply_step(opt, params, loss(), taken=torch.tensor(True))
        before = [p.detach().clone() for p in params] + [opt.state[p][k].clone() for p in params
                                                         for k in ("exp_avg", "exp_avg_sq", "step")]
        bad = loss() * float("inf")
        _apply_step(opt, params, bad, taken=torch.isfinite(bad.detach()))
        after = [p.detach() for p in params] + [opt.state[p][k] for p in params for k in ("exp_avg", "exp_avg_sq", "step")]
        # exact, but for the quaternion's renormalisation after every step (1 ulp)
        torch.testing.assert_close(after.pop(1), before.pop(1), rtol=0, atol=1e-6)
        assert all(torch.equal(a, b) for a, b in zip(before, after))
        _apply_step(opt, params, loss(), taken=torch.tensor(True))
        assert not torch.equal(params[0].detach(), before[0]) and float(opt.state[params[0]]["step"]) == 2
        assert float(opt.state[params[1]]["step"]) == 2

    def test_no_targets(self):
        from lipmap.errors import InputError

        with pytest.raises(InputError):
            optimize_planes([], noisy_wall_planes(), small_conf(epochs=1))

    def test_unknown_preset(self):
        from lipmap.errors import InputError

        with pytest.raises(InputError):
            PlaneOptConfig.preset("nope")


@pytest.mark.slow
def test_fit_planes_synthetic_query_depth(synthetic_root, tmp_path):
    """fast preset on room-s3: rendered depth on the query views (not used for fitting) < 1 cm median."""
    from lipmap.datasets import load_scene
    from lipmap.planes import load_planes
    from lipmap.planes.check import check_png, rendered_depth_errors
    from lipmap.planes.train import fit_planes

    scene = load_scene("synthetic", synthetic_root, "room-s3")
    path = fit_planes(scene, tmp_path, PlaneOptConfig.preset("fast", progress=False))
    assert (tmp_path / "planes.ply").exists()
    planes = load_planes(path)
    err = rendered_depth_errors(planes, scene.query)
    assert err["views"] == len(scene.query)
    assert err["median"] < 0.01, err
    assert err["coverage"] > 0.95, err
    png = check_png(planes, scene.mapping[:2], tmp_path / "check.png")
    assert png.stat().st_size > 1000
    # resume: a second call skips the work
    mtime = path.stat().st_mtime
    assert fit_planes(scene, tmp_path, PlaneOptConfig.preset("fast", progress=False)) == path
    assert path.stat().st_mtime == mtime


@pytest.mark.slow
@pytest.mark.shared
def test_fit_planes_redkitchen_query_depth(redkitchen_root, tmp_path):
    """Real Kinect data: rendered depth agrees with the registered sensor depth on the query views."""
    from lipmap.datasets import load_scene
    from lipmap.planes import load_planes
    from lipmap.planes.check import rendered_depth_errors
    from lipmap.planes.train import fit_planes

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    path = fit_planes(scene, tmp_path, PlaneOptConfig.preset("fast", progress=False))
    err = rendered_depth_errors(load_planes(path), scene.query[::5])
    assert err["median"] < 0.03, err


def test_paper_preset_runs():
    """The reference settings (soft lambda start, splitting at 0.2, back faces culled) run, train the planes that
    face the cameras and keep finite parameters; planes that face away are never rendered."""
    conf = PlaneOptConfig.preset("paper", epochs=2, progress=False)
    assert conf.lr_center == 1e-3 and conf.split and conf.lambda_min == 0 and conf.cull_back_faces
    planes, hist = optimize_planes(wall_targets(2), noisy_wall_planes(facing_camera=True), conf)
    assert hist["lambda"][0] < 300 and hist["skipped"] == [0, 0]
    for t in planes.tensors():
        assert torch.isfinite(t).all()
    _, hist = optimize_planes(wall_targets(2), noisy_wall_planes(), conf)
    assert hist["skipped"] == [2, 2]  # each round's 2 iterations: nothing rendered, no gradient


def test_fine_iterations_train_the_last_steps_at_full_resolution(synthetic_root):
    """Coarse to fine: with ``downscale=2`` and ``fine_iterations=2`` the last 2 of 6 steps render (and hand the
    line term) the views' own resolution, the first 4 half of it; prepared targets cannot do it, and it is a
    no-op where the working resolution already is the views' own."""
    from lipmap.datasets import load_scene
    from lipmap.errors import InputError
    from lipmap.planes.targets import prepare_targets

    views = load_scene("synthetic", synthetic_root, "room-s3").mapping[:3]
    W, H = views[0].camera.width, views[0].camera.height
    seen = []

    def extra(view, planes, iteration, render, target):
        assert tuple(target.depth.shape) == tuple(render.alpha.shape)
        seen.append((iteration, tuple(render.alpha.shape), target.camera.width))
        return None

    conf = PlaneOptConfig.preset("fast", progress=False, downscale=2, epochs=0, iterations=6, fine_iterations=2)
    optimize_planes(list(views), noisy_wall_planes(), conf, extra_loss=extra)
    assert [s[0] for s in seen] == list(range(6))
    assert [s[1] for s in seen] == [(H // 2, W // 2)] * 4 + [(H, W)] * 2
    assert [s[2] for s in seen] == [W // 2] * 4 + [W] * 2

    # the coarse targets are dropped when the fine steps begin (they are not used again); without fine steps they stay
    from lipmap.planes.targets import TargetStore

    store = TargetStore(views, conf)
    optimize_planes(store, noisy_wall_planes(), conf)
    assert len(store._lru) == 0 and store.stats()["misses"] >= 1
    store = TargetStore(views, replace(conf, fine_iterations=0))
    optimize_planes(store, noisy_wall_planes(), replace(conf, fine_iterations=0))
    assert len(store._lru) == len(views)

    with pytest.raises(InputError, match="fine_iterations"):
        optimize_planes(prepare_targets(_frames(views), conf), noisy_wall_planes(), conf)
    seen.clear()
    optimize_planes(list(views), noisy_wall_planes(), PlaneOptConfig.preset(
        "fast", progress=False, downscale=1, epochs=0, iterations=3, fine_iterations=2), extra_loss=extra)
    assert [s[1] for s in seen] == [(H, W)] * 3

    # from a quarter, the fine steps train at half the working downscale (bounded cost), or at the one asked for
    for fine_ds, fine_shape in ((0, (H // 2, W // 2)), (1, (H, W))):
        seen.clear()
        optimize_planes(list(views), noisy_wall_planes(), PlaneOptConfig.preset(
            "fast", progress=False, downscale=4, epochs=0, iterations=4, fine_iterations=2, fine_downscale=fine_ds),
            extra_loss=extra)
        assert [s[1] for s in seen] == [(H // 4, W // 4)] * 2 + [fine_shape] * 2


def _frames(views):
    from lipmap.planes.init import LazyDepthFrames

    frames = LazyDepthFrames(list(views))
    return [frames[i] for i in range(len(frames))]
