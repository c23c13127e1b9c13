"""Plane optimization against depth and normal maps (LiP-Map / PlanarSplatting, plane part).

One view per iteration (seeded order), Adam on centre, quaternion and radii, plane loss
``2 * depth L1 + 5 * (normal L1 + (1 - cos))`` weighted ``10 * max(exp(-i / max_iters), 0.1)``,
re-centring after every step, and once per epoch pruning (smallest radius <= 1.25e-3 or seen by
no view) and splitting (mean |grad| of an axis's radii >= threshold). Reference-code facts are in
DESIGN.md; what is ours is said where it is done.

Hook for the line loss: ``optimize_planes(..., extra_loss=f)`` adds ``f(view, planes, iteration,
render)`` (a scalar tensor, already weighted) to the total; see :func:`optimize_planes`. Pruning and
splitting go through :func:`prune_and_split`, whose :class:`PlaneIndexMap` lets callers carry
per-plane state across the change.
"""
from __future__ import annotations

import inspect
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from .. import logger
from ..errors import InputError
from ..normals import normals_from_depth
from .init import DepthFrame, PlaneInitConfig, auto_downscale, depth_frames, downscale_frames, init_planes, resize_nearest
from .io import export_planes_ply, save_planes
from .primitives import MAX_HITS, R_MAX, R_MIN, Planes
from .render import TILE_SIZE, RenderOutput, lambda_schedule, rasterize_planes


@dataclass
class PlaneOptConfig:
    """Plane optimization settings; build presets with :meth:`preset` (``fast``, ``paper``)."""

    name: str = "custom"
    epochs: int = 60
    downscale: int = 1  # optimize at 1 / downscale of the view resolution; 0 = from target_width
    target_width: int = 160  # with downscale = 0: the integer factor that brings the width closest to this
    lr_center: float = 1e-3
    lr_quat: float = 1e-3
    lr_radii: float = 1e-3
    lr_final_frac: float = 1.0  # learning rates decay exponentially to this fraction by the last iteration
    depth_weight: float = 2.0
    normal_weight: float = 5.0
    plane_weight: float = 10.0  # total = plane_weight * decay * plane_loss + extra
    decay_floor: float = 0.1  # decay = max(exp(-i / max_iters), decay_floor)
    max_depth: float = 6.0  # ignore target depth beyond this (metres)
    normal_step: int = 0  # neighbour distance (full-res pixels) for normals from depth; 0 = width // 80
    # (8 px at 640x480: Kinect depth quantization makes 2-px normals mostly noise)
    max_hits: int = MAX_HITS
    tile_size: int = TILE_SIZE
    lambda_min: float = 0.0  # clip the splat sharpness schedule (0 / 1500 = the reference schedule)
    lambda_max: float = 1500.0
    prune_min_radius: float = 1.25e-3
    prune_unseen: bool = True
    split: bool = True
    split_grad_threshold: float = 0.2  # mean |d loss / d radius| over the epoch (see prune_and_split)
    split_stop_frac: float = 5000 / 6000  # no splitting after this fraction of the iterations
    split_into_four: bool = True  # both axes over the threshold -> 4 children, else 2
    max_planes: int = 20000  # splitting never grows the set beyond this
    seed: int = 0
    device: str = "auto"  # "auto" = CUDA when available
    progress: bool = True
    init: PlaneInitConfig = field(default_factory=PlaneInitConfig)

    @staticmethod
    def preset(name: str, **overrides) -> "PlaneOptConfig":
        if name not in confs:
            raise InputError(f"unknown plane optimization preset {name!r}; choose one of {', '.join(confs)}")
        init_over = overrides.pop("init", None)
        conf = replace(confs[name](), **overrides)
        if init_over is not None:
            conf.init = init_over if isinstance(init_over, PlaneInitConfig) else replace(conf.init, **init_over)
        return conf

    def to_dict(self) -> dict:
        return asdict(self)


