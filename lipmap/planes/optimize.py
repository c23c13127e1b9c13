"""Plane optimization against depth and normal maps (LiP-Map / PlanarSplatting, plane part).

One view per iteration (seeded order), Adam on centre, quaternion and radii, plane loss
``2 * depth L1 + 5 * (normal L1 + (1 - cos))`` weighted ``10 * max(exp(-i / max_iters), 0.1)``,
re-centring after every step, and once per epoch (or every ``restructure_every`` iterations, if longer) pruning
(smallest radius <= 1.25e-3 or seen by no view) and splitting (mean |grad| of an axis's radii >= threshold). Reference-code facts are in
docs/design.md; what is ours is said where it is done.

Hook for the line loss: ``optimize_planes(..., extra_loss=f)`` adds ``f(view, planes, iteration,
render, target)`` (a scalar tensor, already weighted) to the total, with that one fixed signature; see
:func:`optimize_planes`. Pruning and
splitting go through :func:`prune_and_split`, whose :class:`PlaneIndexMap` lets callers carry
per-plane state across the change.
"""
from __future__ import annotations

import functools
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
from ..presets import resolve
from .init import LazyDepthFrames, PlaneInitConfig, init_planes, resize_nearest, working_downscale
from .io import export_planes_ply, save_planes
from .primitives import MAX_HITS, NEAR, Planes, quat_to_rotmat
from .render import TILE_SIZE, RenderOutput, lambda_schedule, rasterize_planes, resolve_backend


@dataclass
class PlaneOptConfig:
    """Plane optimization settings; build presets with :meth:`preset` (``fast``, ``paper``)."""

    name: str = "custom"
    epochs: int = 60
    # > 0: a budget of iterations (one view each) sampled over the views in epochs of len(views), as the
    # reference's max_total_iters, so the cost does not grow with the views; a run does min(epochs x views,
    # iterations), where epochs = 0 or iterations = 0 lifts that bound
    iterations: int = 0
    cache_views: int = 256  # views whose training targets stay in memory (LRU); the rest are re-read from disk
    downscale: int = 1  # optimize at 1 / downscale of the view resolution; 0 = from target_width
    target_width: int = 160  # with downscale = 0: the integer factor that brings the width closest to this
    # the last this many iterations of the budget train at a finer resolution (coarse to fine): edges settle on
    # the camera's pixels at a fraction of a fine run's cost; 0 = off
    fine_iterations: int = 0
    # their downscale; 0 = half the working one, at least 1 (7-Scenes: the camera's own 640x480), so that a larger
    # camera costs those iterations 4x the pixels, not 16x; 1 = the views' own resolution
    fine_downscale: int = 0
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
    split_grad_threshold: float = 0.2  # mean |d loss / d radius| over the round (see prune_and_split)
    split_stop_frac: float = 5000 / 6000  # no splitting after this fraction of the iterations
    # iterations between prune/split rounds, never fewer than an epoch (the paper's round); 0 = once per epoch.
    # With an iteration budget an epoch is as long as the scene has views, so few views would split twice as often.
    # Not shorter than an epoch: the split test averages a plane's radius gradient over the views of the round,
    # and over a subset of them it splits on noise (large synthetic scene, 100 views in rounds of 50: 17,000 planes)
    restructure_every: int = 0
    split_into_four: bool = True  # both axes over the threshold -> 4 children, else 2
    split_grad_reduce: str = "mean"  # |grad| of an axis from its two radii: "mean", or "max" (reference code)
    depth_loss_on_rendered: bool = False  # depth L1 only where the render has alpha > 1e-5 (reference code)
    # the normal loss as the reference codes it: both normals unit length (the composited one is alpha long) and
    # the mean over the pixels that render (alpha > 1e-5), not every pixel with a target normal
    normal_loss_normalized: bool = False
    normal_loss_on_rendered: bool = False
    normal_frame: str = "camera"  # "world" (reference): the L1 part of the normal loss is not rotation-invariant
    adam_betas: tuple = (0.9, 0.999)  # torch's default; reference (0.9, 0.99)
    adam_eps: float = 1e-8  # torch's default; reference 1e-15
    # zero Adam's moments of centre and radii after every step, keeping the step count: the reference replaces both
    # tensors when it re-centres them after each step; with its betas each moves by ~lr x the sign of its gradient
    reset_moments_on_recenter: bool = False
    split_after_rounds: int = 0  # prune/split rounds that only prune before splitting may begin (reference: 1)
    # planes each view renders: the reference's renderer skips planes whose normal faces away from the camera and
    # planes whose centre is nearer than 0.2 m (its near culling); ours renders both sides and culls nothing
    cull_back_faces: bool = False
    min_center_depth: float = 0.0  # m
    near: float = NEAR  # m: the renderer's near plane (reference: 0.1); nearer intersections are not rendered
    max_planes: int = 20000  # splitting never grows the set beyond this
    seed: int = 0
    device: str = "auto"  # "auto" = CUDA when available
    progress: bool = True
    init: PlaneInitConfig = field(default_factory=PlaneInitConfig)

    @staticmethod
    def preset(name="fast", **overrides) -> "PlaneOptConfig":
        """Preset ``name`` (or a dict ``{"preset": name, **overrides}``) with field overrides (``init`` takes a
        dict of overrides or a PlaneInitConfig)."""
        base = dict(name) if isinstance(name, dict) else {"preset": name}
        return resolve({**base, **overrides}, confs, "plane optimization", default="fast")

    def to_dict(self) -> dict:
        return asdict(self)


