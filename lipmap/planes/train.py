"""Plane optimization against depth and normal maps (LiP-Map / PlanarSplatting, plane part): the training loop.

One view per iteration (a seeded permutation per epoch, or in sequence), Adam on centre, rotation (one quaternion, or
the reference's two) and radii, plane loss ``2 * depth L1 + 5 * (normal L1 + (1 - cos))`` weighted
``10 * max(exp(-i / max_iters), 0.1)``, re-centring after every step, and once per epoch (or every
``restructure_every`` iterations, if longer) pruning (smallest radius <= 1.25e-3, and seen by no view of the round
unless ``prune_unseen_every`` renders every view for that on its own schedule) and splitting (an axis's radii's
|grad| statistic >= threshold, ``split_grad_reduce``). Reference-code facts are in
docs/design.md; what is ours is said where it is done.

Hook for the line loss: ``optimize_planes(..., extra_loss=f)`` adds ``f(view, planes, iteration,
render, target)`` (a scalar tensor, already weighted) to the total, with that one fixed signature; see
:func:`optimize_planes`. Pruning and
splitting go through :func:`~lipmap.planes.structure.prune_and_split`, whose
:class:`~lipmap.planes.structure.PlaneIndexMap` lets callers carry per-plane state across the change.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from .. import logger
from ..errors import InputError
from .config import PlaneOptConfig, select_device
from .init import init_planes, working_downscale
from .io import export_planes_ply, save_planes
from .losses import _pulls, _total_loss, plane_loss
from .optimizer import _apply_step, _live, _make_optimizer
from .primitives import Planes, quat_to_rotmat
from .rotation import WIDTH, composed, split
from .render import RenderOutput, lambda_schedule, rasterize_planes
from .structure import prune_and_split
from .targets import TargetStore, ViewTarget


@dataclass
class Schedule:
    """Per-iteration values of the run: splat sharpness, plane-loss decay, learning-rate factor."""

    conf: PlaneOptConfig
    max_iters: int
    n_epochs: int

    @classmethod
    def of(cls, conf: PlaneOptConfig, n_views: int) -> "Schedule":
        """The run over ``n_views``: ``conf.epochs`` epochs of ``n_views`` iterations, at most ``conf.iterations``
        in all (the last epoch cut short); either bound off when 0."""
        bounds = [b for b in (conf.epochs * n_views, conf.iterations) if b > 0]
        if not bounds:
            raise InputError("plane optimization needs epochs > 0 or iterations > 0")
        total = min(bounds)
        return cls(conf, total, math.ceil(total / n_views))

    @property
    def split_stop(self) -> int:
        return int(self.conf.split_stop_frac * self.max_iters)

    def lam(self, it: int) -> float:
        return lambda_schedule(it, self.max_iters, self.conf.lambda_min, self.conf.lambda_max)

    def decay(self, it: int) -> float:
        return max(math.exp(-it / self.max_iters), self.conf.decay_floor)

    def set_lr(self, opt: torch.optim.Adam, it: int) -> None:
        # Adam moves each parameter by ~lr per step whatever its gradient, so edge positions jitter at
        # the lr scale; annealing lets them settle to the pixel level at the end
        if self.conf.lr_final_frac == 1.0:
            return
        f = self.conf.lr_final_frac ** (it / max(self.max_iters - 1, 1))
        for g, base in zip(opt.param_groups, (self.conf.lr_center, self.conf.lr_quat, self.conf.lr_radii)):
            g["lr"] = base * f


@dataclass
class _EpochStats:
    """What one prune/split round (an epoch, or ``restructure_every`` iterations if longer) gathers for pruning,
    splitting and the history."""

    seen: torch.Tensor  # (K,) bool: planes some view rendered
    grad_sum: torch.Tensor  # (K, 2) sum of mean |grad| of the x radii and of the y radii
    grad_count: torch.Tensor  # (K,) views in which each plane was visible at a step
    # sums over the steps taken, kept on the device and read once per round (float() per step would wait for it)
    loss: object = 0.0
    depth: object = 0.0
    normal: object = 0.0
    used: object = 0  # steps taken
    skipped: int = 0  # views without a loss
    dropped: object = 0  # steps the device skipped (a non-finite loss, or nothing to pull on)
    # (K, 4) sum of |grad| of each radius, for reduce "max_of_means" (the larger side is taken once, of the means)
    grad_sides: Optional[torch.Tensor] = None

    @classmethod
    def zeros(cls, K: int, device) -> "_EpochStats":
        return cls(torch.zeros(K, dtype=torch.bool, device=device), torch.zeros(K, 2, device=device),
                   torch.zeros(K, device=device))

    def add_step(self, total: torch.Tensor, parts: Optional[dict], radii_grad: Optional[torch.Tensor], vis: torch.Tensor,
                 reduce: str = "mean", taken: Optional[torch.Tensor] = None):
        """Add one step; ``taken``: a 0-d bool tensor, False where the device skipped it (None: it was taken)."""
        g = radii_grad.abs() if radii_grad is not None else torch.zeros_like(self.grad_sum[:, :1]).expand(-1, 4)
        w = None if taken is None else taken.to(self.grad_sum.dtype)
        if w is not None:
            g = g * w
        if reduce == "max_of_means":
            self.grad_sides = g if self.grad_sides is None else self.grad_sides + g
        elif reduce == "max":
            self.grad_sum[:, 0] += torch.maximum(g[:, 0], g[:, 1])
            self.grad_sum[:, 1] += torch.maximum(g[:, 2], g[:, 3])
        elif reduce == "mean":
            self.grad_sum[:, 0] += 0.5 * (g[:, 0] + g[:, 1])
            self.grad_sum[:, 1] += 0.5 * (g[:, 2] + g[:, 3])
        else:
            raise InputError(f"split_grad_reduce must be 'mean', 'max' or 'max_of_means', got {reduce!r}")
        self.grad_count += vis.float() if w is None else vis.float() * w

        def value(x):
            x = x.detach() if torch.is_tensor(x) else x
            return x if taken is None else torch.where(taken, x, 0.0)

        self.loss = self.loss + value(total)
        self.depth = self.depth + (value(parts["depth"]) if parts and "depth" in parts else 0.0)
        self.normal = self.normal + (value(parts["normal"]) if parts and "normal" in parts else 0.0)
        self.used = self.used + (1 if taken is None else w)
        if taken is not None:
            self.dropped = self.dropped + (1 - w)

    def means(self) -> dict:
        """The round's mean loss, depth and normal terms over the steps taken, and the views skipped (host floats:
        the round's one read of these sums)."""
        n = max(float(self.used), 1.0)
        return {"loss": float(self.loss) / n, "depth": float(self.depth) / n, "normal": float(self.normal) / n,
                "skipped": self.skipped + int(round(float(self.dropped)))}

    def radii_grad(self) -> torch.Tensor:
        """:math:`(K, 2)` mean |grad| per axis over the views that saw each plane."""
        s = self.grad_sum
        if self.grad_sides is not None:  # the radii are (x+, x-, y+, y-)
            g = self.grad_sides
            s = torch.stack([torch.maximum(g[:, 0], g[:, 1]), torch.maximum(g[:, 2], g[:, 3])], 1)
        return s / self.grad_count.clamp(min=1)[:, None]

    def select(self, idx: torch.Tensor) -> "_EpochStats":
        """The same round's sums for the planes ``idx`` (a pruned set's parents), the scalars kept."""
        return replace(self, seen=self.seen[idx], grad_sum=self.grad_sum[idx], grad_count=self.grad_count[idx],
                       grad_sides=None if self.grad_sides is None else self.grad_sides[idx])


