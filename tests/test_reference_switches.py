"""The switches by which ``--preset paper`` follows the reference code (and ``fast`` departs from it),
each on a known answer."""
from pathlib import Path

import numpy as np
import pytest
import torch

from dataclasses import replace

from lipmap.mapping.assign import best_edges, first_hit_in_render, first_hit_torch, pixel_rays_world
from lipmap.mapping.joint import line_supervision
from lipmap.mapping.losses import assigned_edges, line_loss, line_loss_terms
from lipmap.mapping.pipeline import get_conf
from lipmap.mapping.supervision import LineSupervision
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.losses import plane_loss
from lipmap.planes.optimizer import _apply_step, _make_optimizer
from lipmap.planes.primitives import Planes
from lipmap.planes.render import RenderOutput, rasterize_planes
from lipmap.planes.targets import ViewTarget
from lipmap.planes.train import Schedule, _EpochStats, _restructure, render_target
from lipmap.scene import Camera, View
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
    for reduce, want in (("mean", [0.3, 0.2]), ("max", [0.5, 0.2]), ("max_of_means", [0.5, 0.2])):
        s = _EpochStats.zeros(1, "cpu")
        s.add_step(torch.tensor(1.0), None, g, torch.tensor([True]), reduce)
        assert s.radii_grad()[0].tolist() == pytest.approx(want)


def test_split_statistic_max_of_means_over_the_round():
    """The reference (``get_split_mask_via_radii_grad`` on ``radii_grad_accum / radii_grad_denom``): each radius's
    |grad| averaged over the steps that saw the plane, then the larger of the + and - sides. Two steps whose larger
    side alternates: x+ |grad| 0.4 then 0, x- 0 then 0.4: max of means 0.2, mean of max 0.4 (under a 0.3 threshold
    the reference does not split, the step-wise max does). A step that did not see the plane is not counted."""
    steps = [torch.tensor([[0.4, 0.0, 0.1, 0.3]]), torch.tensor([[0.0, 0.4, 0.1, 0.3]]), torch.tensor([[9.0, 9.0, 9.0, 9.0]])]
    got = {}
    for reduce in ("max", "max_of_means", "mean"):
        s = _EpochStats.zeros(1, "cpu")
        for g, vis in zip(steps, (True, True, False)):
            s.add_step(torch.tensor(1.0), None, g * vis, torch.tensor([vis]), reduce)
        got[reduce] = s.radii_grad()[0].tolist()
    assert got["max"] == pytest.approx([0.4, 0.3]) and got["max_of_means"] == pytest.approx([0.2, 0.3])
    assert got["mean"] == pytest.approx([0.2, 0.2])
    assert PlaneOptConfig.preset("paper").split_grad_reduce == "max_of_means"
    assert PlaneOptConfig.preset("fast-lines").split_grad_reduce == "mean"


def test_split_children_start_with_zero_moments():
    """The reference appends a split's new planes to Adam with zeroed moments (``cat_tensors_to_optimizer``) and
    prunes their parent; the planes that were not split keep theirs. ``fast`` copies the parent's moments."""
    planes = Planes.from_normals([[0.0, 0, 2.0], [0.5, 0, 2.0]], [[0, 0, -1.0]] * 2, [0.2, 0.2])
    params = [t.clone().requires_grad_(True) for t in planes.tensors()]
    got = {}
    for name in ("fast-lines", "paper"):
        conf = replace(PlaneOptConfig.preset(name), split_after_rounds=0)
        opt = _make_optimizer(params, conf)
        _apply_step(opt, params, sum((p * torch.arange(1.0, p.numel() + 1).view_as(p)).sum() for p in params))
        stats = _EpochStats.zeros(2, "cpu")
        stats.add_step(torch.tensor(1.0), None, torch.tensor([[1.0] * 4, [0.0] * 4]), torch.tensor([True, True]),
                       conf.split_grad_reduce)
        new, opt_new, imap = _restructure(params, opt, stats, 10, Schedule.of(conf, 10), {}, n_round=1)
        assert imap.n_split == 1 and len(new[0]) == 5 and imap.child.tolist() == [False] + [True] * 4
        got[name] = [opt_new.state[p]["exp_avg"].abs().sum(-1) for p in new]
    for m in got["fast-lines"]:
        assert (m > 0).all()  # the children took plane 0's moments
    for m in got["paper"]:
        assert m[0] > 0 and (m[1:] == 0).all()  # plane 1 (not split) keeps its moments