def _fast() -> PlaneOptConfig:
    # Tests and the demo on a CPU; each departure from the reference is why it is fast (docs/design.md).
    return PlaneOptConfig(
        name="fast",
        epochs=8,
        downscale=0,
        target_width=320,  # ~320 px: at 160 px the rendered depth was twice as far off
        lr_center=1e-2,  # 240 steps at the reference 1e-3 cannot grow 2-3 cm init radii to wall size
        lr_quat=1e-2,
        lr_radii=1e-2,
        lambda_min=300.0,  # the reference's soft start costs ~20 s per epoch on a CPU and did not help here
        split=False,  # within 8 epochs every split threshold tried made the depth worse
        init=PlaneInitConfig(n_planes=2000, voxel_size=0.02, depth_downscale=1),
    )


def _fast_lines() -> PlaneOptConfig:
    # The joint line-plane optimization on a CPU (mapping preset "fast"); see docs/design.md.
    fast = _fast()
    return replace(
        fast,
        name="fast-lines",
        epochs=0,  # no epoch bound: the budget below, whatever the number of views (as the reference)
        iterations=3600,  # line F kept rising to 72 epochs of the 50-view RedKitchen mini, which is this budget
        lr_quat=2e-3,  # 1e-2 random-walks the in-plane rotation, so edges cannot settle on lines
        lr_final_frac=0.1,  # annealed: edges settle to the pixel level at the end
        split=True,
        split_grad_threshold=0.6,  # adds planes where lines pull; 0.2 shatters the planes
        restructure_every=50,  # the 50-view mini's epoch, where the threshold was chosen, for fewer views
        init=replace(fast.init, n_planes=6000),  # more edges to align with the detected lines
        # the last quarter at twice the resolution (7-Scenes: the camera's): edges settle on the pixels held-out
        # queries see (SfM pGT, 5 matches: 32 % within 2 cm against 28; docs/design.md, "Why fast is what it is"),
        # ~80 s on 2 cores
        fine_iterations=900,
    )


def _paper() -> PlaneOptConfig:
    # The reference code (docs/design.md, "The paper, the reference code and `--preset paper`"): full resolution,
    # 6,000 iterations whatever the views, lr 1e-3 with its Adam (betas 0.9 / 0.99, eps 1e-15, centre and radii moments zeroed after
    # each step), 1 cm voxels, its depth and normal losses (unit normals in the world frame, over the rendered
    # pixels), its split criterion from the second round, and its renderer's 30 contributors per pixel, back-face
    # and near-centre culling, its near plane at 0.1 m. Plane loss 2 * depth + 5 * normal as the reference codes it
    # (the paper writes depth 5, normal 1 in Sec. 3.3 and normal 5, depth 1 in appendix A; docs/design.md).
    return PlaneOptConfig(name="paper", epochs=0, iterations=6000, downscale=1, split_grad_reduce="max",
                          depth_loss_on_rendered=True, normal_loss_normalized=True, normal_loss_on_rendered=True,
                          normal_frame="world", adam_betas=(0.9, 0.99), adam_eps=1e-15, reset_moments_on_recenter=True,
                          split_after_rounds=1, cull_back_faces=True, min_center_depth=0.2, near=0.1, max_hits=30,
                          init=PlaneInitConfig(voxel_size=0.01, depth_downscale=1))


