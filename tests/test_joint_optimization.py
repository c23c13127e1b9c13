"""The joint line-plane optimization, through the real plane loop (optimize_planes + LineSupervision).

A 0.6 x 0.4 m panel 2 m in front of a tiled back wall (tiles, because radii are clamped at 0.5 m);
the panel's plane starts 3 cm too large on every side and turned by 1.5 degrees in its plane. The
joint loss (plane loss + line term) must bring its four edges onto the detected lines, so that
extraction finds them within the paper's thresholds (1 px, 0.01 rad), and closer than the plane loss
alone gets them (which, against this exact depth, still leaves them ~4-5 mm off).
"""
import contextlib
import functools
import types

import numpy as np
import pytest
import torch

from lipmap.mapping.extract import ExtractConfig, extract_observations, merge_edges
from lipmap.mapping.pipeline import get_conf, lipmap_linemap
from lipmap.mapping.supervision import LineSupervision
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.init import DepthFrame
from lipmap.planes.primitives import Planes, rotmat_to_quat
from lipmap.planes.targets import prepare_targets
from lipmap.planes.train import optimize_planes
from lipmap.testing import SMALL_CAMERA, raycast_depth, rect
from scipy.spatial.transform import Rotation

from lipmap.poses import make_T
from lipmap.scene import View
from test_mapping_extract import detected


def panel_scene():
    panel = rect([0.1, -0.05, 2.0], 0.3, 0.2)
    tiles = [rect([x, y, 4.0], 0.5, 0.5) for x in np.arange(-2.5, 3.0, 1.0) for y in np.arange(-2.0, 2.5, 1.0)]
    views = []
    for i, (yaw, tx) in enumerate([(0.0, 0.0), (4.0, 0.15), (-5.0, -0.2), (2.0, 0.05)]):
        R = Rotation.from_euler("y", yaw, degrees=True).as_matrix()
        views.append(View(f"v{i}", SMALL_CAMERA, make_T(R, [tx, 0.03 * i, 0]), color_path=None))
    return np.stack([panel, *tiles]), views


def _planes(corners, grow=0.0, turn_deg=0.0):
    """Planes (centre, quaternion, radii) of axis-aligned rectangles (K, 4, 3); first one perturbed."""
    c = corners.mean(1)
    X = corners[:, 0] - corners[:, 3]
    Y = corners[:, 0] - corners[:, 1]
    rx, ry = np.linalg.norm(X, axis=1) / 2, np.linalg.norm(Y, axis=1) / 2
    X, Y = X / (2 * rx[:, None]), Y / (2 * ry[:, None])
    R = np.stack([X, Y, np.cross(X, Y)], 2)
    R[0] = R[0] @ Rotation.from_euler("z", turn_deg, degrees=True).as_matrix()
    radii = np.stack([rx, rx, ry, ry], 1)
    radii[0] += grow
    return Planes(torch.tensor(c, dtype=torch.float32), torch.tensor(rotmat_to_quat(R), dtype=torch.float32),
                  torch.tensor(radii, dtype=torch.float32))


