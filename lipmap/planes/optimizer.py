"""Adam over the plane parameters and the step: backward, update, then the reference's re-centring."""
from __future__ import annotations

from typing import Optional

import torch

from .config import PlaneOptConfig
from .primitives import Planes
from .render import resolve_backend


def _live(planes: Planes) -> list:
    """The live parameters [center, quat, radii]: contiguous copies (numpy-made planes are column-major), which the
    fused re-centring updates in place."""
    return [t.clone(memory_format=torch.contiguous_format).requires_grad_(True) for t in planes.tensors()]


def _make_optimizer(params: list, conf: PlaneOptConfig, old: Optional[torch.optim.Adam] = None, parent=None,
                    fresh: Optional[torch.Tensor] = None):
    """Adam over [center, quat, radii]; with ``old`` and ``parent``, moments follow the index map, except for the
    planes ``fresh`` (bool, new indices), whose moments start at zero."""
    opt = torch.optim.Adam(
        [
            {"params": [params[0]], "lr": conf.lr_center},
            {"params": [params[1]], "lr": conf.lr_quat},
            {"params": [params[2]], "lr": conf.lr_radii},
        ],
        betas=tuple(conf.adam_betas),
        eps=conf.adam_eps,
        # one fused kernel per step, and a skipped step decided on the device (its found_inf, see _apply_step)
        fused=all(p.device.type in ("cpu", "cuda") and p.dtype == torch.float32 for p in params),
    )
    if old is not None and parent is not None:
        for g_old, g_new in zip(old.param_groups, opt.param_groups):
            p_old, p_new = g_old["params"][0], g_new["params"][0]
            st = old.state.get(p_old)
            if st:
                opt.state[p_new] = {
                    "step": st["step"].clone() if torch.is_tensor(st["step"]) else st["step"],
                    "exp_avg": st["exp_avg"][parent].clone(),
                    "exp_avg_sq": st["exp_avg_sq"][parent].clone(),
                }
                if fresh is not None:
                    for key in ("exp_avg", "exp_avg_sq"):
                        opt.state[p_new][key][fresh] = 0
    return opt


def _recenter_fused(params: list) -> bool:
    """The re-centring and quaternion normalisation as one Warp launch where the renderer runs on Warp (:meth:`Planes.
    recentered` is its twin, at about 70 dispatched operations a step); False: not done here."""
    c = params[0]
    if resolve_backend(None, c.device, c.dtype, 1) != "warp":
        return False
    from . import raster_warp

    return raster_warp.recenter_(*params)


def _apply_step(opt: torch.optim.Adam, params: list, total: torch.Tensor, reset_moments: bool = False,
                taken: Optional[torch.Tensor] = None):
    """Backward, Adam step, then the reference's re-centring and quaternion normalisation (and, with
    ``reset_moments``, its reset of the centre's and radii's Adam moments, as a replaced tensor gets).

    ``taken`` (a 0-d bool tensor): False skips the Adam step (parameters, moments and step count untouched). A fused
    Adam skips it on the device (its ``found_inf``); another optimizer reads the flag (one host sync).
    """
    opt.zero_grad(set_to_none=False)
    total.backward()
    for p in params:
        if p.grad is not None:
            torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
    radii_grad = params[2].grad.clone() if params[2].grad is not None else None
    if taken is None:
        opt.step()
    elif opt.defaults.get("fused"):
        opt.found_inf = (~taken).to(torch.float32)
        try:
            opt.step()
        finally:
            opt.found_inf = None
    elif bool(taken):
        opt.step()
    with torch.no_grad():
        if params[1].shape[-1] != 4:  # the reference's two quaternions: re-centred, and never renormalised
            from .rotation import composed

            rec = Planes(params[0], composed(params[1]), params[2]).recentered()
            params[0].copy_(rec.center)
            params[2].copy_(rec.radii)
        elif not _recenter_fused(params):
            rec = Planes(params[0], params[1], params[2]).recentered()
            params[0].copy_(rec.center)
            params[2].copy_(rec.radii)
            params[1].div_(params[1].norm(dim=1, keepdim=True).clamp(min=1e-12))
        if reset_moments:
            for p in (params[0], params[2]):
                st = opt.state.get(p)
                if st:
                    st["exp_avg"].zero_()
                    st["exp_avg_sq"].zero_()
    return radii_grad
