"""Line losses between detected 2D segments and the projections of their assigned plane edges (torch).

Paper Sec. 3.3: endpoint (Euclidean) loss, orthogonal loss, and the group loss (an option, off in the
reference code). Distances are in pixels of the image the lines were detected in.
"""
from __future__ import annotations

import torch

from .. import geometry as geo
from .assign import EDGE_VERTS


def assigned_edges(corners: torch.Tensor, plane_idx, edge_idx) -> torch.Tensor:
    """(K, 4, 3) corners, (P,) plane and edge indices -> (P, 2, 3) 3D edges (differentiable)."""
    ev = torch.as_tensor(EDGE_VERTS, device=corners.device)[torch.as_tensor(edge_idx, device=corners.device)]
    c = corners[torch.as_tensor(plane_idx, device=corners.device)]  # (P, 4, 3)
    return torch.gather(c, 1, ev[..., None].expand(-1, -1, 3))


def line_loss_terms(edges3d: torch.Tensor, det: torch.Tensor, cam_from_world: torch.Tensor, camera,
                    euc_inside_only: bool = False):
    """Per-assignment endpoint and orthogonal distances.

    Args:
        edges3d: :math:`(P, 2, 3)` world edges; det: :math:`(P, 4)` detected segments (px).
        euc_inside_only: D_euc as the reference codes it: only the projected endpoints inside the image count (an
            edge that leaves the image cannot be seen to end where the detection ends), and the endpoints are paired
            on the sum of the squared distances of both, inside or not; else paired on the smaller D_euc.

    Returns:
        **euc** :math:`(P,)` = the summed distances of the paired endpoints (paper D_euc; those inside the image with
        ``euc_inside_only``), **ort** :math:`(P,)` = summed distances of the projected endpoints to the detected line
        (D_ort), **valid** :math:`(P,)` (edge in front of the camera), **inside** :math:`(P, 2)` (the weight of each
        endpoint in ``euc``: 1, or with ``euc_inside_only`` whether it projects inside the image).
    """
    proj, valid = geo.project_segments(edges3d, cam_from_world, camera)
    d = det.reshape(-1, 2, 2)
    proj = torch.where(valid[:, None, None], proj, d)  # invalid -> zero loss, masked below anyway
    w = torch.ones(proj.shape[:2], dtype=proj.dtype, device=proj.device)
    dist_direct = (proj - d).norm(dim=-1)  # (P, 2): endpoint i to detection endpoint i
    dist_swapped = (proj - d.flip(1)).norm(dim=-1)
    if euc_inside_only:
        x, y = proj[..., 0].detach(), proj[..., 1].detach()
        w = ((x >= 0) & (x <= camera.width) & (y >= 0) & (y <= camera.height)).to(proj.dtype)
        swap = (dist_swapped.detach() ** 2).sum(-1) < (dist_direct.detach() ** 2).sum(-1)
        euc = torch.where(swap, (w * dist_swapped).sum(-1), (w * dist_direct).sum(-1))
    else:
        euc = torch.minimum((w * dist_direct).sum(-1), (w * dist_swapped).sum(-1))
    ort = geo.perpendicular_distance(proj, d, reduce=None).sum(-1)
    return euc, ort, valid, w


def group_loss(edges3d: torch.Tensor, line_idx: torch.Tensor) -> torch.Tensor:
    """Paper Eq. (group): 3D orthogonal distance between edges assigned to the same detected line.

    For every pair of assignments of one line, the distances of one edge's endpoints to the other
    edge's infinite 3D line, averaged. Returns 0 when no line has two assignments.
    """
    li = torch.as_tensor(line_idx, device=edges3d.device)
    same = (li[:, None] == li[None]) & ~torch.eye(len(li), dtype=torch.bool, device=edges3d.device)
    if not bool(same.any()):
        return edges3d.sum() * 0
    i, j = same.nonzero(as_tuple=True)
    a, b = edges3d[i], edges3d[j]
    db = b[:, 1] - b[:, 0]
    db = db / db.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    rel = a - b[:, :1]  # (Q, 2, 3)
    perp = rel - (rel * db[:, None]).sum(-1, keepdim=True) * db[:, None]
    return perp.norm(dim=-1).mean()