def _rendered_subset(params: list, cam_from_world: torch.Tensor, conf: PlaneOptConfig) -> Optional[torch.Tensor]:
    """Indices :math:`(K',)` of the planes this view renders under the reference's culling (``conf.cull_back_faces``,
    ``conf.min_center_depth``); None when nothing is culled. A plane faces the camera or not over its whole area, so
    culling whole planes before rendering is exact."""
    if not (conf.cull_back_faces or conf.min_center_depth > 0):
        return None
    with torch.no_grad():
        R, t = cam_from_world[:3, :3].to(params[0].dtype), cam_from_world[:3, 3].to(params[0].dtype)
        c = params[0] @ R.T + t
        keep = c[:, 2] >= conf.min_center_depth
        if conf.cull_back_faces:
            n = quat_to_rotmat(composed(params[1]))[..., 2] @ R.T
            keep &= (n * c).sum(-1) < 0  # the normal points back towards the camera centre
        return keep.nonzero().squeeze(1)


def render_target(params: list, tgt: ViewTarget, lam: float, conf: PlaneOptConfig) -> RenderOutput:
    """The differentiable render of the planes ``params`` = [center, quat, radii] in ``tgt``'s training camera, with
    the culling of ``conf``; ``hits`` index ``params`` (culled planes are never hit)."""
    idx = _rendered_subset(params, tgt.cam_from_world, conf)
    params = [params[0], composed(params[1]), params[2]]
    p = params if idx is None else [t.index_select(0, idx) for t in params]
    out = rasterize_planes(p[0], p[1], p[2], tgt.cam_from_world, tgt.camera.params, tgt.camera.width,
                           tgt.camera.height, lam, conf.max_hits, conf.tile_size, near=conf.near,
                           hit_rule=conf.hit_rule)
    if idx is not None:  # subset indices -> indices of params; -1 stays -1 (the appended last entry)
        vis = None
        if out.visible is not None:
            vis = torch.zeros(len(params[0]), dtype=torch.bool, device=idx.device).index_put((idx,), out.visible)
        idx = torch.cat([idx, idx.new_full((1,), -1)])
        out = RenderOutput(out.depth, out.normal, out.alpha, idx[torch.where(out.hits >= 0, out.hits, len(idx) - 1)],
                           vis, out.hit_rule)
    return out


