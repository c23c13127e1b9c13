"""The switches by which ``--preset paper`` follows the reference code (and ``fast`` departs from it),
each on a known answer."""
import numpy as np
import pytest
import torch

from lipmap.mapping.assign import best_edges
from lipmap.mapping.losses import line_loss_terms
from lipmap.mapping.pipeline import get_conf
from lipmap.planes.optimize import PlaneOptConfig, Schedule, ViewTarget, _apply_step, _EpochStats, plane_loss
from lipmap.planes.render import RenderOutput
from lipmap.scene import Camera
from lipmap.testing import rect

CAM = Camera(100, 80, (100.0, 100.0, 50.0, 40.0))


def _target(depth):
    d = torch.as_tensor(depth, dtype=torch.float32)
    n = torch.zeros(*d.shape, 3)
    return ViewTarget(None, CAM, torch.eye(4), d, n, d > 0, torch.zeros(d.shape, dtype=torch.bool))


def test_depth_loss_only_where_the_render_has_planes():
    # the planes cover the left half at the right depth; the right half renders nothing
    gt = np.full((4, 4), 2.0)
    depth = torch.tensor(np.where(np.arange(4) < 2, 2.0, 0.0)[None].repeat(4, 0), dtype=torch.float32, requires_grad=True)
    alpha = (depth.detach() > 0).float()
    r = RenderOutput(depth, torch.zeros(4, 4, 3), alpha, torch.zeros(4, 4, 1, dtype=torch.long))
    all_px = plane_loss(r, _target(gt), PlaneOptConfig(depth_weight=1.0, normal_weight=0.0))
    rendered = plane_loss(r, _target(gt), PlaneOptConfig(depth_weight=1.0, normal_weight=0.0, depth_loss_on_rendered=True))
    assert all_px[1]["depth"] == pytest.approx(1.0)  # half the pixels are 2 m off
    assert rendered[1]["depth"] == pytest.approx(0.0)


def test_moments_of_centre_and_radii_reset_after_recentring():
    params = [torch.zeros(1, 3, requires_grad=True), torch.tensor([[1.0, 0, 0, 0]], requires_grad=True),
              torch.full((1, 4), 0.1, requires_grad=True)]
    for reset in (False, True):
        opt = torch.optim.Adam([{"params": [p]} for p in params], lr=1e-3)
        _apply_step(opt, params, (params[0].sum() + params[1].sum() + params[2].sum()) * 1.0, reset_moments=reset)
        m = [float(opt.state[p]["exp_avg"].abs().sum()) for p in params]
        assert (m[0] == 0 and m[2] == 0) == reset and m[1] > 0  # the quaternion keeps its moments
        assert int(opt.state[params[0]]["step"]) == 1  # the step count is kept


def test_split_criterion_mean_or_max_of_the_two_radii():
    g = torch.tensor([[0.1, 0.5, 0.2, 0.2]])
    for reduce, want in (("mean", [0.3, 0.2]), ("max", [0.5, 0.2])):
        s = _EpochStats.zeros(1, "cpu")
        s.add_step(torch.tensor(1.0), None, g, torch.tensor([True]), reduce)
        assert s.radii_grad()[0].tolist() == pytest.approx(want)


def test_extraction_distance_max_or_mean_of_the_endpoint_distances():
    # a plane 2 m ahead; its top edge projects to y = 40 - 100 * 0.25 / 2 = 27.5 for x in 35..65; the detection's
    # line (slope 0.1) passes 0.5 px and 3.5 px (vertically) from the edge's projected endpoints
    corners = rect([0, 0, 2.0], 0.3, 0.25)[None]
    det = np.array([[40.0, 28.5, 60.0, 30.5]])
    T = np.eye(4)
    e_max, _, d_max, _ = best_edges(corners, np.array([0]), det, T, CAM, dist_reduce="max")
    e_mean, _, d_mean, _ = best_edges(corners, np.array([0]), det, T, CAM, dist_reduce="mean")
    assert e_max[0] == e_mean[0]
    k = 1 / np.sqrt(1.01)  # vertical -> perpendicular distance
    assert d_max[0] == pytest.approx(3.5 * k, abs=1e-6) and d_mean[0] == pytest.approx(2.0 * k, abs=1e-6)


def test_endpoint_term_ignores_endpoints_outside_the_image():
    # an edge from x = 20 to x = 150 px (outside the 100-px image) on the row y = 40; detection 20..90
    edge = torch.tensor([[[-0.3, 0.0, 1.0], [1.0, 0.0, 1.0]]], dtype=torch.float64)  # u = 50 + 100 x
    det = torch.tensor([[20.0, 40.0, 90.0, 40.0]], dtype=torch.float64)
    euc_all, _, _ = line_loss_terms(edge, det, torch.eye(4, dtype=torch.float64), CAM)
    euc_in, _, _ = line_loss_terms(edge, det, torch.eye(4, dtype=torch.float64), CAM, euc_inside_only=True)
    assert float(euc_all[0]) == pytest.approx(60.0) and float(euc_in[0]) == pytest.approx(0.0)


def test_paper_preset_follows_the_reference_code():
    conf = get_conf("paper")
    planes = PlaneOptConfig.preset(conf.planes)
    assert (planes.split_grad_reduce, planes.depth_loss_on_rendered, planes.reset_moments_on_recenter) == ("max", True, True)
    assert (planes.lr_center, planes.lr_quat, planes.lr_radii) == (1e-3, 1e-3, 1e-3)
    # max_total_iters 6,000 whatever the number of views (60 epochs of the reference's 100 views)
    assert (Schedule.of(planes, 100).max_iters, Schedule.of(planes, 30).max_iters, Schedule.of(planes, 7000).max_iters) == (6000,) * 3
    assert conf.max_assign_frac == 0 and conf.euc_inside_only and conf.extract.dist_reduce == "mean"
    assert (conf.line_weight, conf.endpoint_weight, conf.robust_scale, conf.on_plane_lines) == (0.1, 0.5, 0.0, False)
    assert conf.line_depth_gate == 0 and get_conf("fast").line_depth_gate > 0  # the gate is ours, not the reference's
    assert (conf.extract.max_dist, conf.extract.max_angle) == (1.0, 0.01)