def robust_px(d: torch.Tensor, scale: float) -> torch.Tensor:
    """``scale * log(1 + d / scale)`` of pixel distances d >= 0: L1 near 0, gradient 1 / (1 + d / scale).

    An assignment whose edge is many ``scale`` away is usually another surface's edge (a texture line
    inside a plane is assigned to that plane's nearest edge): its pull fades instead of dragging the
    plane across the scene.
    """
    return scale * torch.log1p(d / scale)


def line_loss(corners, plane_idx, edge_idx, det, line_idx, cam_from_world, camera, use_group: bool = False,
              group_weight: float = 1.0, endpoint_weight: float = 0.5, robust_scale: float = 0.0,
              euc_inside_only: bool = False, mask=None):
    """Mean over assignments of ``endpoint_weight`` * D_euc + max endpoint-to-line distance (0.5: the
    reference code's form), plus the optional group loss (metres, weighted by ``group_weight``).

    With ``euc_inside_only`` the D_euc part is the reference's: ``2 * endpoint_weight`` x the mean distance over the
    endpoints that project inside the image (the reference averages over those, so an edge leaving the image does
    not dilute it), added to the mean over assignments of the max endpoint-to-line distance (with ``robust_scale`` > 0,
    the per-assignment form below with the inside endpoints' D_euc).

    Detected segments are usually shorter than the plane edge they see (fragments, occlusion, the
    image border), so D_euc pulls every assigned edge's ends towards the fragment's ends and shrinks
    the plane; ``endpoint_weight=0`` keeps only the orthogonal term, which every fragment agrees on.

    Args:
        corners: :math:`(K, 4, 3)` plane corners with grad; plane_idx/edge_idx/line_idx: :math:`(P,)`;
        det: :math:`(P, 4)` detected segments in pixels of ``camera``.
        mask: :math:`(P,)` bool tensor, the assignments that count (None: all); the means run over these, with
            no data-dependent shape and no host sync (0 when none counts). The group loss indexes its pairs.
    """
    if len(plane_idx) == 0:
        return corners.sum() * 0
    edges = assigned_edges(corners, plane_idx, edge_idx)
    T = torch.as_tensor(cam_from_world, dtype=corners.dtype, device=corners.device)
    det = torch.as_tensor(det, dtype=corners.dtype, device=corners.device)
    euc, _, valid, inside = line_loss_terms(edges, det, T, camera, euc_inside_only)
    proj, _ = geo.project_segments(edges, T, camera)
    proj = torch.where(valid[:, None, None], proj, det.reshape(-1, 2, 2))
    ort_max = geo.perpendicular_distance(proj, det.reshape(-1, 2, 2), reduce="max")
    if mask is not None:
        valid = valid & torch.as_tensor(mask, device=valid.device)
    n_valid = valid.sum().clamp(min=1).to(corners.dtype)

    def total(x):  # the sum over the valid assignments (finite values elsewhere are masked, not indexed)
        return torch.where(valid.reshape(-1, *([1] * (x.dim() - 1))), x, 0.0).sum()

    if euc_inside_only and robust_scale <= 0:
        n_inside = total(inside).clamp(min=1)
        euc_mean = total(euc) / n_inside * 2  # per assignment, as endpoint_weight expects
        loss = endpoint_weight * euc_mean + total(ort_max) / n_valid
    else:
        per = endpoint_weight * euc + ort_max
        if robust_scale > 0:
            per = robust_px(per, robust_scale)
        loss = total(per) / n_valid
    if use_group:
        li = torch.as_tensor(line_idx, device=edges.device)
        if mask is not None:
            m = torch.as_tensor(mask, device=edges.device)
            edges, li = edges[m], li[m]
        loss = loss + group_weight * group_loss(edges, li)
    return loss