def test_paper_walks_the_views_in_sequence():
    """The reference's ``data_order = sequential``: view i at iteration i (mod the views); ``fast`` shuffles."""
    from lipmap.planes.train import optimize_planes

    targets = [_target(np.full((80, 100), 2.0 + 0.1 * i)) for i in range(4)]
    planes = Planes.from_normals([[0.0, 0, 2.0]], [[0, 0, -1.0]], [0.5])
    seen = {}
    for name in ("fast", "paper"):
        order = []

        def extra(view, pl, it, render, tgt):
            order.append(next(i for i, t in enumerate(targets) if t is tgt))
            return None

        conf = replace(PlaneOptConfig.preset(name), epochs=2, iterations=0, progress=False, device="cpu", split=False,
                       prune_unseen=False, prune_unseen_every=0)
        optimize_planes(targets, planes, conf, extra_loss=extra)
        seen[name] = order
    assert seen["paper"] == [0, 1, 2, 3] * 2
    assert sorted(seen["fast"][:4]) == [0, 1, 2, 3] and seen["fast"] != seen["paper"]


def test_paper_prunes_invisible_planes_at_iteration_0_and_every_1000():
    """The reference checks visibility (every view rendered) before its first step and after steps 1000, 2000, ...;
    its prune/split rounds only prune small planes. Ours by default prunes at each round the planes that round's
    views did not render. A plane behind every camera goes at iteration 0 under ``paper``."""
    from lipmap.planes.train import optimize_planes

    targets = [_target(np.full((80, 100), 2.0)) for _ in range(3)]
    planes = Planes.from_normals([[0.0, 0, 2.0], [0.0, 0, -2.0]], [[0, 0, -1.0], [0, 0, 1.0]], [0.5, 0.5])
    calls = []
    conf = replace(PlaneOptConfig.preset("paper"), iterations=7, progress=False, device="cpu", split=False,
                   prune_unseen_every=2, cull_back_faces=False, min_center_depth=0.0, max_hits=5)
    _, hist = optimize_planes(targets, planes, conf, on_restructure=lambda imap: calls.append(imap.n_old))
    # the clean start, the check at 0 (2 -> 1), rounds after 3, 6 and 7 (the last) steps; checks after the steps
    # of the reference's iterations 2, 4 and 6, with nothing left to prune
    assert [it for it, _ in hist["invisible_pruned"]] == [0, 2, 4, 6] and hist["invisible_pruned"][0][1] == 1
    assert calls == [2, 2, 1, 1, 1] and hist["planes"] == [1, 1, 1] and hist["unseen"] == [0, 0, 0]


def test_paper_counts_pixels_without_a_target_normal():
    """The reference's normal loss masks on the render alone (``valid_ray_mask``): a rendered pixel whose target
    normal is zero costs |n|_1 + 1 (here 1 + 1) and is counted; ours leaves it out."""
    normal = torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]], requires_grad=True)
    r = RenderOutput(torch.zeros(1, 2, requires_grad=True), normal, torch.ones(1, 2), torch.zeros(1, 2, 1, dtype=torch.long))
    tgt = ViewTarget(None, CAM, torch.eye(4), torch.zeros(1, 2), torch.tensor([[[0.0, 0, -1], [0, 0, 0]]]),
                     torch.zeros(1, 2, dtype=torch.bool), torch.tensor([[True, False]]))
    paper = PlaneOptConfig.preset("paper")
    assert paper.normal_loss_on_invalid_targets
    assert plane_loss(r, tgt, paper)[1]["normal"] == pytest.approx(2.0 / 2)
    assert plane_loss(r, tgt, replace(paper, normal_loss_on_invalid_targets=False))[1]["normal"] == pytest.approx(0.0)


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
    euc_all = line_loss_terms(edge, det, torch.eye(4, dtype=torch.float64), CAM)[0]
    euc_in = line_loss_terms(edge, det, torch.eye(4, dtype=torch.float64), CAM, euc_inside_only=True)[0]
    assert float(euc_all[0]) == pytest.approx(60.0) and float(euc_in[0]) == pytest.approx(0.0)


def _row_edges(*us):
    """Corners (K, 4, 3) whose first edge (v1 -> v2) runs along the image row y = 40 at z = 1 between the columns
    ``us`` = (u1, u2), (u3, u4), ...: x = (u - 50) / 100."""
    c = np.zeros((len(us), 4, 3))
    for k, (a, b) in enumerate(us):
        c[k, 0], c[k, 1] = [(a - 50) / 100, 0, 1], [(b - 50) / 100, 0, 1]
        c[k, 2], c[k, 3] = c[k, 1] + [0, 0.1, 0], c[k, 0] + [0, 0.1, 0]
    return torch.tensor(c)