def _train_view(params, opt, tgt: ViewTarget, it: int, sched: Schedule, extra_loss, stats: _EpochStats):
    """One iteration on one view; returns the total loss as a 0-d tensor, not read here (None when the view has no
    loss). Nothing but the renderer's pair count waits for the device: whether the step is taken (a finite loss, and
    a plane drawn or a line term to pull) is decided there."""
    conf = sched.conf
    sched.set_lr(opt, it)
    out = render_target(params, tgt, sched.lam(it), conf)
    pl = plane_loss(out, tgt, conf)
    extra = None if extra_loss is None else extra_loss(tgt.view, _planes(params), it, out, tgt)
    total = _total_loss(pl, extra, conf.plane_weight * sched.decay(it))
    vis = out.visible_planes(len(params[0]))
    stats.seen |= vis
    if total is None:
        stats.skipped += 1
        return None
    taken = torch.isfinite(total.detach())
    if not _pulls(extra):  # the plane loss alone has no gradient where nothing was drawn
        taken = taken & vis.any()
    radii_grad = _apply_step(opt, params, total, conf.reset_moments_on_recenter, taken)
    stats.add_step(total, pl[1] if pl else None, radii_grad, vis, conf.split_grad_reduce, taken)
    return total


def _restructure(params: list, opt, stats: _EpochStats, it: int, sched: Schedule, hist: dict, seen=None,
                 n_round: int = 0):
    """Prune/split round ``n_round`` (0-based, after iteration ``it``); ``seen``: the planes some view saw, when planes
    no view saw are to be pruned now (None: not this round). Returns (params, optimizer, index map) of the new set."""
    conf = sched.conf
    radii_grad = stats.radii_grad()
    seen_g = radii_grad[stats.grad_count > 0].max(1).values
    if len(seen_g):
        q = torch.quantile(seen_g.float(), torch.tensor([0.5, 0.9, 0.99], device=seen_g.device)).tolist()
        hist.setdefault("radii_grad_q50_q90_q99", []).append([round(x, 4) for x in q])
    do_split = conf.split and n_round >= conf.split_after_rounds and it <= sched.split_stop and it < sched.max_iters
    current = _planes(params, detach=True)
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
    params_new = _carry_rotation(_live(new), params[1], imap.parent)
    fresh = imap.child if conf.zero_moments_of_split else None
    return params_new, _make_optimizer(params_new, conf, old=opt, parent=imap.parent, fresh=fresh), imap