@contextlib.contextmanager
def _torch_threads(n):
    """Run torch ops with ``n`` intra-op threads, then restore the previous count."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


# The corner errors below are deterministic on a machine but not across machines: float reduction order
# changes with the thread count (and the CPU's SIMD width), and a 160-step Adam run amplifies it. Two
# measures keep the outcome robust (spread measured over seeds 0-9 of PlaneOptConfig and LineSupervision
# x 1 / 2 torch threads, on an AVX-512 CPU): the optimization runs on 1 thread, so the core count no
# longer matters (and a loaded 2-core machine runs it in ~8 s instead of 60-380 s with 2 spinning
# threads), and the learning rates are annealed to 10 % (lr_final_frac, as the fast-lines preset does):
# at a constant 3e-3 Adam moves the edges by ~3 mm per step to the end, so the errors were that jitter
# (max 1.6-6.4 mm with the line term, 3.0-9.2 mm without (seeds 0-4): no bound separated them);
# annealed they settle.
def _optimize(line_weight, pixels_per_line=1, endpoint_weight=0.0):
    return _optimize_cached(float(line_weight), int(pixels_per_line), float(endpoint_weight))  # one cache key per run


@functools.lru_cache(maxsize=None)
def _optimize_cached(line_weight, pixels_per_line, endpoint_weight):
    corners, views = panel_scene()
    lines = {v.name: detected(corners, v, shrink=0.05) for v in views}  # fragments 5 % short at each end
    frames = [DepthFrame(v, v.camera, v.cam_from_world, raycast_depth(corners, v)) for v in views]
    conf = PlaneOptConfig.preset("fast", epochs=40, lr_center=3e-3, lr_quat=3e-3, lr_radii=3e-3, lr_final_frac=0.1,
                                 prune_unseen=False, progress=False)
    init = _planes(corners, grow=0.03, turn_deg=1.5)
    sup = LineSupervision(lines, weight=line_weight, pixels_per_line=pixels_per_line, endpoint_weight=endpoint_weight)
    with _torch_threads(1):
        planes, _ = optimize_planes(prepare_targets(frames, conf), init, conf, extra_loss=sup)
    got = planes.corners().numpy().astype(float)
    err = np.linalg.norm(got[0][:, None] - corners[0][None], axis=-1).min(1)  # panel corners, metres
    return corners, views, lines, init, got, err


ERR_BOUND = 0.002  # m, panel corners after the joint optimization (see the spread above)


@pytest.mark.parametrize("pixels_per_line", [1, 0])
def test_joint_optimization_puts_edges_on_detected_lines(pixels_per_line):
    corners, views, lines, init, got, err = _optimize(0.1, pixels_per_line)
    before = extract_observations(init.corners().numpy().astype(float), views, lines, ExtractConfig(), progress=False)
    assert len(before["plane"]) == 0  # nothing passes the paper's thresholds before optimizing
    # started 4-5 cm away. Worst 1.34 mm (ppl 1) / 0.83 mm (ppl 0) over seeds 0-9 x 1/2 threads (seed 0:
    # 0.58 / 0.53 mm); bound 1.5x the worst; the plane loss alone leaves 3.75-4.99 mm (test below)
    assert err.max() < ERR_BOUND, err
    obs = extract_observations(got, views, lines, ExtractConfig(), progress=False)
    assert {(0, 0), (0, 1), (0, 2), (0, 3)} <= set(zip(obs["plane"].tolist(), obs["edge"].tolist()))
    lines3d, _, edge_line = merge_edges(got, obs, ExtractConfig())
    assert (edge_line[0] >= 0).all()
    # each panel edge became a 3D line within 5 mm of the true edge
    for e in range(4):
        l = lines3d[edge_line[0, e]]
        a, b = corners[0, e], corners[0, (e + 1) % 4]
        d = b - a
        perp = (l - a) - ((l - a) @ d / (d @ d))[:, None] * d
        assert np.linalg.norm(perp, axis=1).max() < 0.005


def test_plane_loss_alone_leaves_edges_off():
    """What the line term is for: without it (line weight 0) the corners stay outside the bound above."""
    *_, err = _optimize(0.0)
    assert err.max() > ERR_BOUND, err  # 3.75-4.99 mm over seeds 0-9 x 1/2 threads (seed 0: 3.75 mm)


def test_endpoint_term_shrinks_planes_to_short_detections():
    """With detections 5 % short at each end, the reference form (0.5 * D_euc) drags the panel's ends
    inwards; the orthogonal term alone (``endpoint_weight=0``) does not."""
    # Every (line, plane) pair (pixels_per_line=0): with one sampled pixel per line the drag is erratic (max
    # error 2.2-5.3 mm annealed, 2.7-29 mm at a constant lr: the ratio fell below 2 for 1 and 4 of 10 seeds).
    # Here err_euc 2.42-2.60 mm vs err_ort 0.25-0.83 mm over seeds 0-9 x 1/2 threads: ratio >= 2.9.
    *_, err_ort = _optimize(0.1, 0, endpoint_weight=0.0)
    *_, err_euc = _optimize(0.1, 0, endpoint_weight=0.5)
    assert err_euc.max() > 2 * err_ort.max(), (err_euc, err_ort)


def test_depth_check_rejects_lines_off_the_sensor_depth():
    """``max_depth_residual`` keeps the lines of the panel's four edges when the sensor depth agrees with them and
    drops them (and their plane-edge table entries) when the sensor sees the panel 10 cm further away."""
    corners, views = panel_scene()
    lines = {v.name: detected(corners, v, shrink=0.05) for v in views}
    depth = {v.name: raycast_depth(corners, v) for v in views}
    scene = types.SimpleNamespace(mapping=views)
    conf = get_conf({"extract": ExtractConfig(max_depth_residual=0.03), "on_plane_lines": False})
    lm = lipmap_linemap(scene, _planes(corners), lines, conf, depth)
    assert (lm.planes["edge_line"][0] >= 0).all() and lm.metadata.get("n_depth_rejected") == 0
    far = {k: np.where(d > 0, d + 0.1, 0) for k, d in depth.items()}
    lm = lipmap_linemap(scene, _planes(corners), lines, conf, far)
    assert len(lm) == 0 and (lm.planes["edge_line"] == -1).all()
    assert lm.metadata["n_depth_rejected"] >= 4


def test_on_plane_lines_lift_texture_lines_onto_their_plane():
    """A line painted on the back wall is no plane edge: ``on_plane_lines`` lifts it onto the wall (ray
    cast plane depth), merged into one line tracked in every view; the panel's edges stay edge lines."""
    from lipmap.geometry import point_line_distance, project_segments
    from lipmap.mapping.pipeline import edge_line_mask

    corners, views = panel_scene()
    paint = np.array([[-1.4, 0.55, 4.0], [-0.75, 0.7, 4.0]])
    lines = {}
    for v in views:
        seg, ok = project_segments(paint[None], v.cam_from_world, v.camera)
        assert ok.all() and (seg >= 0).all() and (seg[..., 0] < v.camera.width).all() and (seg[..., 1] < v.camera.height).all()
        lines[v.name] = np.concatenate([detected(corners, v, shrink=0.05), seg.reshape(1, 4)])
    depth = {v.name: raycast_depth(corners, v) for v in views}
    scene = types.SimpleNamespace(mapping=views)
    lm = lipmap_linemap(scene, _planes(corners), lines, get_conf("fast"), depth)
    edges = edge_line_mask(lm)
    # the panel's 4 edges (plus a tile border that v0 sees exactly behind the panel's bottom edge)
    assert edges.sum() == lm.metadata["n_edge_lines"] >= 4
    assert (~edges).sum() == lm.metadata["n_on_plane_lines"] == 1
    onp = lm.subset(~edges)
    assert point_line_distance(paint[None], onp.lines[0][None]).max() < 0.005
    assert point_line_distance(onp.lines, paint[None]).max() < 0.005
    assert sorted(o.image_name for o in onp.tracks[0]) == [v.name for v in views]
    assert all(o.line2d_index == 4 for o in onp.tracks[0])
    # the paper's output (plane edges only)
    lm_edges = lipmap_linemap(scene, _planes(corners), lines, get_conf({"on_plane_lines": False}), depth)
    assert len(lm_edges) == edges.sum() and edge_line_mask(lm_edges).all()