def test_endpoint_term_is_the_mean_over_the_endpoints_inside_the_image():
    """The reference's D_euc (``lines_edps_loss_2d``): the mean distance over the projected endpoints inside the
    image, the endpoints paired on the unmasked squared distances. Edge A (u 20..70) sees detection 22..74 (2 and 4
    px); edge B (u -20..50, its first end outside) sees 40..90: paired as they stand (60^2 + 40^2 < 110^2 + 10^2),
    its inside end is 40 px from the detection's end. Mean over the 3 inside endpoints: 46 / 3 px; the edges lie on
    the detections' lines, so D_ort is 0. Pairing on the inside ends alone would have given 10 px, and a mean over
    the assignments 0.5 (6 + 10) / 2 = 4."""
    corners = _row_edges((20, 70), (-20, 50))
    det = np.array([[22.0, 40.0, 74.0, 40.0], [40.0, 40.0, 90.0, 40.0]])
    T = np.eye(4)
    euc, ort, valid, inside = line_loss_terms(assigned_edges(corners, [0, 1], [0, 0]), torch.tensor(det), torch.eye(4, dtype=torch.float64), CAM,
                                              euc_inside_only=True)
    assert euc.tolist() == pytest.approx([6.0, 40.0]) and inside.tolist() == [[1, 1], [0, 1]]
    conf = get_conf("paper")
    loss = line_loss(corners, [0, 1], [0, 0], det, [0, 1], T, CAM, endpoint_weight=conf.endpoint_weight,
                     euc_inside_only=conf.euc_inside_only, robust_scale=conf.robust_scale)
    assert float(loss) == pytest.approx(2 * 0.5 * 46 / 3)


def test_normal_loss_on_a_partly_covered_pixel():
    """The reference's normal loss (``normal_loss`` with ``valid_ray_mask``): unit normals, averaged over the pixels
    that render. A pixel half covered by a plane that faces the camera as the target does (its composited normal is
    alpha = 0.5 long) costs nothing, and a pixel no plane covers is not counted; as composited, over every pixel
    with a target normal, the first costs 0.5 + 0.5 and the second 1 + 1."""
    normal = torch.tensor([[[0.0, 0.0, -0.5], [0.0, 0.0, 0.0]]], requires_grad=True)
    alpha = torch.tensor([[0.5, 0.0]])
    r = RenderOutput(torch.zeros(1, 2, requires_grad=True), normal, alpha, torch.tensor([[[0], [-1]]]))
    tgt = ViewTarget(None, CAM, torch.eye(4), torch.zeros(1, 2), torch.tensor([[[0.0, 0, -1], [0, 0, -1]]]),
                     torch.zeros(1, 2, dtype=torch.bool), torch.ones(1, 2, dtype=torch.bool))
    ref = plane_loss(r, tgt, PlaneOptConfig.preset("paper"))
    assert ref[1]["normal"] == pytest.approx(0.0, abs=1e-7)
    assert plane_loss(r, tgt, PlaneOptConfig.preset("fast"))[1]["normal"] == pytest.approx((1.0 + 2.0) / 2)


def test_normal_loss_in_the_world_frame():
    # camera turned 45 deg about its axis: rendered (1, 0, 0), target (0, 1, 0) in the camera frame; L1 is 2 there
    # and sqrt(2) between the same normals in the world frame (the reference's ``normal_global``); 1 - cos is 1
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    r = RenderOutput(torch.zeros(1, 1), torch.tensor([[[1.0, 0, 0]]], requires_grad=True), torch.ones(1, 1),
                     torch.zeros(1, 1, 1, dtype=torch.long))
    tgt = ViewTarget(None, CAM, T, torch.zeros(1, 1), torch.tensor([[[0.0, 1, 0]]]), torch.zeros(1, 1, dtype=torch.bool),
                     torch.ones(1, 1, dtype=torch.bool))
    assert plane_loss(r, tgt, PlaneOptConfig.preset("paper"))[1]["normal"] == pytest.approx(np.sqrt(2) + 1, rel=1e-6)
    assert plane_loss(r, tgt, PlaneOptConfig.preset("fast"))[1]["normal"] == pytest.approx(3.0, rel=1e-6)


def _adam_steps(conf, n):
    """|centre step| of each of ``n`` steps of the plane optimizer of ``conf`` on one plane whose centre gradient
    changes sign and size at random (the radii and rotation get none)."""
    params = [torch.zeros(1, 3, requires_grad=True), torch.tensor([[1.0, 0, 0, 0]], requires_grad=True),
              torch.full((1, 4), 0.1, requires_grad=True)]
    opt = _make_optimizer(params, conf)
    g = torch.tensor(np.random.default_rng(0).uniform(0.1, 10, (n, 3)) * np.random.default_rng(1).choice([-1, 1], (n, 3)),
                     dtype=torch.float32)
    steps = []
    for i in range(n):
        before = params[0].detach().clone()
        _apply_step(opt, params, (params[0] * g[i]).sum() + 0 * params[1].sum() + 0 * params[2].sum(),
                    conf.reset_moments_on_recenter)
        steps.append((params[0].detach() - before).abs()[0].numpy())
    return opt, np.array(steps)