def _prune_invisible(params: list, opt, targets, it: int, sched: Schedule, hist: dict):
    """The reference's visibility check: render every view with the current planes and prune those none renders.
    Returns (params, optimizer, index map); the index map is None when nothing was pruned."""
    conf = sched.conf
    seen = torch.zeros(len(params[0]), dtype=torch.bool, device=params[0].device)
    with torch.no_grad():
        for i in range(len(targets)):
            seen |= render_target(params, targets[i], sched.lam(it), conf).visible_planes(len(params[0]))
    n_unseen = int((~seen).sum())
    hist.setdefault("invisible_pruned", []).append([it, n_unseen])
    if n_unseen == 0 or n_unseen == len(seen):
        if n_unseen:
            logger.warning("no view renders any plane; keeping the current set")
        return params, opt, None
    new, imap = prune_and_split(_planes(params, detach=True), seen=seen, min_radius=0.0, split_threshold=None)
    params_new = _carry_rotation(_live(new), params[1], imap.parent)
    return params_new, _make_optimizer(params_new, conf, old=opt, parent=imap.parent), imap


HISTORY_KEYS = ("loss", "depth", "normal", "planes", "pruned", "unseen", "split", "lambda", "seconds", "skipped")


def _record_epoch(hist: dict, stats: _EpochStats, imap, n_planes: int, lam: float, seconds: float, epoch: int):
    m = stats.means()
    for key, value in (("loss", m["loss"]), ("depth", m["depth"]), ("normal", m["normal"]),
                       ("planes", n_planes), ("pruned", imap.n_pruned), ("unseen", imap.n_unseen),
                       ("split", imap.n_split), ("lambda", lam), ("seconds", seconds), ("skipped", m["skipped"])):
        hist[key].append(value)
    logger.debug("round %d: loss %.4f depth %.4f normal %.4f planes %d (-%d, split %d)", epoch, hist["loss"][-1],
                 hist["depth"][-1], hist["normal"][-1], n_planes, imap.n_pruned, imap.n_split)


def _planes(params: list, detach: bool = False) -> Planes:
    """The :class:`Planes` of the live parameters (the rotation composed where it is two quaternions)."""
    c, q, r = params[0], composed(params[1]), params[2]
    return Planes(c.detach(), q.detach(), r.detach()) if detach else Planes(c, q, r)


def _carry_rotation(params_new: list, rot: torch.Tensor, parent: torch.Tensor) -> list:
    """``params_new`` (from :func:`_live` of a restructured set) with the two-quaternion rotation of each plane's
    parent, where ``rot`` is one (a split's children share their parent's rotation)."""
    if rot.shape[-1] == WIDTH:
        params_new[1] = rot.detach()[parent].clone(memory_format=torch.contiguous_format).requires_grad_(True)
    return params_new


def _clean_start(planes: Planes, dev, on_restructure, rotation: str = "quaternion") -> list:
    """Drop degenerate planes before optimizing; the live parameters [center, rotation, radii]: the rotation a
    quaternion, or with ``rotation`` "normal-inplane" the reference's two (lipmap/planes/rotation.py)."""
    planes = planes.to(device=dev, dtype=torch.float32)
    planes, imap = prune_and_split(planes, min_radius=0.0, split_threshold=None)
    if imap.n_pruned:
        logger.warning("dropped %d degenerate planes (non-finite or non-positive radii) before optimizing", imap.n_pruned)
    if on_restructure:
        on_restructure(imap)
    params = _live(planes)
    if rotation == "normal-inplane":
        params[1] = split(params[1].detach()).contiguous().requires_grad_(True)
    elif rotation != "quaternion":
        raise InputError(f"rotation must be 'quaternion' or 'normal-inplane', got {rotation!r}")
    return params


ExtraLoss = Callable[[object, Planes, int, RenderOutput, ViewTarget], Optional[torch.Tensor]]