confs = {"fast": _fast(), "fast-lines": _fast_lines(), "paper": _paper()}


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

    @functools.cached_property
    def has_targets(self) -> tuple:
        """(any valid depth, any valid normal): read from the device once per target, not once per step."""
        return bool(self.depth_valid.any()), bool(self.normal_valid.any())


def training_camera(camera, conf: PlaneOptConfig):
    """The camera a view of ``camera`` trains at under ``conf`` (``conf.downscale``, 0 = towards ``target_width``).

    The one definition of the training grid: the targets, the renders and the line term's regions all take it from
    the :class:`ViewTarget`, never from a scale factor of their own (a width ratio rounds the height differently:
    1752x1168 / 5 is 350x234, but 1168 x 350 / 1752 rounds to 233).
    """
    ds = working_downscale(conf.downscale, camera.width, conf.target_width)
    return camera if ds <= 1 else camera.scaled(1.0 / ds)


def view_target(frame, conf: PlaneOptConfig, device=None) -> ViewTarget:
    """The :class:`ViewTarget` of one :class:`~lipmap.planes.init.DepthFrame` (full-resolution depth).

    Normals come from ``view.load_normals()`` when the view has a normal map, else from the
    full-resolution depth (:func:`lipmap.normals.normals_from_depth`), then both maps are resized
    to the working resolution (:func:`training_camera`) by nearest sampling.
    """
    cam = training_camera(frame.camera, conf)
    normals = frame.view.load_normals() if getattr(frame.view, "normal_path", None) is not None else None
    if normals is None:
        step = conf.normal_step or max(2, frame.camera.width // 80)
        normals = normals_from_depth(frame.depth, frame.camera, step=step)
    depth = resize_nearest(frame.depth, cam.width, cam.height)
    normals = resize_nearest(normals, cam.width, cam.height)
    depth = np.where(np.isfinite(depth) & (depth > 0) & (depth <= conf.max_depth), depth, 0).astype(np.float32)
    normals = np.nan_to_num(normals).astype(np.float32)
    d = torch.as_tensor(depth, device=device)
    n = torch.as_tensor(normals, device=device)
    return ViewTarget(frame.view, cam, torch.as_tensor(frame.cam_from_world, dtype=torch.float32, device=device),
                      d, n, d > 0, n.norm(dim=-1) > 0.5)


def prepare_targets(frames: list, conf: PlaneOptConfig, device=None) -> list:
    """:class:`ViewTarget` per :class:`~lipmap.planes.init.DepthFrame`, all in memory (see :func:`view_target`)."""
    return [view_target(f, conf, device) for f in frames]


class TargetStore:
    """The :class:`ViewTarget` of each of ``views`` (those with depth and a pose), built from the view's files on
    first use and kept in an LRU of ``conf.cache_views``: memory does not grow with the number of views."""

    def __init__(self, views, conf: PlaneOptConfig, device=None):
        from ..frames import LRU

        self.views = list(views)
        self.frames = LazyDepthFrames(self.views)
        self._lru = LRU(lambda i: view_target(self.frames[i], conf, device), conf.cache_views)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> ViewTarget:
        return self._lru(int(i))

    def stats(self) -> dict:
        return self._lru.stats()

    def release(self) -> None:
        """Drop the cached targets (they are read again on use): the coarse ones once the fine phase begins."""
        self._lru.clear()


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
    nvalid = target.normal_valid & rendered if conf.normal_loss_on_rendered else target.normal_valid
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
def select_device(conf: PlaneOptConfig) -> torch.device:
    """The torch device of ``conf.device`` ("auto" = CUDA when available, else CPU)."""
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
    return opt


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
        if reduce == "max":
            self.grad_sum[:, 0] += torch.maximum(g[:, 0], g[:, 1])
            self.grad_sum[:, 1] += torch.maximum(g[:, 2], g[:, 3])
        else:
            self.grad_sum[:, 0] += 0.5 * (g[:, 0] + g[:, 1])
            self.grad_sum[:, 1] += 0.5 * (g[:, 2] + g[:, 3])
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
        return self.grad_sum / self.grad_count.clamp(min=1)[:, None]


def _pulls(extra) -> bool:
    """Whether an extra loss term has a gradient path to the planes."""
    return extra is not None and torch.is_tensor(extra) and extra.requires_grad


def _total_loss(pl: Optional[tuple], extra, plane_scale: float):
    """``plane_scale * plane loss + extra`` (either may be missing); None when nothing has a gradient."""
    total = None if pl is None else plane_scale * pl[0]
    if _pulls(extra):
        total = extra if total is None else total + extra
    return total


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
        if not _recenter_fused(params):
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
            n = quat_to_rotmat(params[1])[..., 2] @ R.T
            keep &= (n * c).sum(-1) < 0  # the normal points back towards the camera centre
        return keep.nonzero().squeeze(1)


def render_target(params: list, tgt: ViewTarget, lam: float, conf: PlaneOptConfig) -> RenderOutput:
    """The differentiable render of the planes ``params`` = [center, quat, radii] in ``tgt``'s training camera, with
    the culling of ``conf``; ``hits`` index ``params`` (culled planes are never hit)."""
    idx = _rendered_subset(params, tgt.cam_from_world, conf)
    p = params if idx is None else [t.index_select(0, idx) for t in params]
    out = rasterize_planes(p[0], p[1], p[2], tgt.cam_from_world, tgt.camera.params, tgt.camera.width,
                           tgt.camera.height, lam, conf.max_hits, conf.tile_size, near=conf.near)
    if idx is not None:  # subset indices -> indices of params; -1 stays -1 (the appended last entry)
        vis = None
        if out.visible is not None:
            vis = torch.zeros(len(params[0]), dtype=torch.bool, device=idx.device).index_put((idx,), out.visible)
        idx = torch.cat([idx, idx.new_full((1,), -1)])
        out = RenderOutput(out.depth, out.normal, out.alpha, idx[torch.where(out.hits >= 0, out.hits, len(idx) - 1)],
                           vis)
    return out


def _train_view(params, opt, tgt: ViewTarget, it: int, sched: Schedule, extra_loss, stats: _EpochStats):
    """One iteration on one view; returns the total loss as a 0-d tensor, not read here (None when the view has no
    loss). Nothing but the renderer's pair count waits for the device: whether the step is taken (a finite loss, and
    a plane drawn or a line term to pull) is decided there."""
    conf = sched.conf
    sched.set_lr(opt, it)
    out = render_target(params, tgt, sched.lam(it), conf)
    pl = plane_loss(out, tgt, conf)
    extra = None if extra_loss is None else extra_loss(tgt.view, Planes(params[0], params[1], params[2]), it, out, tgt)
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
    params_new = _live(new)
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


def _clean_start(planes: Planes, dev, on_restructure) -> list:
    """Drop degenerate planes before optimizing; the live parameters [center, quat, radii]."""
    planes = planes.to(device=dev, dtype=torch.float32)
    planes, imap = prune_and_split(planes, min_radius=0.0, split_threshold=None)
    if imap.n_pruned:
        logger.warning("dropped %d degenerate planes (non-finite or non-positive radii) before optimizing", imap.n_pruned)
    if on_restructure:
        on_restructure(imap)
    return _live(planes)


def _live(planes: Planes) -> list:
    """The live parameters [center, quat, radii]: contiguous copies (numpy-made planes are column-major), which the
    fused re-centring updates in place."""
    return [t.clone(memory_format=torch.contiguous_format).requires_grad_(True) for t in planes.tensors()]


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
    params = _clean_start(planes, dev, on_restructure)
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
    for epoch in range(sched.n_epochs):
        for vi in rng.permutation(len(targets))[: sched.max_iters - it]:
            if it == fine_from and isinstance(targets, TargetStore):
                targets.release()  # the coarse targets are not used again: up to cache_views of them held
            _train_view(params, opt, (fine if it >= fine_from else targets)[vi], it, sched, extra_loss, stats)
            it += 1
            visited[vi] = True
            if bar is not None:
                bar.update(1)
            if it % every and it < sched.max_iters:
                continue
            # "seen by no view" only where the round trained on every view (not so in a last round cut short by
            # the budget, or a round that is not a whole number of epochs and straddles two)
            params, opt, imap = _restructure(params, opt, stats, it, sched, hist, stats.seen if visited.all() else None,
                                             n_round)
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
    return Planes(*(p.detach() for p in params)), hist


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
