"""The plane loss (depth and normals against a view's targets) and the total with an extra term."""
from __future__ import annotations

from typing import Optional

import torch

from ..errors import InputError
from .config import PlaneOptConfig
from .render import RenderOutput
from .targets import ViewTarget


def plane_loss(render: RenderOutput, target: ViewTarget, conf: PlaneOptConfig) -> Optional[tuple]:
    """(loss, parts) = depth_weight * L1(depth) + normal_weight * (L1(normal) + mean(1 - n . n_gt)).

    Means run over the pixels with valid targets (the paper's sums, normalised), and with
    ``conf.depth_loss_on_rendered`` / ``conf.normal_loss_on_rendered`` only over those the render covers (alpha >
    1e-5). The rendered normal is the alpha-weighted sum of the hit planes' normals: ``conf.normal_loss_normalized``
    compares unit normals (the reference), else it is compared as it is. ``conf.normal_frame`` "world" compares them
    rotated into the world frame (the reference), "camera" as rendered. Returns None when the view has no valid
    target pixel or the render has no gradient path; ``parts`` are detached 0-d tensors.

    Masked means over the whole map, never a boolean index: nothing here waits for the device (a mean over no pixel
    is 0, with no gradient). Whether anything rendered at all is :func:`_train_view`'s to check.
    """
    parts = {}
    loss = None
    has_depth, has_normal = target.has_targets
    rendered = render.alpha.detach() > 1e-5
    valid = target.depth_valid & rendered if conf.depth_loss_on_rendered else target.depth_valid
    if render.depth.requires_grad and has_depth:
        dl = _masked_mean((render.depth - target.depth).abs(), valid)
        parts["depth"] = dl.detach()
        loss = conf.depth_weight * dl
    nvalid = torch.ones_like(rendered) if conf.normal_loss_on_invalid_targets else target.normal_valid
    nvalid = nvalid & rendered if conf.normal_loss_on_rendered else nvalid
    if render.normal.requires_grad and has_normal:
        pn, gn = render.normal, target.normal
        if conf.normal_loss_normalized:
            pn, gn = torch.nn.functional.normalize(pn, dim=-1), torch.nn.functional.normalize(gn, dim=-1)
        if conf.normal_frame == "world":  # n_world = R^T n_cam, as rows
            R = target.cam_from_world[:3, :3].to(pn.dtype)
            pn, gn = pn @ R, gn @ R
        elif conf.normal_frame != "camera":
            raise InputError(f"normal_frame must be 'camera' or 'world', got {conf.normal_frame!r}")
        nl = _masked_mean((pn - gn).abs().sum(-1), nvalid) + _masked_mean(1 - (pn * gn).sum(-1), nvalid)
        parts["normal"] = nl.detach()
        loss = conf.normal_weight * nl if loss is None else loss + conf.normal_weight * nl
    return None if loss is None else (loss, parts)


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``mask`` (same shape), 0 over an empty mask; no data-dependent shape, so no host sync."""
    return torch.where(mask, x, 0.0).sum() / mask.sum().clamp(min=1).to(x.dtype)


def _pulls(extra) -> bool:
    """Whether an extra loss term has a gradient path to the planes."""
    return extra is not None and torch.is_tensor(extra) and extra.requires_grad


def _total_loss(pl: Optional[tuple], extra, plane_scale: float):
    """``plane_scale * plane loss + extra`` (either may be missing); None when nothing has a gradient."""
    total = None if pl is None else plane_scale * pl[0]
    if _pulls(extra):
        total = extra if total is None else total + extra
    return total