def optimize_planes(
    targets: list,
    planes: Planes,
    conf: Optional[PlaneOptConfig] = None,
    extra_loss: Optional[ExtraLoss] = None,
    on_restructure: Optional[Callable] = None,
) -> tuple[Planes, dict]:
    """Optimize ``planes`` against the views' depth and normals.

    Args:
        targets: :class:`ViewTarget` sequence: a list from :func:`prepare_targets`, a :class:`TargetStore`, or a
            list of :class:`~lipmap.scene.View` (read through a TargetStore here).
        planes: initial planes (degenerate ones are dropped first).
        conf: :class:`PlaneOptConfig` (default: the ``fast`` preset).
        extra_loss: ``f(view, planes, iteration, render, target) -> scalar tensor or None``, added unweighted to
            ``plane_weight * decay * plane_loss``; ``planes`` are the live parameters (differentiable),
            ``render`` the :class:`RenderOutput` of this view at the working resolution
            (``render.hits[..., 0]`` = the first plane each pixel's ray meets), ``target`` its
            :class:`ViewTarget` (sensor depth and normals on the same grid). The line term of the
            joint optimization is one (:class:`lipmap.mapping.supervision.LineSupervision`).
        on_restructure: ``g(index_map: PlaneIndexMap)`` called after every prune/split (and the
            initial clean-up) so per-plane state kept outside can follow.

    Returns:
        (optimized :class:`Planes` on the optimization device, history dict with per-round
        ``loss``, ``depth``, ``normal``, ``planes``, ``pruned``, ``split``, ``seconds``).
    """
    conf = conf or PlaneOptConfig.preset("fast")
    dev = select_device(conf)
    if isinstance(targets, list) and targets and not isinstance(targets[0], ViewTarget):
        targets = TargetStore(targets, conf, device=dev)
    if not targets:
        raise InputError("no view with depth and pose to optimize planes against")
    params = _clean_start(planes, dev, on_restructure, conf.rotation)
    opt = _make_optimizer(params, conf)
    sched = Schedule.of(conf, len(targets))
    fine, fine_from = _fine_targets(targets, conf, sched, dev)
    rng = np.random.default_rng(conf.seed)
    hist = {k: [] for k in HISTORY_KEYS}
    bar = _progress_bar(conf, sched.max_iters)
    every = max(conf.restructure_every, len(targets))  # iterations per prune/split round: at least an epoch
    it, n_round = 0, 0
    visited = np.zeros(len(targets), dtype=bool)  # the views this round has trained on
    t0 = time.time()
    stats = _EpochStats.zeros(len(params[0]), dev)
    if conf.view_order not in ("shuffle", "sequential"):
        raise InputError(f"view_order must be 'shuffle' or 'sequential', got {conf.view_order!r}")
    check_every = conf.prune_unseen_every

    def prune_invisible(at):
        nonlocal params, opt, stats
        params, opt, imap = _prune_invisible(params, opt, fine if fine is not None and it >= fine_from else targets, at,
                                             sched, hist)
        if imap is not None:
            stats = stats.select(imap.parent)
            if on_restructure:
                on_restructure(imap)

    if check_every > 0:
        prune_invisible(0)
    for epoch in range(sched.n_epochs):
        order = rng.permutation(len(targets)) if conf.view_order == "shuffle" else np.arange(len(targets))
        for vi in order[: sched.max_iters - it]:
            if it == fine_from and isinstance(targets, TargetStore):
                targets.release()  # the coarse targets are not used again: up to cache_views of them held
            _train_view(params, opt, (fine if it >= fine_from else targets)[vi], it, sched, extra_loss, stats)
            it += 1
            visited[vi] = True
            if bar is not None:
                bar.update(1)
            if check_every > 0 and it - 1 > 0 and (it - 1) % check_every == 0:
                prune_invisible(it - 1)  # the reference checks after the step of its iteration it - 1
            if it % every and it < sched.max_iters:
                continue
            # "seen by no view" only where the round trained on every view (not so in a last round cut short by
            # the budget, or a round that is not a whole number of epochs and straddles two)
            seen = stats.seen if visited.all() and check_every <= 0 else None
            params, opt, imap = _restructure(params, opt, stats, it, sched, hist, seen, n_round)
            visited[:] = False
            if on_restructure:
                on_restructure(imap)
            _record_epoch(hist, stats, imap, len(params[0]), sched.lam(it - 1), time.time() - t0, n_round)
            if bar is not None:  # the round's mean loss: read from the device once per round, not per step
                bar.set_postfix(loss=f"{hist['loss'][-1]:.4f}", planes=len(params[0]))
            n_round += 1
            t0 = time.time()
            stats = _EpochStats.zeros(len(params[0]), dev)
    if bar is not None:
        bar.close()
    return _planes(params, detach=True), hist


