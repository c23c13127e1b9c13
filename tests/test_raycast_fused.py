"""The Warp first-hit kernel (lipmap.planes.raycast_warp) against its torch twin (lipmap.mapping.assign): the same
plane for every ray, with and without a render's hit lists, on random, coplanar, edge-on and empty scenes."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from lipmap.mapping.assign import _rect_frames, first_hit, first_hit_in_render, first_hit_torch, pixel_rays_world
from lipmap.planes import Planes, rasterize_planes
from lipmap.planes import raycast_warp
from lipmap.scene import Camera

HAVE_WARP = raycast_warp.unsupported(torch.device("cpu"), torch.float32) is None
needs_warp = pytest.mark.skipif(not HAVE_WARP and not os.environ.get("LIPMAP_REQUIRE_WARP"),
                                reason="warp-lang is not installed")
CAM = Camera(100, 80, (70.0, 70.0, 50.0, 40.0))


def random_planes(K, seed):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(K, 3)) * [0.3, 0.3, 1.0]
    normals[:, 2] = -np.abs(normals[:, 2])
    return Planes.from_normals(rng.uniform([-0.6, -0.5, 1.0], [0.6, 0.5, 2.5], (K, 3)), normals,
                               rng.uniform(0.05, 0.3, K))


def rays(cam_from_world=np.eye(4), step=1):
    jj, ii = np.meshgrid(np.arange(0, CAM.width, step), np.arange(0, CAM.height, step))
    pix = np.stack([jj.ravel(), ii.ravel()], 1)
    return (torch.as_tensor(a, dtype=torch.float32) for a in pixel_rays_world(pix, cam_from_world, CAM))


def away_from_borders(corners, o, d, k, margin=1e-3):
    """Rays whose chosen rectangle is not within ``margin`` (m) of a border and whose next rectangle along the ray is
    not within ``margin`` in depth: where float rounding (an FMA on one machine) cannot change the answer."""
    v3, X, Y, lx, ly, n = _rect_frames(corners)
    t = (((v3[None] - o[:, None]) * n[None]).sum(-1) / (d[:, None] * n[None]).sum(-1))  # (P, K)
    rel = o[:, None] + t[..., None] * d[:, None] - v3[None]
    u, w = (rel * X[None]).sum(-1), (rel * Y[None]).sum(-1)
    near_border = ((u.abs() < margin) | ((u - lx).abs() < margin) | (w.abs() < margin) | ((w - ly).abs() < margin))
    inside = (t > 0) & (u > -margin) & (u < lx + margin) & (w > -margin) & (w < ly + margin)
    tt = torch.where(inside, t, torch.full_like(t, float("inf"))).sort(1).values
    return ~(near_border & inside).any(1) & ~((tt[:, 1] - tt[:, 0]).abs() < margin)


@needs_warp
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_plane_agrees_with_torch(seed):
    planes = random_planes(60, seed)
    corners = planes.corners()
    o, d = rays()
    want = first_hit_torch(corners, o, d)[0]
    got = first_hit(corners, o, d, backend="warp")
    assert (want >= 0).float().mean() > 0.5 and len(set(want.tolist())) > 20
    ok = away_from_borders(corners, o, d, want)
    assert ok.float().mean() > 0.9
    assert torch.equal(got[ok], want[ok])
    assert (got != want).float().mean() < 0.01  # the rest: rounding at a border or a depth tie, if anywhere


@needs_warp
@pytest.mark.parametrize("max_hits", [5, 1])
def test_render_lists_agree_with_torch(max_hits):
    """Candidates from a render (cut at 1 hit: most rays fall back to every plane) against the torch twin and against
    casting every ray."""
    planes = random_planes(40, 0)
    corners = planes.corners()
    o, d = rays()
    out = rasterize_planes(planes.center, planes.quat, planes.radii, torch.eye(4), CAM.params, 100, 80, 36.8, max_hits)
    cand = out.hits.reshape(-1, max_hits)
    complete = (cand[:, -1] < 0) & (out.alpha.reshape(-1) < 1 - 1e-4)
    want = first_hit_in_render(corners, cand, o, d, complete, backend="torch")
    got = first_hit_in_render(corners, cand, o, d, complete, backend="warp")
    ok = away_from_borders(corners, o, d, want)
    assert torch.equal(got[ok], want[ok])
    assert torch.equal(got[ok], first_hit_torch(corners, o, d)[0][ok])


@needs_warp
def test_ties_edge_on_and_behind():
    """Exact duplicates go to the lower index (as torch.min); a plane seen edge-on and one behind the camera are never
    hit; a ray through nothing gets -1."""
    p = Planes.from_normals(np.array([[0, 0, 2.0], [0, 0, 2.0], [0.0, 0, 1.5], [-0.4, 0, -1.0]]),
                            np.array([[0, 0, -1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 0, -1.0]]), np.full(4, 0.3))
    corners = p.corners()
    o = torch.zeros(4, 3)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0, 1], [0.05, 0.02, 1], [0.5, 0.5, 1], [0.4, 0, 1.0]]), dim=1)
    for backend in ("torch", "warp"):
        assert first_hit(corners, o, d, backend=backend).tolist() == [0, 0, -1, -1], backend
    cand = torch.tensor([[1, 0], [-1, -1], [2, -1], [3, -1]])
    complete = torch.tensor([True, True, False, False])
    for backend in ("torch", "warp"):
        # the listed order decides a tie: first_hit_in_render takes the first candidate at the least depth
        got = first_hit_in_render(corners, cand, o, d, complete, backend=backend)
        assert got.tolist() == [1, -1, -1, -1], backend


@needs_warp
def test_empty_inputs():
    corners = random_planes(5, 0).corners()
    none = torch.zeros(0, 3)
    assert first_hit(corners, none, none, backend="warp").shape == (0,)
    o, d = rays(step=10)
    empty = torch.zeros(0, 4, 3)
    assert (first_hit(empty, o, d, backend="warp") == -1).all()
    assert (first_hit(empty, o, d, backend="torch") == -1).all()


@needs_warp
def test_float64_falls_back_to_torch():
    """The kernel is float32; float64 corners take the torch twin under "auto" and are refused under "warp"."""
    from lipmap.errors import InputError

    corners = random_planes(10, 0).corners().double()
    o, d = (x.double() for x in rays(step=5))
    assert torch.equal(first_hit(corners, o, d), first_hit_torch(corners, o, d)[0])
    with pytest.raises(InputError, match="float32"):
        first_hit(corners, o, d, backend="warp")