def _fast() -> PlaneOptConfig:
    # Tests and the demo (CPU): ~320 px wide images, 8 epochs, 2 cm TSDF voxels. Measured on the
    # synthetic room-s3 (30 mapping views at 320x240; median |rendered - true depth| on the 20
    # query views) while tuning, all else equal:
    # - lr 1e-2 (reference 1e-3): Adam moves a parameter by ~lr per step, and 240 steps at
    #   1e-3..3e-3 cannot grow the 2-3 cm init radii to wall size (lr 3e-3 -> 1e-2 at 160 px:
    #   8.6 cm -> 2.5 cm);
    # - lambda clipped to >= 300: the reference's soft start (lambda 37..300, splats reaching
    #   3-27 cm beyond each rectangle) costs ~20 s per epoch on CPU and was worse here
    #   (2.5 cm -> 1.6 cm at 160 px); 320 px instead of 160 px: 1.6 -> 0.9 cm;
    # - no splitting: within 8 epochs each split threshold tried (0.2, 0.6, 1.5 on our
    #   mean-over-pixels losses) made it worse (4.5, 2.2, 1.1 cm vs 0.9 cm without).
    return PlaneOptConfig(
        name="fast",
        epochs=8,
        downscale=0,
        target_width=320,
        lr_center=1e-2,
        lr_quat=1e-2,
        lr_radii=1e-2,
        lambda_min=300.0,
        split=False,
        init=PlaneInitConfig(n_planes=2000, voxel_size=0.02, depth_downscale=1),
    )


def _fast_lines() -> PlaneOptConfig:
    # The joint line-plane optimization on CPU (mapping preset "fast"). Measured on the synthetic
    # room-s0 (line F@5cm against the mesh; line weight 0.3 unless said) starting from "fast":
    # - lr 1e-2 on the quaternion random-walks the in-plane rotation (median 8.5 deg off the room's
    #   axes after optimization), so edges cannot settle on lines: 2e-3, with every lr annealed to
    #   10 % (lr_final_frac), 24 epochs: F 0.057 -> 0.156; 40 epochs: 0.193;
    # - 6000 initial planes instead of 2000 (more edges to align): F 0.242 -> 0.284 (weight 1, 24 ep.);
    # - splitting (threshold on the mean |d loss / d radius|): 1.0 adds planes where lines pull,
    #   0.284 -> 0.298; 0.6 at 72 epochs 0.325 -> 0.326 and R@50mm 279 -> 301; 0.2 shatters the
    #   planes (median depth error 1.5 mm -> 8.8 cm);
    # - 24 -> 48 -> 72 epochs (split 1.0): F 0.271 -> 0.314 -> 0.325, depth error stays 1-2 mm.
    # On the RedKitchen mini (50 views, 640x480 trained at 320x240) the same run takes ~4-7 min.
    fast = _fast()
    return replace(
        fast,
        name="fast-lines",
        epochs=72,
        lr_quat=2e-3,
        lr_final_frac=0.1,
        split=True,
        split_grad_threshold=0.6,
        init=replace(fast.init, n_planes=6000),
    )


def _paper() -> PlaneOptConfig:
    # Reference-code settings: full resolution, 60 epochs, lr 1e-3, 1 cm voxels.
    return PlaneOptConfig(name="paper", epochs=60, downscale=1, init=PlaneInitConfig(voxel_size=0.01, depth_downscale=1))


confs = {"fast": _fast, "fast-lines": _fast_lines, "paper": _paper}


# ------------------------------------------------------------------------------------------------
# targets
# ------------------------------------------------------------------------------------------------
@dataclass
class ViewTarget:
    """Supervision of one view at the working resolution (tensors on the optimization device)."""

    view: object
    camera: object  # scaled Camera
    cam_from_world: torch.Tensor  # (4, 4)
    depth: torch.Tensor  # (h, w), 0 = invalid
    normal: torch.Tensor  # (h, w, 3) camera frame, 0 = invalid
    depth_valid: torch.Tensor  # (h, w) bool
    normal_valid: torch.Tensor  # (h, w) bool