def _fine_targets(targets, conf: PlaneOptConfig, sched: Schedule, dev):
    """(finer targets, first iteration that uses them) for ``conf.fine_iterations`` at ``conf.fine_downscale``;
    (None, never) when off or when that resolution is no finer than the working one."""
    if conf.fine_iterations <= 0:
        return None, sched.max_iters
    views = getattr(targets, "views", None)
    if views is None:
        raise InputError("fine_iterations needs the views (a TargetStore or a list of views), not prepared targets")
    ds = working_downscale(conf.downscale, views[0].camera.width, conf.target_width)
    fine_ds = conf.fine_downscale or max(ds // 2, 1)
    if fine_ds >= ds:
        return None, sched.max_iters
    fine = TargetStore(views, replace(conf, downscale=fine_ds), device=dev)
    if len(fine) != len(targets):
        raise InputError(f"fine_iterations: {len(fine)} finer targets for {len(targets)} views")
    return fine, max(sched.max_iters - conf.fine_iterations, 0)


def _progress_bar(conf: PlaneOptConfig, total: int):
    if not conf.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc="planes", unit="it", leave=False)


# ------------------------------------------------------------------------------------------------
# pipeline step
# ------------------------------------------------------------------------------------------------
def planes_stamp(scene, conf: PlaneOptConfig, extra: Optional[dict] = None):
    """The :class:`~lipmap.artifacts.Stamp` of ``planes.h5``: the settings, the mapping views and ``extra``
    (what else shapes the planes, e.g. the line term and its 2D lines)."""
    from ..artifacts import Stamp, planes_code_digest, scene_key

    settings = {k: v for k, v in conf.to_dict().items() if k not in ("progress", "device", "name")}
    return Stamp("planes", {"planes": settings, "scene": scene_key(scene), "code": planes_code_digest(), **(extra or {})})


def fit_planes(scene, out_dir, conf: Optional[PlaneOptConfig] = None, extra_loss: Optional[ExtraLoss] = None,
               stamp_extra: Optional[dict] = None, overwrite: bool = False) -> Path:
    """Initialize and optimize planes on ``scene.mapping``; write ``planes.h5`` and ``planes.ply``.

    Args:
        extra_loss: added to the plane loss (see :func:`optimize_planes`); the mapping passes the line term.
        stamp_extra: settings of ``extra_loss`` recorded in the stamp (see :func:`planes_stamp`).

    Reuses ``out_dir/planes.h5`` when the same settings made it (:func:`lipmap.artifacts.reuse`).
    Returns the .h5 path.
    """
    from ..artifacts import reuse

    conf = conf or PlaneOptConfig.preset("fast")
    path = Path(out_dir) / "planes.h5"
    stamp = planes_stamp(scene, conf, stamp_extra)
    if reuse(path, stamp, overwrite, "plane optimization"):
        return path
    logger.info("fitting planes on %s/%s (%d mapping views), preset %s", scene.dataset, scene.name, len(scene.mapping), conf.name)
    dev = select_device(conf)
    t0 = time.time()
    targets = TargetStore(scene.mapping, conf, device=dev)  # read from disk as needed: memory bounded
    if not len(targets):
        raise InputError(f"scene {scene.name}: no mapping view has depth and a pose", scene.root)
    planes = init_planes(scene.mapping, conf.init, device=dev)
    t_init = time.time() - t0
    planes, hist = optimize_planes(targets, planes, conf, extra_loss=extra_loss)
    hist["target_cache"] = targets.stats()
    hist["init_seconds"] = t_init
    hist["total_seconds"] = time.time() - t0
    save_planes(path, planes, attrs={"config": conf.to_dict(), "history": hist, "scene": scene.name, "dataset": scene.dataset},
                stamp=stamp)
    export_planes_ply(Path(out_dir) / "planes.ply", planes)
    logger.info(
        "planes: %d after %d prune/split rounds, final loss %.4f, %.1f s (init %.1f s) -> %s",
        len(planes), len(hist["loss"]), hist["loss"][-1] if hist["loss"] else float("nan"), hist["total_seconds"], t_init, path,
    )
    return path