def test_paper_adam_moves_each_centre_by_lr_times_the_sign_of_its_gradient():
    """The reference's plane optimizer (``build_plane_optimizer_and_LRscheduler``, ``regularize_plane_shape``): Adam
    with betas (0.9, 0.99) and eps 1e-15 whose centre and radii moments are zeroed after every step, the step count
    kept. Step t is then lr * (1 - b1) / (1 - b1^t) * sqrt(1 - b2^t) / sqrt(1 - b2), whatever the gradient: lr from a
    few hundred steps on. With torch's b2 = 0.999 the same reset gives 2.1 lr at step 600 (3.2 lr at 6,000)."""
    conf = PlaneOptConfig.preset("paper")
    opt, steps = _adam_steps(conf, 600)
    assert opt.defaults["betas"] == (0.9, 0.99) and opt.defaults["eps"] == 1e-15
    t = np.arange(1, 601)[:, None]
    want = conf.lr_center * 0.1 / (1 - 0.9 ** t) * np.sqrt(1 - 0.99 ** t) / 0.1
    np.testing.assert_allclose(steps, np.broadcast_to(want, steps.shape), rtol=1e-3)
    assert steps[-1] == pytest.approx([conf.lr_center] * 3, rel=2e-3)  # sqrt(1 - 0.99^600) = 0.9988
    assert steps[0] == pytest.approx([conf.lr_center] * 3, rel=1e-3)


def test_fast_adam_keeps_its_moments():
    # fast: torch's Adam, moments kept (docs/design.md): after a run of gradients of one sign, a sign change moves
    # the centre less than lr, not lr the other way
    conf = PlaneOptConfig.preset("fast-lines")
    opt, _ = _adam_steps(conf, 3)
    assert opt.defaults["betas"] == tuple(conf.adam_betas) and opt.defaults["eps"] == conf.adam_eps
    assert not conf.reset_moments_on_recenter and float(opt.state[opt.param_groups[0]["params"][0]]["exp_avg"].abs().sum()) > 0


def _blank_target(view=None):
    """A view's target with no depth and no normals: what the renders and the line term see without supervision."""
    return ViewTarget(view, CAM, torch.eye(4), torch.zeros(80, 100), torch.zeros(80, 100, 3),
                      torch.zeros(80, 100, dtype=torch.bool), torch.zeros(80, 100, dtype=torch.bool))


def _occluder_scene():
    """An occluder (plane 0, 1 m ahead, its right edge at x = 0: column 50) in front of a wall (plane 1, 1.5 m), and
    a detected vertical line along column 51.5: its region pixels' rays pass 0.5-2.5 cm right of the occluder."""
    planes = Planes.from_normals([[-0.25, 0.0, 1.0], [0.0, 0.0, 1.5]], np.tile([0, 0, -1.0], (2, 1)),
                                 np.array([[0.25, 0.25, 0.3, 0.3], [0.5, 0.5, 0.5, 0.5]]))
    line = np.array([[51.5, 20.0, 51.5, 60.0]])
    return planes, line


def test_line_term_first_hit_is_the_rectangle_not_its_splat():
    """Paper Sec. 3.2 and the reference (``check_intersections_in_plane``): a region pixel's plane is the first
    rectangle its ray meets. At the reference's first splat sharpness (lambda 36.8) the occluder's fall-off reaches
    27 cm past its edge: the render's nearest splat along these pixels is the occluder, the rectangle they meet is
    the wall."""
    planes, line = _occluder_scene()
    v = View("v", CAM, np.eye(4), color_path=None)
    tgt = _blank_target(v)
    out = rasterize_planes(planes.center, planes.quat, planes.radii, torch.eye(4), CAM.params, 100, 80, 36.8)
    assert int(out.hits[40, 51, 0]) == 0 and int(out.hits[40, 51, 1]) == 1  # the occluder's splat, then the wall
    got = {}
    for name, kw in (("soft", dict(pixels_per_line=0, hard_first_hit=False)), ("hard", dict(pixels_per_line=0, hard_first_hit=True)),
                     ("sampled", dict(pixels_per_line=1))):
        sup = LineSupervision({"v": line}, weight=1.0, max_assign_frac=0.0, **kw)
        sup(v, planes, 0, out, tgt)
        got[name] = set(sup.last["planes"].tolist())
    assert got == {"soft": {0}, "hard": {1}, "sampled": {1}}
    paper = line_supervision({"v": line}, get_conf("paper"))
    paper(v, planes, 0, out, tgt)
    assert set(paper.last["planes"].tolist()) == {1}