def test_on_plane_lines_take_the_input_depth_where_no_plane_models_it():
    """Where the input depth is > plane_depth_tol from the planes (clutter no plane models), the on-plane
    lines follow the input depth; within the tolerance (or with tol 0) they stay on the plane."""
    from lipmap.geometry import project_segments
    from lipmap.mapping.pipeline import edge_line_mask

    corners, views = panel_scene()
    paint = np.array([[-1.4, 0.55, 4.0], [-0.75, 0.7, 4.0]])  # on the back wall (z = 4)
    lines = {}
    for v in views:
        seg, _ = project_segments(paint[None], v.cam_from_world, v.camera)
        lines[v.name] = np.concatenate([detected(corners, v, shrink=0.05), seg.reshape(1, 4)])
    scene = types.SimpleNamespace(mapping=views)
    exact = {v.name: raycast_depth(corners, v) for v in views}

    def wall_offsets(depth, tol):
        lm = lipmap_linemap(scene, _planes(corners), lines, get_conf({"plane_depth_tol": tol}), depth)
        onp = lm.subset(~edge_line_mask(lm))
        assert len(onp) >= 1
        return onp.lines[..., 2] - 4.0

    for off in (0.01, 0.1):  # the sensor puts every surface `off` further along the optical axis
        shifted = {k: np.where(d > 0, d + off, 0).astype(np.float32) for k, d in exact.items()}
        assert np.abs(wall_offsets(shifted, 0.0)).max() < 0.005  # plane depth alone
        z = wall_offsets(shifted, 0.03)
        if off < 0.03:  # the plane models the surface: its depth wins
            assert np.abs(z).max() < 0.005
        else:  # it does not: the input depth (z-depth + 10 cm -> 10 cm behind the wall)
            assert np.abs(z - off).max() < 0.01


