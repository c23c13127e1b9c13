"""Plane optimization settings and their named presets (``fast``, ``fast-lines``, ``paper``)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import torch

from ..presets import resolve
from .init import PlaneInitConfig
from .primitives import MAX_HITS, NEAR
from .render import TILE_SIZE, check_hit_rule, check_near


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
    # the reference code's weights (weight_mono_depth 2, weight_mono_normal 5); the paper's text writes alpha_D = 5,
    # alpha_N = 1, which no preset uses (docs/design.md)
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
    # |grad| of an axis from its two radii (the + and - sides): "mean" of the two at each step, "max" of the two at
    # each step, both then averaged over the round; or "max_of_means" (reference code): each side's |grad| averaged
    # over the round, then the larger side
    split_grad_reduce: str = "mean"
    # planes made by a split start with zeroed Adam moments (reference code: they are appended to the optimizer with
    # zeros); off: they take their parent's
    zero_moments_of_split: bool = False
    depth_loss_on_rendered: bool = False  # depth L1 only where the render has alpha > 1e-5 (reference code)
    # the normal loss as the reference codes it: both normals unit length (the composited one is alpha long) and
    # the mean over the pixels that render (alpha > 1e-5), not every pixel with a target normal
    normal_loss_normalized: bool = False
    normal_loss_on_rendered: bool = False
    # count the pixels without a target normal (zero) in the normal loss (reference code: its mask is the rendered
    # pixels alone, and there such a pixel costs 2); off: they are left out
    normal_loss_on_invalid_targets: bool = False
    normal_frame: str = "camera"  # "world" (reference): the L1 part of the normal loss is not rotation-invariant
    # "quaternion": one (w, x, y, z) per plane, renormalised after every step; "normal-inplane" (reference code): a
    # normal quaternion (w, x, y) and an in-plane one (w, z), normalised only where used (lipmap/planes/rotation.py)
    rotation: str = "quaternion"
    adam_betas: tuple = (0.9, 0.999)  # torch's default; reference (0.9, 0.99)
    adam_eps: float = 1e-8  # torch's default; reference 1e-15
    # zero Adam's moments of centre and radii after every step, keeping the step count: the reference replaces both
    # tensors when it re-centres them after each step; with its betas each moves by ~lr x the sign of its gradient
    reset_moments_on_recenter: bool = False
    # order of the views: "shuffle" (a seeded permutation per epoch) or "sequential" (reference: data_order
    # sequential, the views as given)
    view_order: str = "shuffle"
    # prune the planes no view renders: 0 = at every prune/split round, from the views that round trained on; N > 0 =
    # from a pass rendering every view, before the first step and after every N steps (reference: 1000, its
    # check_plane_vis_freq_ite), not at the rounds
    prune_unseen_every: int = 0
    split_after_rounds: int = 0  # prune/split rounds that only prune before splitting may begin (reference: 1)
    # planes each view renders: the reference's renderer skips planes whose normal faces away from the camera and
    # planes whose centre is nearer than 0.2 m (its near culling); ours renders both sides and culls nothing
    cull_back_faces: bool = False
    min_center_depth: float = 0.0  # m
    near: float = NEAR  # m, > 0: the renderer's near plane (reference: 0.1); nearer intersections are not rendered
    # which hits a pixel composites: "nearest" (its M nearest) or "reference" (its renderer's: the tile's planes by
    # their centres' depth, a hit nearer than the last one taken skipped; lipmap.planes.render.select_hits)
    hit_rule: str = "nearest"
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

    def __post_init__(self):
        check_near(self.near)  # refused when set, not thousands of iterations later in the first render
        check_hit_rule(self.hit_rule)

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
    # 6,000 iterations
    # whatever the views, lr 1e-3 with its Adam (betas 0.9 / 0.99, eps 1e-15, centre and radii moments zeroed after
    # each step), 1 cm voxels, its depth and normal losses (unit normals in the world frame, over the rendered
    # pixels), its split criterion from the second round, and its renderer's 30 contributors per pixel, back-face
    # and near-centre culling, its near plane at 0.1 m, its hit rule; its views in sequence, its split statistic (the larger side
    # of the radii's mean |grad|), split planes' moments from zero, its visibility pruning (iteration 0 and every
    # 1,000), its fusion (_paper_init). Plane loss 2 * depth + 5 * normal as the reference codes it
    # (weight_mono_depth, weight_mono_normal in its confs); the paper writes depth 5, normal 1 in Sec. 3.3 and normal 5,
    # depth 1 in appendix A (docs/design.md).
    return PlaneOptConfig(name="paper", epochs=0, iterations=6000, downscale=1,
                          depth_loss_on_rendered=True, normal_loss_normalized=True, normal_loss_on_rendered=True,
                          normal_frame="world", adam_betas=(0.9, 0.99), adam_eps=1e-15, reset_moments_on_recenter=True,
                          split_after_rounds=1, cull_back_faces=True, min_center_depth=0.2, near=0.1, max_hits=30,
                          split_grad_reduce="max_of_means", zero_moments_of_split=True,
                          normal_loss_on_invalid_targets=True, view_order="sequential", prune_unseen_every=1000,
                          rotation="normal-inplane", max_depth=10.0, hit_rule="reference", init=_paper_init())


def _paper_init() -> PlaneInitConfig:
    # The reference's fusion (GeneralDataset.get_mesh, its RGB-D confs): 1 cm voxels, 2 cm truncation, every view,
    # depth up to 10 m (depth_trunc), decimated to 10,000 planes (init_plane_num of scannetv2 / scannetpp). Its
    # volume is sparse (open3d's ScalableTSDFVolume); ours is dense, so the cap on voxels bounds the memory: 100M
    # voxels are 0.8 GB of grid (TSDF and weight, float32); a box that needs more is fused at coarser voxels.
    return PlaneInitConfig(n_planes=10000, voxel_size=0.01, trunc_voxels=2.0, max_frames=0, max_depth=10.0,
                           depth_downscale=1, max_voxels=100_000_000)


confs = {"fast": _fast(), "fast-lines": _fast_lines(), "paper": _paper()}


def select_device(conf: PlaneOptConfig) -> torch.device:
    """The torch device of ``conf.device`` ("auto" = CUDA when available, else CPU)."""
    if conf.device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(conf.device)