def test_first_hit_in_render_agrees_with_casting_every_ray():
    """:func:`first_hit_in_render` (the render's lists, rays cast only where a list may have been cut) against
    :func:`first_hit_torch` (every ray against every plane), on random planes, with lists long enough and cut at 1."""
    rng = np.random.default_rng(0)
    K = 40
    normals = rng.normal(size=(K, 3)) * [0.3, 0.3, 1.0]
    normals[:, 2] = -np.abs(normals[:, 2])
    planes = Planes.from_normals(rng.uniform([-0.6, -0.5, 1.0], [0.6, 0.5, 2.5], (K, 3)), normals,
                                 rng.uniform(0.05, 0.3, K))
    corners = planes.corners()
    jj, ii = np.meshgrid(np.arange(100), np.arange(80))
    pix = np.stack([jj.ravel(), ii.ravel()], 1)
    o, d = (torch.as_tensor(a, dtype=torch.float32) for a in pixel_rays_world(pix, np.eye(4), CAM))
    want = first_hit_torch(corners, o, d)[0]
    assert (want >= 0).float().mean() > 0.5 and len(set(want.tolist())) > 20
    for max_hits in (5, 1):
        out = rasterize_planes(planes.center, planes.quat, planes.radii, torch.eye(4), CAM.params, 100, 80, 36.8, max_hits)
        cand = out.hits.reshape(-1, max_hits)
        complete = (cand[:, -1] < 0) & (out.alpha.reshape(-1) < 1 - 1e-4)
        got = first_hit_in_render(corners, cand, o, d, complete)
        assert torch.equal(got, want), (max_hits, int((got != want).sum()))


def _crossing_scene():
    """A slanted plane (0, centre 2 m, z = 2 + x tan 50deg) crossing a wall (1, centre 2.1 m): right of x = 0.084 m the
    slanted plane lies behind the wall."""
    a = np.radians(50)
    return Planes.from_normals([[0, 0, 2.0], [0, 0, 2.1]], [[np.sin(a), 0, -np.cos(a)], [0, 0, -1.0]], [0.5, 0.5])


def test_paper_renders_with_the_reference_hit_rule():
    """The reference's renderer walks a tile's planes by their centres' depth and skips a hit nearer than the last
    one it took: where the slanted plane (nearer centre) lies behind the wall, `paper` renders the slanted plane and
    `fast` the wall."""
    planes = _crossing_scene()
    tgt = _blank_target()
    first = {}
    for name in ("fast", "paper"):
        conf = replace(PlaneOptConfig.preset(name), max_hits=5)
        out = render_target(planes.tensors(), tgt, 1500.0, conf)
        assert out.hit_rule == conf.hit_rule
        first[name] = int(out.hits[40, 60, 0])  # its ray meets the wall at 2.1 m, the slanted plane at 2.29 m
    assert (PlaneOptConfig.preset("paper").hit_rule, PlaneOptConfig.preset("fast").hit_rule) == ("reference", "nearest")
    assert first == {"fast": 1, "paper": 0}


def test_the_line_term_casts_every_ray_under_the_reference_hit_rule():
    """A reference-rule render's list can leave out the first rectangle a ray meets (the wall, above): the line
    term's first hit then comes from every plane, as the reference's ``ray_plane_intersect`` does."""
    planes = _crossing_scene()
    v = View("v", CAM, np.eye(4), color_path=None)
    tgt = _blank_target(v)
    line = np.array([[60.5, 30.0, 60.5, 50.0]])
    out = rasterize_planes(planes.center, planes.quat, planes.radii, torch.eye(4), CAM.params, 100, 80, 1500.0,
                           hit_rule="reference")
    assert int(out.hits[40, 60, 0]) == 0 and int(out.hits[40, 60, 1]) == -1  # the wall is not in the list
    sup = LineSupervision({"v": line}, weight=1.0, max_assign_frac=0.0, pixels_per_line=0, hard_first_hit=True)
    sup(v, planes, 0, out, tgt)
    assert set(sup.last["planes"].tolist()) == {1}


def test_culled_planes_are_not_rendered():
    """The reference's renderer skips planes whose normal faces away from the camera and planes whose centre is
    nearer than 0.2 m; hits index the whole plane set."""
    planes = Planes.from_normals([[0.0, 0, 2.0], [0.1, 0, 1.5], [0.0, 0.1, 0.15]], [[0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]],
                                 [0.2, 0.2, 0.05])
    tgt = _blank_target()
    params = planes.tensors()
    seen = {}
    for name, conf in (("fast", PlaneOptConfig.preset("fast")), ("paper", PlaneOptConfig.preset("paper"))):
        out = render_target(params, tgt, 1500.0, replace(conf, max_hits=5))
        seen[name] = out.visible_planes(3).tolist()
    assert seen == {"fast": [True, True, True], "paper": [True, False, False]}