def prepare_targets(frames: list, conf: PlaneOptConfig, device=None) -> list:
    """:class:`ViewTarget` per :class:`~lipmap.planes.init.DepthFrame` (full-resolution depth).

    Normals come from ``view.load_normals()`` when the view has a normal map, else from the
    full-resolution depth (:func:`lipmap.normals.normals_from_depth`), then both maps are resized
    to the working resolution by nearest sampling.
    """
    out = []
    for f in frames:
        ds = conf.downscale or auto_downscale(f.camera.width, conf.target_width)
        cam = f.camera if ds <= 1 else f.camera.scaled(1.0 / ds)
        normals = f.view.load_normals() if getattr(f.view, "normal_path", None) is not None else None
        if normals is None:
            step = conf.normal_step or max(2, f.camera.width // 80)
            normals = normals_from_depth(f.depth, f.camera, step=step)
        depth = resize_nearest(f.depth, cam.width, cam.height)
        normals = resize_nearest(normals, cam.width, cam.height)
        depth = np.where(np.isfinite(depth) & (depth > 0) & (depth <= conf.max_depth), depth, 0).astype(np.float32)
        normals = np.nan_to_num(normals).astype(np.float32)
        d = torch.as_tensor(depth, device=device)
        n = torch.as_tensor(normals, device=device)
        out.append(
            ViewTarget(
                f.view, cam, torch.as_tensor(f.cam_from_world, dtype=torch.float32, device=device),
                d, n, d > 0, n.norm(dim=-1) > 0.5,
            )
        )
    return out


def plane_loss(render: RenderOutput, target: ViewTarget, conf: PlaneOptConfig) -> Optional[tuple]:
    """(loss, parts) = depth_weight * L1(depth) + normal_weight * (L1(normal) + mean(1 - n . n_gt)).

    Means run over the pixels with valid targets (the paper's sums, normalised). Returns None when
    the view has no valid target pixel or the render has no gradient path (nothing visible).
    """
    parts = {}
    loss = None
    if render.n_pairs == 0:  # every plane culled for this view
        return None
    if render.depth.requires_grad and bool(target.depth_valid.any()):
        dl = (render.depth - target.depth)[target.depth_valid].abs().mean()
        parts["depth"] = float(dl.detach())
        loss = conf.depth_weight * dl
    if render.normal.requires_grad and bool(target.normal_valid.any()):
        pn, gn = render.normal[target.normal_valid], target.normal[target.normal_valid]
        nl = (pn - gn).abs().sum(-1).mean() + (1 - (pn * gn).sum(-1)).mean()
        parts["normal"] = float(nl.detach())
        loss = conf.normal_weight * nl if loss is None else loss + conf.normal_weight * nl
    return None if loss is None else (loss, parts)


# ------------------------------------------------------------------------------------------------
# pruning / splitting
# ------------------------------------------------------------------------------------------------
@dataclass
class PlaneIndexMap:
    """How a restructured plane set relates to the previous one.

    Attributes:
        parent: :math:`(K_{new},)` int64, the old index each new plane comes from (a split plane's
            children share their parent). Per-plane state follows as ``state_new = state_old[parent]``.
        n_old: K_old.
    """

    parent: torch.Tensor
    n_old: int
    n_pruned: int = 0
    n_split: int = 0
    n_unseen: int = 0  # of n_pruned: valid and large enough, but seen by no view

    def old_to_new(self) -> torch.Tensor:
        """:math:`(K_{old}, 4)` int64: the new indices of each old plane (-1 padded; all -1 = pruned)."""
        out = torch.full((self.n_old, 4), -1, dtype=torch.long, device=self.parent.device)
        order = torch.argsort(self.parent, stable=True)
        p = self.parent[order]
        first = torch.searchsorted(p, p)  # index of the first child of the same parent
        out[p, torch.arange(len(p), device=p.device) - first] = order
        return out


def prune_and_split(
    planes: Planes,
    seen: Optional[torch.Tensor] = None,  # (K,) bool
    radii_grad: Optional[torch.Tensor] = None,  # (K, 2) mean |grad| of the x radii and of the y radii
    min_radius: float = 1.25e-3,
    split_threshold: Optional[float] = 0.2,
    split_into_four: bool = True,
    max_planes: int = 20000,
) -> tuple[Planes, PlaneIndexMap]:
    """Remove degenerate, tiny and unseen planes; split planes with large radius gradients.

    Removed: non-finite parameters, zero quaternions, any radius <= ``min_radius`` (radii are
    read unclamped, so zero and negative radii go too), and ``~seen`` when ``seen`` is given.
    Split (when ``split_threshold`` is set and ``radii_grad`` given): an axis whose mean |grad|
    >= threshold is cut in two halves (children half as long along it, centred on each half); with
    both axes over it and ``split_into_four``, into four. The highest-gradient planes go first if
    ``max_planes`` would be exceeded. Returns detached planes (re-centred) and the index map.
    """
    K = len(planes)
    dev = planes.device
    with torch.no_grad():
        keep = planes.valid_mask() & (torch.nan_to_num(planes.radii, nan=-1.0).min(1).values > min_radius)
        n_unseen = 0
        if seen is not None:
            n_unseen = int((keep & ~seen.to(dev)).sum())
            keep &= seen.to(dev)
        base = planes.detach()[keep].recentered()
        parent = keep.nonzero().squeeze(1)
        n_pruned = int(K - keep.sum())
        n_split = 0
        if split_threshold is not None and radii_grad is not None and len(base) > 0:
            g = torch.nan_to_num(radii_grad.to(dev)[keep])
            sx, sy = g[:, 0] >= split_threshold, g[:, 1] >= split_threshold
            if not split_into_four:  # only the larger axis
                sx, sy = sx & (g[:, 0] >= g[:, 1]), sy & (g[:, 1] > g[:, 0])
            extra = sx.long() + sy.long() + (sx & sy).long()  # children - 1
            budget = max_planes - len(base)
            if int(extra.sum()) > budget:
                order = torch.argsort(g.max(1).values, descending=True)
                allowed = torch.zeros_like(sx)
                allowed[order[torch.cumsum(extra[order], 0) <= max(budget, 0)]] = True
                sx, sy = sx & allowed, sy & allowed
            split = sx | sy
            n_split = int(split.sum())
            if n_split:
                R = base.rotation()
                X, Y = R[..., 0], R[..., 1]
                rx, ry = base.radii[:, 0], base.radii[:, 2]
                # offsets along (X, Y) in units of the current radii, per child
                cx = torch.where(sx, 0.5, 0.0)
                cy = torch.where(sy, 0.5, 0.0)
                children = []
                parents_new = []
                idx = split.nonzero().squeeze(1)
                for ox, oy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                    # (ox, oy) children exist when the axis with a -1 is split (or it's the first)
                    m = split.clone()
                    if ox < 0:
                        m &= sx
                    if oy < 0:
                        m &= sy
                    i = m[idx].nonzero().squeeze(1)
                    j = idx[i]
                    c = base.center[j] + (ox * cx[j] * rx[j])[:, None] * X[j] + (oy * cy[j] * ry[j])[:, None] * Y[j]
                    nrx = torch.where(sx[j], 0.5 * rx[j], rx[j])
                    nry = torch.where(sy[j], 0.5 * ry[j], ry[j])
                    children.append(Planes(c, base.quat[j], torch.stack([nrx, nrx, nry, nry], 1)))
                    parents_new.append(parent[j])
                stay = ~split
                base = Planes.cat([base[stay]] + children)
                parent = torch.cat([parent[stay]] + parents_new)
    return base, PlaneIndexMap(parent, K, n_pruned, n_split, n_unseen)


# ------------------------------------------------------------------------------------------------
# optimization loop
# ------------------------------------------------------------------------------------------------
def _device(conf: PlaneOptConfig) -> torch.device:
    if conf.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(conf.device)


def _make_optimizer(params: list, conf: PlaneOptConfig, old: Optional[torch.optim.Adam] = None, parent=None):
    """Adam over [center, quat, radii]; with ``old`` and ``parent``, moments follow the index map."""
    opt = torch.optim.Adam(
        [
            {"params": [params[0]], "lr": conf.lr_center},
            {"params": [params[1]], "lr": conf.lr_quat},
            {"params": [params[2]], "lr": conf.lr_radii},
        ]
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
    return opt


def _call_extra(extra_loss, view, planes, it, render):
    if extra_loss is None:
        return None
    try:
        params = inspect.signature(extra_loss).parameters
        takes_render = "render" in params or any(p.kind == p.VAR_KEYWORD for p in params.values())
    except (TypeError, ValueError):
        takes_render = False
    return extra_loss(view, planes, it, render=render) if takes_render else extra_loss(view, planes, it)


def optimize_planes(
    targets: list,
    planes: Planes,
    conf: Optional[PlaneOptConfig] = None,
    extra_loss: Optional[Callable] = None,
    on_restructure: Optional[Callable] = None,
) -> tuple[Planes, dict]:
    """Optimize ``planes`` against the views' depth and normals.

    Args:
        targets: :class:`ViewTarget` list from :func:`prepare_targets` (or a list of
            :class:`~lipmap.scene.View`, loaded here).
        planes: initial planes (degenerate ones are dropped first).
        conf: :class:`PlaneOptConfig` (default: the ``fast`` preset).
        extra_loss: ``f(view, planes, iteration, render=None) -> scalar tensor or None``, added
            unweighted to ``plane_weight * decay * plane_loss``; ``planes`` are the live
            parameters (differentiable), ``render`` the :class:`RenderOutput` of this view at the
            working resolution (``render.hits[..., 0]`` = the first plane each pixel's ray meets).
            A ``render`` parameter is optional in ``f``'s signature.
        on_restructure: ``g(index_map: PlaneIndexMap)`` called after every prune/split (and the
            initial clean-up) so per-plane state kept outside can follow.

    Returns:
        (optimized :class:`Planes` on the optimization device, history dict with per-epoch
        ``loss``, ``depth``, ``normal``, ``planes``, ``pruned``, ``split``, ``seconds``).
    """
    conf = conf or PlaneOptConfig.preset("fast")
    dev = _device(conf)
    if targets and not isinstance(targets[0], ViewTarget):
        targets = prepare_targets(depth_frames(targets), conf, device=dev)
    if not targets:
        raise InputError("no view with depth and pose to optimize planes against")
    planes = planes.to(device=dev, dtype=torch.float32)
    planes, imap = prune_and_split(planes, min_radius=0.0, split_threshold=None)
    if imap.n_pruned:
        logger.warning("dropped %d degenerate planes (non-finite or non-positive radii) before optimizing", imap.n_pruned)
    if on_restructure:
        on_restructure(imap)
    params = [t.clone().requires_grad_(True) for t in planes.tensors()]
    opt = _make_optimizer(params, conf)
    n_views = len(targets)
    max_iters = conf.epochs * n_views
    split_stop = int(conf.split_stop_frac * max_iters)
    rng = np.random.default_rng(conf.seed)
    hist = {k: [] for k in ("loss", "depth", "normal", "planes", "pruned", "unseen", "split", "lambda", "seconds", "skipped")}
    it = 0
    bar = None
    if conf.progress:
        from tqdm import tqdm

        bar = tqdm(total=max_iters, desc="planes", unit="it", leave=False)
    for epoch in range(conf.epochs):
        t0 = time.time()
        K = len(params[0])
        seen = torch.zeros(K, dtype=torch.bool, device=dev)
        gsum = torch.zeros(K, 2, device=dev)
        gcnt = torch.zeros(K, device=dev)
        sums = {"loss": 0.0, "depth": 0.0, "normal": 0.0}
        n_used = skipped = 0
        for vi in rng.permutation(n_views):
            tgt = targets[vi]
            lam = lambda_schedule(it, max_iters, conf.lambda_min, conf.lambda_max)
            if conf.lr_final_frac != 1.0:
                # Adam moves each parameter by ~lr per step whatever its gradient, so edge positions
                # jitter at the lr scale; annealing lets them settle to the pixel level at the end
                f = conf.lr_final_frac ** (it / max(max_iters - 1, 1))
                for g, base in zip(opt.param_groups, (conf.lr_center, conf.lr_quat, conf.lr_radii)):
                    g["lr"] = base * f
            out = rasterize_planes(
                params[0], params[1], params[2], tgt.cam_from_world, tgt.camera.params,
                tgt.camera.width, tgt.camera.height, lam, conf.max_hits, conf.tile_size,
            )
            pl = plane_loss(out, tgt, conf)
            decay = max(math.exp(-it / max_iters), conf.decay_floor)
            live = Planes(params[0], params[1], params[2])
            extra = _call_extra(extra_loss, tgt.view, live, it, out)
            total = None if pl is None else conf.plane_weight * decay * pl[0]
            if extra is not None and torch.is_tensor(extra) and extra.requires_grad:
                total = extra if total is None else total + extra
            vis = out.visible_planes(K)
            seen |= vis
            if total is not None and torch.isfinite(total):
                opt.zero_grad(set_to_none=False)
                total.backward()
                for p in params:
                    if p.grad is not None:
                        torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
                g = params[2].grad.abs() if params[2].grad is not None else torch.zeros_like(params[2])
                gsum[:, 0] += 0.5 * (g[:, 0] + g[:, 1])
                gsum[:, 1] += 0.5 * (g[:, 2] + g[:, 3])
                gcnt += vis.float()
                opt.step()
                with torch.no_grad():
                    rec = Planes(params[0], params[1], params[2]).recentered()
                    params[0].copy_(rec.center)
                    params[2].copy_(rec.radii)
                    params[1].div_(params[1].norm(dim=1, keepdim=True).clamp(min=1e-12))
                sums["loss"] += float(total.detach())
                sums["depth"] += pl[1].get("depth", 0.0) if pl else 0.0
                sums["normal"] += pl[1].get("normal", 0.0) if pl else 0.0
                n_used += 1
            else:
                skipped += 1
            it += 1
            if bar is not None:
                bar.update(1)
                loss_value = float(total.detach()) if torch.is_tensor(total) else float("nan" if total is None else total)
                bar.set_postfix(loss=f"{loss_value:.4f}", planes=K)
        # once per epoch: prune and split (the index map carries the Adam moments along)
        radii_grad = gsum / gcnt.clamp(min=1)[:, None]
        seen_g = radii_grad[gcnt > 0].max(1).values
        if len(seen_g):
            q = torch.quantile(seen_g.float(), torch.tensor([0.5, 0.9, 0.99], device=dev)).tolist()
            hist.setdefault("radii_grad_q50_q90_q99", []).append([round(x, 4) for x in q])
        do_split = conf.split and it <= split_stop and epoch < conf.epochs - 1
        current = Planes(*(p.detach() for p in params))
        new, imap = prune_and_split(
            current,
            seen=seen if conf.prune_unseen else None,
            radii_grad=radii_grad if do_split else None,
            min_radius=conf.prune_min_radius,
            split_threshold=conf.split_grad_threshold if do_split else None,
            split_into_four=conf.split_into_four,
            max_planes=conf.max_planes,
        )
        if len(new) == 0:
            logger.warning("pruning would remove every plane; keeping the current set")
            new, imap = prune_and_split(current, min_radius=0.0, split_threshold=None)
        params_new = [t.clone().requires_grad_(True) for t in new.tensors()]
        opt = _make_optimizer(params_new, conf, old=opt, parent=imap.parent)
        params = params_new
        if on_restructure:
            on_restructure(imap)
        n = max(n_used, 1)
        hist["loss"].append(sums["loss"] / n)
        hist["depth"].append(sums["depth"] / n)
        hist["normal"].append(sums["normal"] / n)
        hist["planes"].append(len(new))
        hist["pruned"].append(imap.n_pruned)
        hist["unseen"].append(imap.n_unseen)
        hist["split"].append(imap.n_split)
        hist["lambda"].append(lambda_schedule(it - 1, max_iters, conf.lambda_min, conf.lambda_max))
        hist["seconds"].append(time.time() - t0)
        hist["skipped"].append(skipped)
        logger.debug(
            "epoch %d: loss %.4f depth %.4f normal %.4f planes %d (-%d, split %d)",
            epoch, hist["loss"][-1], hist["depth"][-1], hist["normal"][-1], len(new), imap.n_pruned, imap.n_split,
        )
    if bar is not None:
        bar.close()
    return Planes(*(p.detach() for p in params)), hist


# ------------------------------------------------------------------------------------------------
# pipeline step
# ------------------------------------------------------------------------------------------------
def fit_planes(scene, out_dir, conf: Optional[PlaneOptConfig] = None, overwrite: bool = False) -> Path:
    """Initialize and optimize planes on ``scene.mapping``; write ``planes.h5`` and ``planes.ply``.

    Skips the work when ``out_dir/planes.h5`` exists unless ``overwrite``. Returns the .h5 path.
    """
    conf = conf or PlaneOptConfig.preset("fast")
    out_dir = Path(out_dir)
    path = out_dir / "planes.h5"
    if path.exists() and not overwrite:
        logger.info("Skipping plane fitting: %s exists (overwrite=False)", path)
        return path
    logger.info("fitting planes on %s/%s (%d mapping views), preset %s", scene.dataset, scene.name, len(scene.mapping), conf.name)
    dev = _device(conf)
    t0 = time.time()
    frames = depth_frames(scene.mapping)  # loaded once, full resolution
    if not frames:
        raise InputError(f"scene {scene.name}: no mapping view has depth and a pose", scene.root)
    planes = init_planes(None, conf.init, device=dev, frames=downscale_frames(frames, conf.init.depth_downscale, conf.init.target_width))
    t_init = time.time() - t0
    targets = prepare_targets(frames, conf, device=dev)
    planes, hist = optimize_planes(targets, planes, conf)
    hist["init_seconds"] = t_init
    hist["total_seconds"] = time.time() - t0
    save_planes(path, planes, attrs={"config": conf.to_dict(), "history": hist, "scene": scene.name, "dataset": scene.dataset})
    export_planes_ply(out_dir / "planes.ply", planes)
    logger.info(
        "planes: %d after %d epochs, final loss %.4f, %.1f s (init %.1f s) -> %s",
        len(planes), conf.epochs, hist["loss"][-1] if hist["loss"] else float("nan"), hist["total_seconds"], t_init, path,
    )
    return path


def add_fit_planes_parser(subparsers):
    """``fit-planes`` subcommand (wired by the CLI owner)."""
    p = subparsers.add_parser("fit-planes", help="initialize and optimize planar primitives for a scene")
    p.add_argument("--dataset", default="synthetic")
    p.add_argument("--root", required=True)
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True, help="output folder for planes.h5 / planes.ply")
    p.add_argument("--preset", default="fast", choices=list(confs))
    p.add_argument("--epochs", type=int, default=None)
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cli_fit_planes)
    return p


def cli_fit_planes(args) -> Path:
    from ..datasets import load_scene

    scene = load_scene(args.dataset, args.root, args.scene)
    over = {} if args.epochs is None else {"epochs": args.epochs}
    return fit_planes(scene, args.out, PlaneOptConfig.preset(args.preset, **over), overwrite=args.overwrite)
