"""Readable all-pairs twin of the fast plane renderer (for tests only; O(pixels x planes) memory).

:func:`_render_all_pairs` is the pure-torch reference implementation of
:func:`lipmap.planes.render.rasterize_planes`: it intersects every pixel ray with every plane, so
it is slow and memory-hungry (320x240 x 2000 planes: seconds and tens of GB) but obviously
follows the paper's appendix A. Tests compare both on values and on gradients.
"""
from __future__ import annotations

import torch

from ..geometry import ray_plane_intersection
from .primitives import MAX_HITS, NEAR, R_MAX, R_MIN, TRANSMITTANCE_EPS, WEIGHT_EPS, quat_to_rotmat


def _axis_weight(p: torch.Tensor, r_pos: torch.Tensor, r_neg: torch.Tensor, lam: float) -> torch.Tensor:
    """Splat weight along one axis: 1 inside [-r_neg, r_pos], 2 sigmoid(lam (r - |p|)) outside."""
    r = torch.where(p > 0, r_pos, r_neg)
    z = lam * (r - p.abs())
    return torch.where(z >= 0, torch.ones_like(z), 2 * torch.sigmoid(z))


def _render_all_pairs(
    center: torch.Tensor,  # (K, 3) world
    quat: torch.Tensor,  # (K, 4) wxyz
    radii: torch.Tensor,  # (K, 4) x+, x-, y+, y-
    cam_from_world: torch.Tensor,  # (4, 4)
    intrinsics: tuple,  # (fx, fy, cx, cy), COLMAP pixel centres
    width: int,
    height: int,
    lam: float,
    max_hits: int = MAX_HITS,
    near: float = NEAR,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """PyTorch all-pairs implementation of :func:`lipmap.planes.render.rasterize_planes`.

    Returns:
        **depth** :math:`(H, W)` z-depth, **normal** :math:`(H, W, 3)` camera-frame normals facing the
        camera, **alpha** :math:`(H, W)` accumulated weight sum_j T_j w_j.
    """
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    dev, dt = center.device, center.dtype
    T = cam_from_world.to(device=dev, dtype=dt)
    R_cw, t_cw = T[:3, :3], T[:3, 3]

    # planes in the camera frame
    c = center @ R_cw.T + t_cw  # (K, 3)
    Rc = R_cw @ quat_to_rotmat(quat)  # (K, 3, 3): columns X, Y, normal
    ax, ay, n = Rc[..., 0], Rc[..., 1], Rc[..., 2]
    r = radii.clamp(R_MIN, R_MAX)
    # the side of the plane the camera is on: normals are flipped to face the camera
    n = torch.where(((n * c).sum(-1) > 0)[:, None], -n, n)

    # pixel rays with z = 1, so the ray parameter is the z-depth
    u = (torch.arange(width, device=dev, dtype=dt) + 0.5 - cx) / fx
    v = (torch.arange(height, device=dev, dtype=dt) + 0.5 - cy) / fy
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    d = torch.stack([uu, vv, torch.ones_like(uu)], -1).reshape(-1, 1, 3)  # (P, 1, 3)

    # all ray x plane intersections (appendix A, "Ray-to-Plane Intersection")
    t = ray_plane_intersection(torch.zeros_like(d), d, c[None], n[None])  # (P, K)
    finite = torch.isfinite(t)
    t = torch.where(finite, t, torch.zeros_like(t))  # keeps NaN out of the backward pass
    p = t[..., None] * d - c[None]  # (P, K, 3) intersection relative to the centre
    px, py = (p * ax[None]).sum(-1), (p * ay[None]).sum(-1)

    # plane splatting function
    w = torch.minimum(_axis_weight(px, r[:, 0], r[:, 1], lam), _axis_weight(py, r[:, 2], r[:, 3], lam))

    # planar blending: the M nearest intersections with weight > WEIGHT_EPS, front to back
    valid = finite & (t > near) & (w > WEIGHT_EPS)
    key = torch.where(valid, t, torch.full_like(t, float("inf"))).detach()
    k = min(max_hits, key.shape[1])
    key_sel, idx = torch.topk(key, k, dim=1, largest=False, sorted=True)
    ok = torch.isfinite(key_sel)
    w_sel = torch.where(ok, w.gather(1, idx), torch.zeros_like(key_sel))
    t_sel = torch.where(ok, t.gather(1, idx), torch.zeros_like(key_sel))
    n_sel = n[idx]  # (P, k, 3)

    P = d.shape[0]
    depth = torch.zeros(P, device=dev, dtype=dt)
    normal = torch.zeros(P, 3, device=dev, dtype=dt)
    alpha = torch.zeros(P, device=dev, dtype=dt)
    trans = torch.ones(P, device=dev, dtype=dt)
    for j in range(k):
        use = ok[:, j] & (trans.detach() >= TRANSMITTANCE_EPS)
        wj = torch.where(use, w_sel[:, j], torch.zeros_like(trans))
        contrib = trans * wj
        depth = depth + contrib * t_sel[:, j]
        normal = normal + contrib[:, None] * n_sel[:, j]
        alpha = alpha + contrib
        trans = trans * (1 - wj)
    return depth.reshape(height, width), normal.reshape(height, width, 3), alpha.reshape(height, width)