def test_paper_near_plane_is_the_reference_s():
    """The reference renders nothing nearer than z = 0.1 m; fast's near plane is 1 cm. A slanted plane (centre 0.25 m,
    so near-centre culling keeps it) reaches z = 0.08 m at the image's left edge."""
    planes = Planes.from_normals([[0.0, 0, 0.25]], [[4.0, 0, -1.0]], [0.5])
    tgt = _blank_target()
    nearest = {}
    for name in ("fast", "paper"):
        conf = replace(PlaneOptConfig.preset(name), max_hits=5)
        out = render_target(planes.tensors(), tgt, 1500.0, conf)
        hit = out.hits[..., 0] >= 0
        nearest[name] = float((out.depth.detach() / out.alpha.detach().clamp(min=1e-9))[hit & (out.alpha > 0.99)].min())
    assert PlaneOptConfig.preset("paper").near == 0.1 and PlaneOptConfig.preset("fast").near == 0.01
    assert nearest["fast"] < 0.09 and 0.0999 < nearest["paper"] < 0.11


def test_paper_splits_after_one_pass_over_the_views():
    # the reference's trainer splits when iter > split_start_ite = the number of views: from the second round on
    planes = Planes.from_normals([[0.0, 0, 2.0]], [[0, 0, -1.0]], [0.2])
    params = [t.clone().requires_grad_(True) for t in planes.tensors()]
    conf = PlaneOptConfig.preset("paper")
    sched = Schedule.of(conf, 10)
    splits = []
    for n_round in (0, 1):
        stats = _EpochStats.zeros(1, "cpu")
        stats.add_step(torch.tensor(1.0), None, torch.ones(1, 4), torch.tensor([True]), conf.split_grad_reduce)
        new, _, imap = _restructure(params, _make_optimizer(params, conf), stats, 10 * (n_round + 1), sched, {},
                                    n_round=n_round)
        splits.append(imap.n_split)
    assert splits == [0, 1]


def test_paper_preset_follows_the_reference_code():
    conf = get_conf("paper")
    planes = PlaneOptConfig.preset(conf.planes)
    assert (planes.split_grad_reduce, planes.depth_loss_on_rendered, planes.reset_moments_on_recenter) == ("max_of_means", True, True)
    assert (planes.zero_moments_of_split, planes.view_order, planes.prune_unseen_every) == (True, "sequential", 1000)
    assert planes.normal_loss_on_invalid_targets and planes.max_depth == 10.0 and planes.hit_rule == "reference"
    # the reference's fusion: 1 cm voxels, 2 cm truncation, every view, depth to 10 m, 10,000 planes
    i = planes.init
    assert (i.voxel_size, i.voxel_size * i.trunc_voxels, i.max_frames, i.max_depth, i.n_planes) == (0.01, 0.02, 0, 10.0, 10000)
    assert (planes.adam_betas, planes.adam_eps) == ((0.9, 0.99), 1e-15)
    assert (planes.normal_loss_normalized, planes.normal_loss_on_rendered, planes.normal_frame) == (True, True, "world")
    # the reference renderer: 30 contributors per pixel, back faces and planes whose centre is nearer than 0.2 m culled
    assert (planes.max_hits, planes.cull_back_faces, planes.min_center_depth, planes.split_after_rounds) == (30, True, 0.2, 1)
    # one sampled pixel per line and iteration, its first rectangle; every view; no minimum line length
    assert (conf.pixels_per_line, conf.hard_first_hit, conf.keyframes.enabled, conf.extract.min_length) == (1, True, False, 0)
    assert (planes.lr_center, planes.lr_quat, planes.lr_radii) == (1e-3, 1e-3, 1e-3)
    # max_total_iters 6,000 whatever the number of views (60 epochs of the reference's 100 views)
    assert (Schedule.of(planes, 100).max_iters, Schedule.of(planes, 30).max_iters, Schedule.of(planes, 7000).max_iters) == (6000,) * 3
    assert conf.max_assign_frac == 0 and conf.euc_inside_only and conf.extract.dist_reduce == "mean"
    assert (conf.line_weight, conf.endpoint_weight, conf.robust_scale, conf.on_plane_lines) == (0.1, 0.5, 0.0, False)
    assert conf.line_depth_gate == 0 and get_conf("fast").line_depth_gate > 0  # the gate is ours, not the reference's
    assert (conf.extract.max_dist, conf.extract.max_angle) == (1.0, 0.01)


def test_paper_gives_each_pixel_to_one_line():
    """The reference's attraction field labels each pixel with one line (``compute_point_line_attraction``): where
    two lines' 1-pixel regions overlap, the pixel goes to the nearer. Lines at y = 10.2 and 11.0 (x 5..20): row 10
    (centres at y 10.5) lies 0.3 px from the first and 0.5 px from the second."""
    from lipmap.mapping.assign import line_regions

    lines = np.array([[5.0, 10.2, 20.0, 10.2], [5.0, 11.0, 20.0, 11.0]])
    rows = {}
    for exclusive in (False, True):
        pix, li = line_regions(lines, 40, 30, exclusive=exclusive)
        rows[exclusive] = [sorted(set(pix[li == k, 1].tolist())) for k in (0, 1)]
        assert all((li == k).sum() == 15 * len(r) for k, r in enumerate(rows[exclusive]))
    assert rows == {False: [[9, 10], [10, 11]], True: [[9, 10], [11]]}
    conf = get_conf("paper")
    assert conf.one_line_per_pixel and conf.extract.exclusive_pixels and line_supervision({}, conf).exclusive_pixels
    assert not get_conf("fast").one_line_per_pixel and not get_conf("fast").extract.exclusive_pixels