def test_explained_detections_keep_only_those_near_the_edge_with_a_gate():
    """A track built with loose gates holds detections beside the edge (other lines): with ``explain_gate`` they are
    no longer explained, so the on-plane step lifts them; the detection on the edge stays explained."""
    from lipmap.geometry import project_segments
    from lipmap.linemap import LineMap
    from lipmap.mapping.pipeline import explained_detections

    corners, views = panel_scene()
    edge = corners[0][[0, 1]]  # one edge of the panel
    tracks = [[]]
    for v in views[:2]:
        seg = project_segments(edge[None], v.cam_from_world, v.camera)[0][0]
        d = seg[1] - seg[0]
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        c = seg.mean(0)
        turn = Rotation.from_euler("z", 0.03).as_matrix()[:2, :2]  # 0.03 rad about the segment's middle
        tracks[0] += [(v.name, 0, seg.reshape(4)), (v.name, 1, (seg + 3.0 * n).reshape(4)),
                      (v.name, 2, ((seg - c) @ turn.T + c).reshape(4))]
    lm = LineMap(edge[None], tracks)
    assert explained_detections(lm, views, ()) == {v.name: [0, 1, 2] for v in views[:2]}
    assert explained_detections(lm, views, (2.0, 0.01)) == {v.name: [0] for v in views[:2]}
    assert explained_detections(lm, views, (4.0, 0.01)) == {v.name: [0, 1] for v in views[:2]}
    assert explained_detections(lm, views, (4.0, 0.05)) == {v.name: [0, 1, 2] for v in views[:2]}


def test_plane_or_input_depth_known_values():
    from lipmap.mapping.assign import plane_or_input_depth

    plane = np.array([[2.0, 2.0, 0.0, 3.0]], dtype=np.float32)
    inp = np.array([[2.01, 2.2, 1.5, 0.0]], dtype=np.float32)
    np.testing.assert_allclose(plane_or_input_depth(plane, inp, 0.03), [[2.0, 2.2, 1.5, 3.0]])
    np.testing.assert_allclose(plane_or_input_depth(plane, inp, 0.0), plane)
    np.testing.assert_allclose(plane_or_input_depth(plane, None, 0.03), plane)
    # input depth at half the resolution is sampled to the plane depth's size
    big = np.full((4, 6), 2.0, dtype=np.float32)
    small = np.full((2, 3), 2.5, dtype=np.float32)
    np.testing.assert_allclose(plane_or_input_depth(big, small, 0.03), np.full((4, 6), 2.5))


def test_edge_refinement_moves_plane_edges_onto_their_detections():
    """A plane 5 mm too large on every side gives edges 5 mm off the panel's (still within extraction's 2 px);
    ``refine.lines="edges"`` moves them onto the four views' detections, and leaves them alone when off."""
    corners, views = panel_scene()
    lines = {v.name: detected(corners, v, shrink=0.05) for v in views}
    depth = {v.name: raycast_depth(corners, v) for v in views}
    scene = types.SimpleNamespace(mapping=views)

    def panel_edge_offsets(refine):
        conf = get_conf({"on_plane_lines": False, "refine": refine})
        lm = lipmap_linemap(scene, _planes(corners, grow=0.005), lines, conf, depth)
        assert (lm.planes["edge_line"][0] >= 0).all()
        out = []
        for e in range(4):
            a, b = corners[0, e], corners[0, (e + 1) % 4]
            l = lm.lines[lm.planes["edge_line"][0, e]]
            d = (b - a) / np.linalg.norm(b - a)
            out.append(np.linalg.norm((l - a) - ((l - a) @ d)[:, None] * d, axis=1).max())
        return np.array(out)

    plain = panel_edge_offsets({"enabled": False, "lines": "edges"})
    assert plain.min() > 0.004, plain
    on_plane_only = panel_edge_offsets({"enabled": True, "lines": "on-plane"})
    assert np.allclose(on_plane_only, plain)
    refined = panel_edge_offsets({"enabled": True, "lines": "edges"})
    assert refined.max() < 0.0015, refined
