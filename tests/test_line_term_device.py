"""The line term on the training device: its pieces against their NumPy twins (the edge choice, the pairs of
(line, plane) each taken once under the depth gate), and a whole call that never waits for the device."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lipmap.mapping.assign import best_edges
from lipmap.mapping.pipeline import get_conf, line_supervision
from lipmap.mapping.supervision import _first_of_each_pair
from lipmap.planes import Planes
from lipmap.planes.init import DepthFrame
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.render import rasterize_planes
from lipmap.planes.targets import prepare_targets
from lipmap.testing import raycast_depth
from test_joint_optimization import _planes, panel_scene
from test_mapping_extract import detected
from test_raster_fused import CountDispatch, needs_warp
from test_raycast_fused import random_planes


@pytest.mark.parametrize("reduce", ["max", "mean"])
def test_best_edges_on_tensors_is_best_edges_on_arrays(reduce):
    """Tensors (the training device's path) and arrays (extraction, localization): the same edge, angle, distance and
    projected edge for every (plane, line) row, planes behind the camera included."""
    _, views = panel_scene()
    v = views[0]
    rng = np.random.default_rng(3)
    corners = random_planes(40, 0).corners().double()
    corners[:5, :, 2] *= -1  # behind the camera: no edge projects
    plane = rng.integers(0, 40, 500)
    lines = rng.uniform(0, [v.camera.width, v.camera.height] * 2, (500, 4))
    T = np.asarray(v.cam_from_world, dtype=np.float64)
    e_np, a_np, d_np, p_np = best_edges(corners.numpy(), plane, lines, T, v.camera, reduce)
    e_t, a_t, d_t, p_t = best_edges(corners, torch.as_tensor(plane), torch.as_tensor(lines), torch.as_tensor(T),
                                    v.camera, reduce)
    assert isinstance(e_np, np.ndarray) and torch.is_tensor(e_t)
    assert np.isinf(d_np).any() and np.isfinite(d_np).mean() > 0.5
    assert np.array_equal(e_t.numpy(), e_np)
    np.testing.assert_allclose(a_t.numpy(), a_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d_t.numpy(), d_np, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(p_t.numpy(), p_np, rtol=1e-12, atol=1e-9)  # NaN where the edge does not project


def test_each_line_plane_pair_once_under_the_gate():
    """Against the NumPy formulation the line term used: np.unique over (line, plane) keys, a pair kept when one of
    its pixels agrees with the sensor depth or none has sensor depth."""
    rng = np.random.default_rng(0)
    P, K = 3000, 50
    li = rng.integers(0, 200, P)
    plane = rng.integers(-1, K, P)
    ok_pix = rng.integers(-1, 2, P).astype(np.int8)
    keys, inv = np.unique(li * (K + 1) + (plane + 1), return_inverse=True)
    pairs = np.stack([keys // (K + 1), keys % (K + 1) - 1], 1)
    agree, known = np.zeros(len(pairs), bool), np.zeros(len(pairs), bool)
    np.logical_or.at(agree, inv, ok_pix == 1)
    np.logical_or.at(known, inv, ok_pix >= 0)
    want = pairs[(pairs[:, 1] >= 0) & (agree | ~known)]
    for gate in (True, False):
        rows, keep = _first_of_each_pair(torch.as_tensor(li), torch.as_tensor(plane), K,
                                         torch.as_tensor(ok_pix) if gate else None)
        got = torch.stack([torch.as_tensor(li)[rows], torch.as_tensor(plane)[rows]], 1)[keep].numpy()
        assert np.array_equal(got, want if gate else pairs[pairs[:, 1] >= 0])  # the same pairs, in key order


@needs_warp
@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_a_line_term_call_never_waits_for_the_device(preset):
    """The mapping presets' line term on a real render: assignments found, and no operation that would wait for the
    device (``nonzero``, ``.item()``, boolean indexing, ``unique``). The NumPy line term copied hits, corners and
    depth to the host at every call."""
    corners_true, views = panel_scene()
    v = views[0]
    frames = [DepthFrame(v, v.camera, v.cam_from_world, raycast_depth(corners_true, v))]
    tgt = prepare_targets(frames, PlaneOptConfig.preset("fast", downscale=1, progress=False))[0]
    planes = _planes(corners_true + np.array([0.01, -0.005, 0.0]))  # a little off the lines: a gradient everywhere
    out = rasterize_planes(*planes.tensors(), tgt.cam_from_world, tgt.camera.params, tgt.camera.width,
                           tgt.camera.height, 1500.0)
    got = {}
    for compact in (False, True):  # a GPU's rows (every candidate, masked) and a CPU's (the kept pairs)
        sup = line_supervision({v.name: detected(corners_true, v)}, get_conf(preset))
        sup.compact_rows = compact
        params = [t.clone().requires_grad_() for t in planes.tensors()]
        sup(v, Planes(*params), 0, out, tgt)  # the first call builds the view's cached geometry on the device
        with CountDispatch() as n:
            loss = sup(v, Planes(*params), 1, out, tgt)
            loss.backward()
        assert n.syncs == (1 if compact else 0), (compact, n.syncs)  # compacting reads the mask, once
        assert sup.last["n_assign"] > 0
        assert all(torch.isfinite(p.grad).all() and float(p.grad.abs().sum()) > 0 for p in (params[0], params[2]))
        got[compact] = (float(loss.detach()), sorted(sup.last["planes"].tolist()), params[0].grad.clone())
    assert got[False][1] == got[True][1]
    assert got[False][0] == pytest.approx(got[True][0], rel=1e-5)
    torch.testing.assert_close(got[False][2], got[True][2], rtol=1e-4, atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA needed")
def test_cuda_training_step_with_the_line_term_syncs_once():
    """A whole ``fast`` training step on CUDA (render, plane loss, line term, backward, fused Adam, the round's sums):
    torch's sync debug mode warns at most once (the renderer's pair count)."""
    import warnings

    from lipmap.planes.optimizer import _make_optimizer
    from lipmap.planes.train import Schedule, _EpochStats, _train_view

    corners_true, views = panel_scene()
    v = views[0]
    frames = [DepthFrame(v, v.camera, v.cam_from_world, raycast_depth(corners_true, v))]
    conf = PlaneOptConfig.preset("fast-lines", downscale=1, progress=False)
    tgt = prepare_targets(frames, conf, device="cuda")[0]
    params = [t.cuda().requires_grad_() for t in _planes(corners_true + np.array([0.01, -0.005, 0.0])).tensors()]
    sup = line_supervision({v.name: detected(corners_true, v)}, get_conf("fast"))
    opt, sched = _make_optimizer(params, conf), Schedule.of(conf, 1)
    stats = _EpochStats.zeros(len(params[0]), "cuda")
    _train_view(params, opt, tgt, 0, sched, sup, stats)  # kernels, cached geometry
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            _train_view(params, opt, tgt, 1, sched, sup, stats)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert sum("synchroniz" in str(w.message) for w in caught) <= 1, [str(w.message) for w in caught]
    assert stats.means()["skipped"] == 0 and sup.last["n_assign"] > 0