def _edge_corners(segments):
    """Corners (K, 4, 3) whose first edge (v1 -> v2) is each segment (2, 3); the rest of each rectangle 1 m above."""
    s = np.asarray(segments, dtype=float)
    up = np.array([0, 0, 1.0])
    return np.stack([s[:, 0], s[:, 1], s[:, 1] + up, s[:, 0] + up], 1)


def _obs(rows):
    r = np.array(rows, dtype=np.int64)
    return {"view": r[:, 0], "line": r[:, 1], "plane": r[:, 2], "edge": np.zeros(len(r), dtype=np.int64),
            "n_pixels": np.ones(len(r), dtype=np.int64)}


def test_reference_global_merge_never_joins_groups():
    """Four collinear edges A..D (x 0-1, 1-2, 2-3, 3-4): view 0's first detection sees A, B, its second C, D; view
    1's detection sees B, C. The reference gives A, B one group and C, D another; the cluster {B, C} has no new
    edge, so nothing changes: two lines. Connected components join the groups through it: one line."""
    from lipmap.mapping.extract import ExtractConfig, merge_edges

    x = np.arange(5.0)
    corners = _edge_corners([[[x[i], 0, 2], [x[i + 1], 0, 2]] for i in range(4)])
    obs = _obs([(0, 0, 0), (0, 0, 1), (0, 1, 2), (0, 1, 3), (1, 0, 1), (1, 0, 2)])
    lines = {}
    for rule in ("components", "reference"):
        lines[rule], obs_line, edge_line = merge_edges(corners, obs, ExtractConfig(min_length=0.0, global_rule=rule))
    assert len(lines["components"]) == 1 and len(lines["reference"]) == 2
    spans = sorted(sorted(l[:, 0].round(6).tolist()) for l in lines["reference"])
    assert spans == [[0.0, 2.0], [2.0, 4.0]]
    assert edge_line[:, 0].tolist() == [0, 0, 1, 1]
    assert get_conf("paper").extract.global_rule == "reference" and get_conf("fast").extract.global_rule == "components"


def test_reference_global_merge_distance_is_one_sided():
    """A 2 cm edge a at the origin along x and a 2 m edge b through it at 0.1 rad: a's points lie within 0.6 mm of
    b's line, b's points 5.5 cm (mean) from a's. The reference's DBSCAN (eps 1 cm) on the one-sided matrix puts b in
    a's neighbourhood: one line; the symmetrised distance (2.8 cm) keeps them apart."""
    from lipmap.mapping.extract import ExtractConfig, _edge_distance_matrix, merge_edges

    t = 0.1
    segs = [[[-0.01, 0, 2], [0.01, 0, 2]], [[-np.cos(t), -np.sin(t), 2], [np.cos(t), np.sin(t), 2]]]
    corners = _edge_corners(segs)
    D = _edge_distance_matrix(np.asarray(segs), symmetric=False)
    assert D[0, 1] < 1e-3 and D[1, 0] == pytest.approx(np.mean(np.abs(np.linspace(-1, 1, 10))) * np.sin(t), rel=1e-6)
    obs = _obs([(0, 0, 0), (0, 0, 1)])
    n = {rule: len(merge_edges(corners, obs, ExtractConfig(min_length=0.0, global_rule=rule))[0])
         for rule in ("components", "reference")}
    assert n == {"components": 2, "reference": 1}


def test_paper_writes_the_merged_and_the_unmerged_map(tmp_path):
    """``paper`` writes linemap.h5 (the reference's global merge) and linemap_unmerged.h5 (one line per accepted
    plane edge), each saying which it is; a second call reuses both. A short run of the preset (its switches, fewer
    iterations, coarser fusion) on a tiny synthetic room."""
    from lipmap.datasets import load_scene
    from lipmap.datasets.synthetic import SynthConfig, generate_scene
    from lipmap.linemap import LineMap
    from lipmap.mapping.pipeline import UNMERGED, map_scene

    generate_scene(tmp_path / "data", seed=1, preset=SynthConfig("tiny", 160, 120, 131.25, 131.25, 80.0, 60.0,
                                                                   n_mapping=6, n_query=1, texels_per_m=100.0))
    scene = load_scene("synthetic", tmp_path / "data", "room-s1")
    conf = {"preset": "paper", "planes": {"preset": "paper", "iterations": 24, "prune_unseen_every": 12,
                                          "init": {"voxel_size": 0.05, "n_planes": 400}}}
    path = map_scene(scene, tmp_path / "m", conf)
    merged, unmerged = LineMap.load(path), LineMap.load(path.with_name(UNMERGED))
    assert (merged.metadata["map"], unmerged.metadata["map"], merged.metadata["unmerged_file"]) == ("merged", "unmerged", UNMERGED)
    assert 0 < len(merged) <= len(unmerged)
    assert unmerged.metadata["config"]["extract"]["merge"] == "none"
    mtime = path.stat().st_mtime_ns
    assert map_scene(scene, tmp_path / "m", conf) == path and path.stat().st_mtime_ns == mtime


