"""Bounded per-view caches: LRU eviction, lazy depth maps, and the plane targets read through them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lipmap.frames import LRU, ViewCache, depth_maps


def test_lru_evicts_the_least_recently_used_and_reloads_it():
    calls = []
    lru = LRU(lambda k: calls.append(k) or k * 10, capacity=2)
    assert [lru(1), lru(2), lru(1), lru(3)] == [10, 20, 10, 30]  # 3 evicts 2, not 1 (used last)
    assert len(lru) == 2
    assert lru(1) == 10 and calls == [1, 2, 3]
    assert lru(2) == 20 and calls == [1, 2, 3, 2]
    assert lru.stats() == {"capacity": 2, "hits": 2, "misses": 4}
    with pytest.raises(ValueError):
        LRU(lambda k: k, capacity=0)


def test_view_cache_is_a_mapping_of_the_loadable_views():
    class V:
        def __init__(self, name, ok):
            self.name, self.ok = name, ok

    views = [V("a", True), V("b", False), V("c", True)]
    cache = ViewCache(views, lambda v: v.name.upper(), capacity=1, has=lambda v: v.ok)
    assert list(cache) == ["a", "c"] and len(cache) == 2
    assert "b" not in cache and cache.get("b") is None
    assert cache["c"] == "C" and cache["a"] == "A" and cache["c"] == "C"
    assert cache.stats()["misses"] == 3  # capacity 1: every switch reloads
    with pytest.raises(KeyError):
        cache["b"]


def test_depth_maps_equal_the_views_depth(synthetic_root):
    from lipmap.datasets import load_scene

    scene = load_scene("synthetic", synthetic_root, "room-s3")
    views = scene.mapping[:5]
    dm = depth_maps(views, capacity=2)
    assert set(dm) == {v.name for v in views}
    for v in views[::-1] + views:
        np.testing.assert_array_equal(dm[v.name], v.load_depth())


def test_plane_optimization_is_the_same_whatever_the_target_cache_size(synthetic_root):
    """Targets rebuilt after eviction are the same tensors, so a tiny cache changes nothing but time."""
    from lipmap.datasets import load_scene
    from lipmap.planes.init import PlaneInitConfig, init_planes
    from lipmap.planes.config import PlaneOptConfig
    from lipmap.planes.targets import TargetStore
    from lipmap.planes.train import optimize_planes

    torch.set_num_threads(1)
    scene = load_scene("synthetic", synthetic_root, "room-s3")
    views = scene.mapping[:6]
    init = init_planes(views, PlaneInitConfig(n_planes=200, voxel_size=0.05))
    out = []
    for cap in (256, 2):
        conf = PlaneOptConfig.preset("fast", iterations=15, cache_views=cap, progress=False)
        store = TargetStore(views, conf)
        planes, hist = optimize_planes(store, init, conf)
        out.append(planes)
        assert store.stats()["misses"] == 6 if cap == 256 else store.stats()["misses"] > 6
    for a, b in zip(out[0].tensors(), out[1].tensors()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_a_fixed_iteration_budget_is_sampled_over_the_views_in_epochs(synthetic_root):
    from lipmap.datasets import load_scene
    from lipmap.planes.init import PlaneInitConfig, init_planes
    from lipmap.planes.config import PlaneOptConfig
    from lipmap.planes.targets import TargetStore
    from lipmap.planes.train import Schedule, optimize_planes

    assert (Schedule.of(PlaneOptConfig(iterations=100), 30).max_iters, Schedule.of(PlaneOptConfig(iterations=100), 30).n_epochs) == (100, 4)
    assert (Schedule.of(PlaneOptConfig(epochs=3), 30).max_iters, Schedule.of(PlaneOptConfig(epochs=3), 30).n_epochs) == (90, 3)
    torch.set_num_threads(1)
    scene = load_scene("synthetic", synthetic_root, "room-s3")
    views = scene.mapping[:4]
    init = init_planes(views, PlaneInitConfig(n_planes=200, voxel_size=0.05))
    seen = []

    def count(view, planes, it, render, target):
        seen.append((it, view.name))
        return None

    conf = PlaneOptConfig.preset("fast", iterations=10, progress=False)
    planes_b, hist = optimize_planes(TargetStore(views, conf), init, conf, extra_loss=count)
    assert [it for it, _ in seen] == list(range(10)) and len(hist["loss"]) == 3  # 4 + 4 + 2
    assert {n for _, n in seen[:4]} == {v.name for v in views}  # each epoch visits every view once
    # a budget of whole epochs is the epoch-based run
    planes_e, _ = optimize_planes(views, init, PlaneOptConfig.preset("fast", epochs=2, progress=False))
    planes_b, _ = optimize_planes(views, init, PlaneOptConfig.preset("fast", iterations=8, progress=False))
    for a, b in zip(planes_e.tensors(), planes_b.tensors()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_the_fast_budget_is_the_same_whatever_the_views_and_epochs_can_cap_it():
    from lipmap.planes.config import PlaneOptConfig
    from lipmap.planes.train import Schedule

    fast = PlaneOptConfig.preset("fast-lines")
    assert Schedule.of(fast, 30).max_iters == 3600 and Schedule.of(fast, 30).n_epochs == 120
    assert Schedule.of(fast, 50).max_iters == 3600
    capped = PlaneOptConfig.preset("fast-lines", epochs=72)
    assert Schedule.of(capped, 30).max_iters == 72 * 30 and Schedule.of(capped, 1500).max_iters == 3600
    assert Schedule.of(fast, 1500).max_iters == 3600 and Schedule.of(fast, 1500).n_epochs == 3
    from lipmap.errors import InputError

    with pytest.raises(InputError):
        Schedule.of(PlaneOptConfig(epochs=0, iterations=0), 10)


def test_prune_and_split_rounds_last_restructure_every_iterations_and_at_least_an_epoch(synthetic_root):
    """``restructure_every``: rounds of N iterations where a scene has fewer views (few views used to split twice
    as often under an iteration budget), never shorter than an epoch: over a subset of the views the split test
    averages a plane's gradient over fewer views and splits on noise. "Seen by no view" only after a round that
    trained on every view."""
    from lipmap.datasets import load_scene
    from lipmap.planes.init import PlaneInitConfig, init_planes
    from lipmap.planes.config import PlaneOptConfig
    from lipmap.planes.targets import TargetStore
    from lipmap.planes.train import optimize_planes

    torch.set_num_threads(1)
    scene = load_scene("synthetic", synthetic_root, "room-s3")
    views = scene.mapping[:4]
    init = init_planes(views, PlaneInitConfig(n_planes=200, voxel_size=0.05))
    base = dict(iterations=12, split=True, split_grad_threshold=1e-6, progress=False)  # every seen plane splits
    store = TargetStore(views, PlaneOptConfig.preset("fast", **base))
    by_epoch, h_e = optimize_planes(store, init, PlaneOptConfig.preset("fast", **base))
    assert len(h_e["loss"]) == 3
    # rounds asked shorter than an epoch (1, 2 iterations over 4 views) are an epoch long: the same run to the bit
    for every in (1, 2, 4):
        planes, h = optimize_planes(store, init, PlaneOptConfig.preset("fast", restructure_every=every, **base))
        assert h["planes"] == h_e["planes"] and h["split"] == h_e["split"]
        for a, b in zip(by_epoch.tensors(), planes.tensors()):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    # rounds of 6 iterations over 4 views: 2 rounds, and the one before the last step splits
    _, h_6 = optimize_planes(store, init, PlaneOptConfig.preset("fast", restructure_every=6, **base))
    assert len(h_6["loss"]) == 2 and h_6["split"][0] > 0 and h_6["split"][-1] == 0
    # "seen by no view" needs a round that trained on every view: 6 iterations over 4 views are a round of 4
    # (prunes the unseen) and a last one of 2, cut short by the budget (prunes none as unseen)
    no_split = {**base, "split": False}
    _, h_cut = optimize_planes(store, init, PlaneOptConfig.preset("fast", **{**no_split, "iterations": 6}))
    assert len(h_cut["unseen"]) == 2 and h_cut["unseen"][0] > 0 and h_cut["unseen"][1] == 0
    # rounds of 5 over 4 views straddle epochs: with seed 0 (one permutation per epoch) the third round,
    # iterations 10-14, never trains on one of the views, whose planes it must not prune as unseen
    rng = np.random.default_rng(0)
    order = np.concatenate([rng.permutation(4) for _ in range(4)])
    assert [len(set(order[k : k + 5].tolist())) for k in (0, 5, 10)] == [4, 4, 3]
    _, h_5 = optimize_planes(store, init, PlaneOptConfig.preset("fast", restructure_every=5, **{**no_split, "iterations": 15}))
    assert len(h_5["unseen"]) == 3 and h_5["unseen"][0] > 0 and h_5["unseen"][2] == 0
