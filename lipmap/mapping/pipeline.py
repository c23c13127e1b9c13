"""Mapping step: posed RGB-D views -> ``linemap.h5`` (+ ``linemap.ply``, ``planes.ply``), hloc-style.

``map_scene(scene, out_dir, conf)`` runs, skipping what its artifacts already hold:
    lines2d.h5      2D lines of the mapping views (LSD, or imported with ``lines_source``)
    planes.h5       planar primitives after the joint line-plane optimization (method ``lipmap``)
    linemap.h5      3D lines + tracks (+ the planes and edge->line table the line query needs)
Method ``lift`` back-projects each 2D line with depth instead (the paper's Fig. 1 baseline).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import logger
from ..errors import InputError
from .extract import ExtractConfig, build_tracks, depth_residuals, extract_observations, merge_edges


@dataclass
class MappingConfig:
    preset: str = "fast"
    lines: str = "lsd"  # lipmap.lines2d preset
    planes: str = "fast-lines"  # lipmap.planes.optimize preset
    # Line term: paper alpha_L = 0.1 and the reference's loss 0.5 * D_euc + max D_ort. Measured with
    # "fast-lines" (line F@5cm on room-s0 / RedKitchen mini, edge lines only, 24 epochs unless said):
    # D_euc drags every edge towards the ends of short fragments (RedKitchen lines: median 30 px);
    # dropping it and raising the weight to 0.3: RedKitchen F 0.176 -> 0.195. With plain pixel
    # distances, weight 0.5 wins on the synthetic room (F 0.326 -> 0.359 at 72 epochs) but on RedKitchen
    # bends planes off the surface (PREC@5cm 0.80 -> 0.51): a texture line inside a plane is assigned to
    # that plane's nearest edge, tens of pixels away, and drags it; even at weight 0.3, 27 % of the
    # RedKitchen pixels ended > 5 cm off the sensor depth (12 % for planes fitted without lines).
    # The robust loss (robust_scale 2 px: the pull of an edge 20 px away is 1/11 of a close one's)
    # keeps the planes where the depth puts them (13 % at weight 1, 16 % at 2) and lets the weight
    # rise: full maps (edges + on-plane lines), F@5cm / R@50mm at weights 0.3 / 1 / 2:
    # room-s0 0.390 / 0.419 / 0.448, 446 / 547 / 637; RedKitchen 0.739 / 0.724 / 0.696, 418 / 417 / 419.
    line_weight: float = 1.0
    pixels_per_line: int = 1
    group_loss: bool = False
    endpoint_weight: float = 0.0  # D_euc weight in the line loss (0.5: reference code)
    robust_scale: float = 2.0  # px (full resolution); > 0: robust line loss (losses.robust_px); 0: paper
    # Detections that no plane edge explains (texture, and lines inside a surface: most of them in real
    # rooms) lifted onto the optimized planes with the ``lift`` procedure (the preset in field ``lift``), depth ray
    # cast from the planes. False = the paper's output, plane edges only (RedKitchen mini, `lipmap-loc map`:
    # 334 edge lines, F@5cm 0.370, R@50mm 121; with on-plane lines 3411 lines, F 0.793, R@50mm 518).
    on_plane_lines: bool = True
    # On-plane lines take the input depth where the planes are more than this far from it (metres; 0 = plane
    # depth alone): on clutter no plane models, the planes sit a median 4.7 cm off the sensor depth
    # (RedKitchen). RedKitchen mini F@5cm / R@50mm at 0 / 1 / 2 / 3 / 5 cm (with the paper's extraction
    # thresholds): 0.716 / 0.785 / 0.785 / 0.786 / 0.778, 429 / 462 / 464 / 474 / 470; room-s0 (exact
    # depth) 0.428 -> 0.439 at 3 cm. Noisy depth (synthetic preset small-noisy-depth): 0 is as good.
    plane_depth_tol: float = 0.03
    # Extraction: the paper's 1 px / 0.01 rad (ExtractConfig defaults, preset "paper") assume planes trained at
    # full resolution to convergence; "fast" trains RedKitchen at half resolution, where 1 full-res px is half
    # a training pixel. 2 px / 0.02 rad on the same planes, full map (plane edges) F@5cm, R@50mm:
    # RedKitchen 0.786 -> 0.793 (edges 0.239 -> 0.370; 179 -> 334 edge lines), 474 -> 518; room-s0
    # 0.439 -> 0.462 (0.351 -> 0.403), 581 -> 639; room-s1 0.444 -> 0.461; noisy room-s0 0.425 -> 0.446.
    # 3 px / 0.03 rad gains less again and costs edge precision (RedKitchen edges PREC 0.933 / 0.921 / 0.901).
    extract: ExtractConfig = field(default_factory=lambda: ExtractConfig(max_dist=2.0, max_angle=0.02))
    lift: str = "lift-merge-loose"  # lipmap.lift preset: method "lift", and the on-plane lines of "lipmap"
    seed: int = 0


confs = {
    # CPU line mapping: RedKitchen mini (50 views) in ~5 min on 2 cores
    "fast": MappingConfig(),
    # tests, notebooks and demos on small scenes: 8 epochs of the plain "fast" plane preset
    "quick": MappingConfig(preset="quick", planes="fast"),
    # the paper and its reference code
    "paper": MappingConfig(preset="paper", planes="paper", line_weight=0.1, endpoint_weight=0.5, robust_scale=0.0,
                           on_plane_lines=False, extract=ExtractConfig()),
}


def get_conf(conf) -> MappingConfig:
    if conf is None:
        return confs["fast"]
    if isinstance(conf, str):
        if conf not in confs:
            raise InputError(f"unknown mapping preset {conf!r}; choose one of {', '.join(confs)}")
        return confs[conf]
    if isinstance(conf, dict):
        return replace(confs[conf.get("preset", "fast")], **{k: v for k, v in conf.items() if k != "preset"})
    return conf


def _lines_by_view(lines_h5: Path, views) -> dict:
    from ..lines2d import load_lines

    return {v.name: load_lines(lines_h5, v.name) for v in views}


def detect_or_import_lines(views, out_dir: Path, conf: MappingConfig, lines_source=None, overwrite=False) -> Path:
    from ..lines2d import detect_lines, import_lines

    out = out_dir / "lines2d.h5"
    if lines_source is not None:
        return import_lines(views, lines_source, out, overwrite=overwrite)
    return detect_lines(views, out, conf.lines, overwrite=overwrite)


def fit_planes_with_lines(scene, lines_by_view: dict, out_dir: Path, conf: MappingConfig, overwrite=False):
    """Joint line-plane optimization; writes/reads ``planes.h5`` and ``planes.ply``. Returns Planes."""
    from ..planes import io as pio
    from ..planes.init import depth_frames, downscale_frames, init_planes
    from ..planes.optimize import PlaneOptConfig, _device, optimize_planes, prepare_targets
    from .supervision import LineSupervision

    planes_h5 = out_dir / "planes.h5"
    if planes_h5.exists() and not overwrite:
        logger.info("Skipping plane optimization: %s exists.", planes_h5)
        return pio.load_planes(planes_h5)
    pconf = PlaneOptConfig.preset(conf.planes, seed=conf.seed)
    dev = _device(pconf)
    frames = depth_frames(scene.mapping)
    if not frames:
        raise InputError(f"scene {scene.name}: no mapping view has depth and a pose", scene.root)
    t0 = time.time()
    planes = init_planes(None, pconf.init, device=dev, frames=downscale_frames(frames, pconf.init.depth_downscale))
    t_init = time.time() - t0
    targets = prepare_targets(frames, pconf, device=dev)
    sup = LineSupervision(lines_by_view, weight=conf.line_weight, pixels_per_line=conf.pixels_per_line,
                          use_group=conf.group_loss, seed=conf.seed,
                          endpoint_weight=conf.endpoint_weight, robust_scale=conf.robust_scale)
    planes, history = optimize_planes(targets, planes, pconf, extra_loss=sup)
    history["init_seconds"] = t_init
    history["total_seconds"] = time.time() - t0
    pio.save_planes(planes_h5, planes, attrs={"config": pconf.to_dict(), "mapping": asdict(conf), "history": history,
                                              "scene": scene.name, "dataset": scene.dataset})
    pio.export_planes_ply(out_dir / "planes.ply", planes)
    from ..testing import fault_point

    fault_point("planes")
    logger.info("planes: %d after %d epochs in %.1f s (init %.1f s)", len(planes), pconf.epochs,
                history["total_seconds"], t_init)
    return planes


def lipmap_linemap(scene, planes, lines_by_view: dict, conf: MappingConfig, depth_by_view=None):
    """Extraction, merging and tracks from optimized planes -> LineMap (with planes and edge_line)."""
    from ..linemap import LineMap

    planes = planes.detach()
    corners = planes.corners().cpu().numpy().astype(np.float64)
    obs = extract_observations(corners, scene.mapping, lines_by_view, conf.extract)
    lines, obs_line, edge_line = merge_edges(corners, obs, conf.extract)
    tracks_arr = build_tracks(lines, scene.mapping, lines_by_view, conf.extract, depth_by_view)
    # evidence from extraction counts too (the pixel votes that produced the line)
    ext = np.stack([obs_line, obs["view"], obs["line"]], 1)
    ext = ext[ext[:, 0] >= 0]
    tracks_arr = np.unique(np.concatenate([tracks_arr, ext]).astype(np.int64), axis=0) if len(ext) else tracks_arr
    tracks = [[] for _ in range(len(lines))]
    for l, vi, di in tracks_arr:
        v = scene.mapping[vi]
        tracks[l].append((v.name, int(di), lines_by_view[v.name][di]))
    p = planes.numpy()
    plane_dict = {"center": p["center"], "quaternion": p["quat"], "radii": p["radii"], "corners": corners,
                  "edge_line": edge_line}
    meta = {"method": "lipmap", "config": json.loads(json.dumps(asdict(conf), default=str)),
            "n_observations": int(len(obs["plane"])), "n_planes": int(len(planes))}
    lm = LineMap(lines, tracks, planes=plane_dict, metadata=meta)
    tol = conf.extract.max_depth_residual
    if tol > 0 and depth_by_view and len(lm):
        res = depth_residuals(lines, tracks_arr, scene.mapping, depth_by_view)
        keep = ~(res > tol)  # NaN (no depth evidence) keeps the line
        logger.info("depth check: %d of %d lines within %.0f mm of the sensor depth", keep.sum(), len(keep), tol * 1e3)
        lm = lm.subset(keep)
        lm.metadata["n_depth_rejected"] = int((~keep).sum())
    lm.metadata["n_edge_lines"] = len(lm)
    if conf.on_plane_lines:
        lm = _add_on_plane_lines(lm, scene, corners, lines_by_view, conf, depth_by_view)
    return lm


def _add_on_plane_lines(edges, scene, corners, lines_by_view: dict, conf: MappingConfig, depth_by_view=None):
    """``edges`` followed by the detections no edge line explains, lifted onto the planes (onto the input
    depth where the planes do not model it, ``conf.plane_depth_tol``)."""
    from ..lift import lift_linemap
    from ..linemap import LineMap
    from .assign import PlaneRaycaster, plane_depth, plane_or_input_depth

    explained = {}
    for t in edges.tracks:
        for o in t:
            explained.setdefault(o.image_name, []).append(o.line2d_index)
    caster = PlaneRaycaster(corners)
    logger.info("lifting the detections no plane edge explains onto the planes")
    depth_by_view = depth_by_view or {}

    def depth_of(v):
        return plane_or_input_depth(plane_depth(caster, v), depth_by_view.get(v.name), conf.plane_depth_tol)

    onp = lift_linemap(scene.mapping, lines_by_view, conf.lift, depth_of=depth_of, skip=explained)
    meta = {**edges.metadata, "n_on_plane_lines": len(onp)}
    # edge lines keep indices 0..n_edge-1, so the planes' edge -> line table stays valid
    return LineMap(np.concatenate([edges.lines, onp.lines]), list(edges.tracks) + list(onp.tracks),
                   np.concatenate([edges.supports, onp.supports]), edges.planes, meta)


def edge_line_mask(lm) -> np.ndarray:
    """(N,) bool: the lines of a ``lipmap`` map that are plane edges (the paper's output); the rest
    are detections lifted onto the planes (``MappingConfig.on_plane_lines``)."""
    mask = np.zeros(len(lm), dtype=bool)
    if lm.planes is not None and "edge_line" in lm.planes:
        el = np.asarray(lm.planes["edge_line"]).ravel()
        mask[el[el >= 0]] = True
    return mask


def map_scene(scene, out_dir, conf=None, method: str = "lipmap", lines_source=None, overwrite: bool = False) -> Path:
    """Build the line map of ``scene`` in ``out_dir``; returns the path of ``linemap.h5``."""
    from ..linemap import LineMap

    conf = get_conf(conf)
    if method not in ("lipmap", "lift"):
        raise InputError(f"unknown mapping method {method!r}; choose lipmap or lift")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    out = out_dir / "linemap.h5"
    if out.exists() and not overwrite:
        logger.info("Skipping mapping: %s exists.", out)
        return out
    t0 = time.time()
    timings = {}
    lines_h5 = detect_or_import_lines(scene.mapping, out_dir, conf, lines_source, overwrite)
    lines_by_view = _lines_by_view(lines_h5, scene.mapping)
    timings["lines2d_s"] = time.time() - t0
    if method == "lift":
        from ..lift import lift_linemap

        t = time.time()
        lm = lift_linemap(scene.mapping, lines_h5, conf.lift)
        timings["lift_s"] = time.time() - t
    else:
        t = time.time()
        planes = fit_planes_with_lines(scene, lines_by_view, out_dir, conf, overwrite)
        timings["optimize_s"] = time.time() - t
        t = time.time()
        depth = {v.name: v.load_depth() for v in scene.mapping if v.depth_path is not None}
        lm = lipmap_linemap(scene, planes, lines_by_view, conf, depth)
        timings["extract_s"] = time.time() - t
    timings["total_s"] = time.time() - t0
    lm.metadata.update({"scene": scene.name, "dataset": scene.dataset, "pose_source": scene.pose_source,
                        "timings": timings, "method": method})
    lm.save(out)
    lm.to_ply(out_dir / "linemap.ply")
    try:
        from ..viz import render_linemap_views

        render_linemap_views(lm, scene, out_dir)
    except Exception as e:  # noqa: BLE001 - a failed picture must not lose the map
        logger.warning("Could not render the line map: %s", e)
    n_img = lm.supports[:, 0] if len(lm) else np.zeros(0)
    logger.info("Mapped %s with %s: %d lines (median %.0f views each) in %.1f s -> %s", scene.name, method, len(lm),
                np.median(n_img) if len(n_img) else 0, timings["total_s"], out)
    return out