def test_map_eval_says_which_map_it_scores(tmp_path):
    """``lipmap-loc map-eval`` names the map it scores; ``--unmerged`` scores linemap_unmerged.h5 beside --linemap,
    and refuses where there is none."""
    import json

    import trimesh

    from localization.cli import main
    from lipmap.linemap import LineMap
    from lipmap.mapping.pipeline import UNMERGED

    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.export(tmp_path / "box.ply")
    seg = np.array([[[-0.5, -0.5, 0.5], [0.5, -0.5, 0.5]], [[-0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]])
    LineMap(seg[:1], [[]], metadata={"map": "merged", "method": "lipmap"}).save(tmp_path / "linemap.h5")
    LineMap(seg, [[], []], metadata={"map": "unmerged", "method": "lipmap"}).save(tmp_path / UNMERGED)
    for flag, which, name in (([], "merged", "linemap.h5"), (["--unmerged"], "unmerged", UNMERGED)):
        out = tmp_path / f"eval{len(flag)}.json"
        assert main(["map-eval", "--linemap", str(tmp_path / "linemap.h5"), *flag, "--gt", str(tmp_path / "box.ply"),
                     "--json", str(out)]) == 0
        res = json.loads(out.read_text())
        assert (res["map"], Path(res["linemap"]).name, res["n_lines"]) == (which, name, len(flag) + 1)
    (tmp_path / UNMERGED).unlink()
    assert main(["map-eval", "--linemap", str(tmp_path / "linemap.h5"), "--unmerged", "--gt", str(tmp_path / "box.ply")]) == 2


def test_paper_rotation_is_two_quaternions_never_renormalised():
    """The reference's rotation: a normal quaternion (w, x, y) and an in-plane one (w, z), q = q_n * q_z, each
    normalised where used and never in place. Its first Adam step moves each of the five numbers by lr x the sign of
    its gradient, and they stay where the step put them; ``fast``'s one quaternion is renormalised after the step."""
    from lipmap.planes.primitives import quat_to_rotmat
    from lipmap.planes.rotation import composed, split

    q = torch.nn.functional.normalize(torch.tensor(np.random.default_rng(0).normal(size=(50, 4))), dim=-1)
    assert torch.allclose(quat_to_rotmat(composed(split(q))), quat_to_rotmat(q), atol=1e-12)
    # q_n = (cos 30, sin 30, 0): the normal turned 60 deg about x; q_z = (cos 45, sin 45): the x axis turned 90 deg
    rot = torch.tensor([[np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0, np.cos(np.pi / 4), np.sin(np.pi / 4)]])
    R = quat_to_rotmat(composed(rot))[0]
    assert torch.allclose(R[:, 2], torch.tensor([0.0, -np.sin(np.pi / 3), np.cos(np.pi / 3)]), atol=1e-6)
    assert torch.allclose(R[:, 0], torch.tensor([0.0, np.cos(np.pi / 3), np.sin(np.pi / 3)]), atol=1e-6)

    conf = PlaneOptConfig.preset("paper")
    assert conf.rotation == "normal-inplane" and PlaneOptConfig.preset("fast").rotation == "quaternion"
    params = [torch.zeros(1, 3, requires_grad=True), torch.tensor([[1.0, 0, 0, 1, 0]], requires_grad=True),
              torch.full((1, 4), 0.1, requires_grad=True)]
    opt = _make_optimizer(params, conf)
    g = torch.tensor([[1.0, -1.0, 2.0, -3.0, 4.0]])
    _apply_step(opt, params, (params[1] * g).sum() + 0 * params[0].sum() + 0 * params[2].sum(), True)
    lr = conf.lr_quat
    assert params[1].detach()[0].tolist() == pytest.approx([1 - lr, lr, -lr, 1 + lr, -lr], rel=1e-6)
    fast = PlaneOptConfig.preset("fast")
    p4 = [torch.zeros(1, 3, requires_grad=True), torch.tensor([[1.0, 0, 0, 0]], requires_grad=True),
          torch.full((1, 4), 0.1, requires_grad=True)]
    _apply_step(_make_optimizer(p4, fast), p4, (p4[1] * g[:, :4]).sum() + 0 * p4[0].sum() + 0 * p4[2].sum())
    assert float(p4[1].detach().norm()) == pytest.approx(1.0, abs=1e-6)
