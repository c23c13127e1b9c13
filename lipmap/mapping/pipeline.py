"""Mapping step: posed RGB-D views -> ``linemap.h5`` (+ ``linemap.ply``, ``planes.ply``, ``linemap.html``), hloc-style.

``map_scene(scene, out_dir, conf)`` runs, skipping what its artifacts already hold:
    lines2d.h5      2D lines of the mapping views (LSD, or imported with ``lines_source``)
    planes.h5       planar primitives after the joint line-plane optimization (method ``lipmap``)
    linemap.h5      3D lines + tracks (+ the planes and edge->line table the line query needs), merged as
                    ``extract.merge`` says (metadata "map": "merged", or "unmerged" for merge "none")
    linemap_unmerged.h5  with ``write_unmerged``: the same map with one line per accepted plane edge
Method ``lift`` back-projects each 2D line with depth instead (the paper's Fig. 1 baseline).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from .. import geometry as geo
from .. import logger
from ..artifacts import Stamp, mapping_code_digest, reuse, scene_key, variant_dir
from ..errors import InputError
from ..linemap import edge_line_mask  # noqa: F401 - its home is the artifact; kept importable from here
from ..presets import resolve
from .aggregate import AggregateConfig, aggregate_linemap
from .extract import ExtractConfig, add_tracks, depth_residuals, extract_observations, merge_edges, verify_tracks
from .joint import fit_planes_with_lines, line_supervision, lines_settings, planes_variant_dir  # noqa: F401 - importable from here
from .keyframes import KeyframeConfig, keyframe_views
from .refine import RefineConfig, refine_linemap


@dataclass
class MappingConfig:
    """Line mapping settings; named presets in :data:`confs` (figures behind each default:
    ``docs/design.md``, "Why `fast` is what it is", and ``benchmarks/results/``)."""

    preset: str = "fast"
    lines: str = "lsd"  # lipmap.lines2d preset
    planes: object = "fast-lines"  # lipmap.planes.config preset name, or {"preset": name, **overrides}
    line_weight: float = 3.0  # paper alpha_L 0.1; the robust loss below lets a higher weight help without bending planes
    pixels_per_line: int = 0  # every region pixel, each (line, first-hit plane) pair once (reference: 1 sampled pixel)
    group_loss: bool = False  # the paper's group loss; off in the reference code, ~1.6x the time for little gain
    endpoint_weight: float = 0.0  # D_euc weight (reference 0.5): it drags edges to the ends of short fragments
    robust_scale: float = 2.0  # px (full resolution), 0 = paper: an edge far from its line is usually another surface's
    max_assign_frac: float = 0.1  # skip assignments whose edge is > this x image size away (0: reference, none)
    euc_inside_only: bool = False  # D_euc averaged over the endpoints inside the image (reference; moot without D_euc)
    # each region pixel's plane is the first rectangle its ray meets (paper, reference); off: the render's nearest
    # splat, whose fall-off reaches past the rectangle's edge onto the surface behind
    hard_first_hit: bool = True
    # a pixel in several lines' 1-pixel regions supervises the nearest line only (reference: its attraction field gives
    # each pixel one line); off: each line that claims it
    one_line_per_pixel: bool = False
    # method lipmap: also write linemap_unmerged.h5, one line per accepted plane edge (extract.merge "none"), beside
    # the merged linemap.h5, as the reference writes both
    write_unmerged: bool = False
    # m: the line term pulls a plane only where it lies this close to the sensor depth (0: the paper); without it
    # the term holds planes floating in front of the surface, whose edges fit lines in a few views
    line_depth_gate: float = 0.1
    on_plane_lines: bool = True  # lift the detections no plane edge explains onto the planes (ours, not the paper's)
    plane_depth_tol: float = 0.03  # m: on-plane lines take the input depth where the planes are farther from it (clutter)
    # (px, rad): a detection an edge tracks stays out of the on-plane lines only when the edge projects this close to
    # it; () = every detection an edge tracks. Loose track gates claim neighbouring detections that are other lines
    explain_gate: tuple = ()
    # 3 px / 0.03 rad: "fast" trains at half resolution, where the paper's 1 px is half a training pixel
    extract: ExtractConfig = field(default_factory=lambda: ExtractConfig(max_dist=3.0, max_angle=0.03))
    lift: str = "lift-merge-loose"  # lipmap.lift preset: method "lift", and the on-plane lines of "lipmap"
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)  # the views a map is built from
    # every line refined against the mapping views that see it, then tracked again: a plane's edge fits its detections
    # only as well as the plane fits the depth, an on-plane line carries one view's depth
    # (docs/design.md, "Why fast is what it is")
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(enabled=True, lines="all"))
    # lines that share detections merged, each spanning its track's detections (ours; lipmap/mapping/aggregate.py);
    # off: the mapping metrics gain and the weak queries of the held-out split lose
    # (docs/design.md, "Why fast is what it is")
    aggregate: AggregateConfig = field(default_factory=AggregateConfig)
    seed: int = 0


confs = {
    # CPU line mapping: RedKitchen mini (50 views) in ~5 min on 2 cores
    "fast": MappingConfig(),
    # tests, notebooks and demos on small scenes: 8 epochs of the plain "fast" plane preset
    "quick": MappingConfig(preset="quick", planes="fast", refine=RefineConfig(enabled=False)),
    # the paper and its reference code (docs/design.md, "The paper, the reference code and `--preset paper`"); where
    # the paper's text is silent or differs, the reference: the line loss as coded (0.5 * D_euc + max D_ort, group loss off,
    # D_euc over the endpoints inside the image), one sampled pixel per line and iteration, hard first hits,
    # extraction on the mean of the endpoint distances, every view, no assignment filter and no minimum line length
    "paper": MappingConfig(preset="paper", planes="paper", line_weight=0.1, pixels_per_line=1, endpoint_weight=0.5,
                           robust_scale=0.0, max_assign_frac=0.0, euc_inside_only=True, hard_first_hit=True,
                           on_plane_lines=False, line_depth_gate=0.0, one_line_per_pixel=True,
                           extract=ExtractConfig(dist_reduce="mean", min_length=0.0, exclusive_pixels=True,
                                                 global_rule="reference"), write_unmerged=True, refine=RefineConfig(enabled=False),
                           keyframes=KeyframeConfig(min_translation=0.0, min_rotation_deg=0.0, max_frame_gap=0)),
}

METHODS = ("lipmap", "lift")
UNMERGED = "linemap_unmerged.h5"  # beside linemap.h5, with MappingConfig.write_unmerged


def get_conf(conf=None) -> MappingConfig:
    """A :class:`MappingConfig` from a preset name, a dict of overrides (``{"preset": ..., **fields}``) or itself."""
    return resolve(conf, confs, "mapping", default="fast")


def mapping_stamp(scene, conf=None, method: str = "lipmap", lines_source=None) -> Stamp:
    """The :class:`~lipmap.artifacts.Stamp` of the ``linemap.h5`` that :func:`map_scene` would build."""
    conf = get_conf(conf)
    settings = {"method": method, "lines": lines_settings(conf, lines_source), "scene": scene_key(scene),
                "code": mapping_code_digest()}
    if method == "lift":
        from ..lift import get_conf as lift_conf

        settings["lift"] = asdict(lift_conf(conf.lift))
        settings["keyframes"] = asdict(conf.keyframes)  # lift maps the keyframes too
    else:
        from ..planes.config import PlaneOptConfig

        settings["mapping"] = asdict(conf)
        settings["planes"] = {k: v for k, v in PlaneOptConfig.preset(conf.planes, seed=conf.seed).to_dict().items()
                              if k not in ("progress", "device")}
    return Stamp("linemap", settings)


def map_variant_dir(scene_dir, scene, conf=None, method: str = "lipmap", lines_source=None) -> Path:
    """``scene_dir/map-<method>-<preset>-<digest>``: where a pipeline keeps this variant of the map."""
    conf = get_conf(conf)
    return variant_dir(scene_dir, f"map-{method}-{conf.preset}", mapping_stamp(scene, conf, method, lines_source))


def _lines_by_view(lines_h5: Path, views) -> dict:
    from ..lines2d import load_lines

    return {v.name: load_lines(lines_h5, v.name) for v in views}


def detect_or_import_lines(views, out_dir: Path, conf: MappingConfig, lines_source=None, overwrite=False) -> Path:
    from ..lines2d import detect_lines, import_lines

    out = out_dir / "lines2d.h5"
    if lines_source is not None:
        return import_lines(views, lines_source, out, overwrite=overwrite)
    return detect_lines(views, out, conf.lines, overwrite=overwrite)


def lipmap_linemap(scene, planes, lines_by_view: dict, conf: MappingConfig, depth_by_view=None):
    """Extraction, merging and tracks from optimized planes -> LineMap (with planes and edge_line).

    Every line's track holds the detections the track builder matches in every mapping view that sees it past the
    planes (:func:`~lipmap.mapping.extract.add_tracks`), and those that produced it (extraction votes, or the
    lifted detection) where they agree with the finished line by the same test
    (:func:`~lipmap.mapping.extract.verify_tracks`).
    """
    from ..linemap import LineMap
    from .assign import PlaneRaycaster

    planes = planes.detach()
    corners = planes.corners().cpu().numpy().astype(np.float64)
    caster = PlaneRaycaster(corners)
    obs = extract_observations(corners, scene.mapping, lines_by_view, conf.extract)
    lines, obs_line, edge_line = merge_edges(corners, obs, conf.extract)
    # the evidence of extraction: the detections whose pixels voted for the line
    ext = np.unique(np.stack([obs_line, obs["view"], obs["line"]], 1), axis=0)
    tracks = [[] for _ in range(len(lines))]
    for l, vi, di in ext[ext[:, 0] >= 0]:
        v = scene.mapping[vi]
        tracks[l].append((v.name, int(di), lines_by_view[v.name][di]))
    p = planes.numpy()
    plane_dict = {"center": p["center"], "quaternion": p["quat"], "radii": p["radii"], "corners": corners,
                  "edge_line": edge_line}
    meta = {"method": "lipmap", "config": json.loads(json.dumps(asdict(conf), default=str)),
            "n_observations": int(len(obs["plane"])), "n_planes": int(len(planes))}
    lm = add_tracks(LineMap(lines, tracks, planes=plane_dict, metadata=meta), scene.mapping, lines_by_view,
                    conf.extract, caster)
    if conf.refine.enabled and conf.refine.lines in ("edges", "all"):
        lm = refine_linemap(lm, scene.mapping, lines_by_view, conf.refine, caster)
        lm = add_tracks(lm, scene.mapping, lines_by_view, conf.extract, caster)
    lm = _depth_check(lm, scene, conf, depth_by_view)
    lm.metadata["n_edge_lines"] = n_edges = len(lm)
    if conf.on_plane_lines:
        lm = _add_on_plane_lines(lm, scene, corners, lines_by_view, conf, depth_by_view)
        onp = np.arange(n_edges, len(lm))
        if conf.refine.lines in ("on-plane", "all"):
            lm = refine_linemap(lm, scene.mapping, lines_by_view, conf.refine, caster, which=onp)
        lm = add_tracks(lm, scene.mapping, lines_by_view, conf.extract, caster, which=onp)
    lm = aggregate_linemap(lm, scene.mapping, conf.aggregate, depth_by_view)
    return verify_tracks(lm, scene.mapping, conf.extract)


def _depth_check(lm, scene, conf: MappingConfig, depth_by_view):
    """Drop lines whose tracked views' sensor depth disagrees (``ExtractConfig.max_depth_residual``; 0: off)."""
    tol = conf.extract.max_depth_residual
    if not (tol > 0 and depth_by_view and len(lm)):
        return lm
    index = {v.name: i for i, v in enumerate(scene.mapping)}
    rows = np.array([(l, index[o.image_name], o.line2d_index) for l, t in enumerate(lm.tracks) for o in t], dtype=np.int64)
    res = depth_residuals(lm.lines, rows.reshape(-1, 3), scene.mapping, depth_by_view)
    keep = ~(res > tol)  # NaN (no depth evidence) keeps the line
    logger.info("depth check: %d of %d lines within %.0f mm of the sensor depth", keep.sum(), len(keep), tol * 1e3)
    lm = lm.subset(keep)
    lm.metadata["n_depth_rejected"] = int((~keep).sum())
    return lm


def explained_detections(edges, views, gate: tuple = ()) -> dict:
    """{view name: indices of the detections that the lines ``edges`` explain}: every detection in their tracks, or
    with ``gate`` = (px, rad) those the line's projection lies within px (both endpoints) and rad of."""
    rows = [(l, o) for l, t in enumerate(edges.tracks) for o in t]
    if gate and rows:
        max_px, max_rad = (float(x) for x in gate)
        by_view = {}
        for i, (_, o) in enumerate(rows):
            by_view.setdefault(o.image_name, []).append(i)
        view_of = {v.name: v for v in views}
        keep = np.zeros(len(rows), bool)
        for name, idx in by_view.items():
            v = view_of[name]
            proj, valid = geo.project_segments(edges.lines[[rows[i][0] for i in idx]], v.cam_from_world, v.camera)
            det = np.stack([rows[i][1].segment for i in idx])
            with np.errstate(invalid="ignore"):
                keep[idx] = valid & (geo.angle_distance(proj, det) < max_rad) & (geo.perpendicular_distance(proj, det) < max_px)
        rows = [r for r, k in zip(rows, keep) if k]
    explained = {}
    for _, o in rows:
        explained.setdefault(o.image_name, []).append(o.line2d_index)
    return explained


def _add_on_plane_lines(edges, scene, corners, lines_by_view: dict, conf: MappingConfig, depth_by_view=None):
    """``edges`` followed by the detections no edge line explains, lifted onto the planes (onto the input
    depth where the planes do not model it, ``conf.plane_depth_tol``)."""
    from ..lift import lift_linemap
    from ..linemap import LineMap
    from .assign import PlaneRaycaster, plane_depth, plane_or_input_depth

    explained = explained_detections(edges, scene.mapping, conf.explain_gate)
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


def map_scene(scene, out_dir, conf=None, method: str = "lipmap", lines_source=None, overwrite: bool = False,
              checkpoint: Optional[Callable[[str], None]] = None, planes_root=None) -> Path:
    """Build the line map of ``scene`` in ``out_dir``; returns the path of ``linemap.h5``.

    Reuses ``out_dir/linemap.h5`` when the same settings and inputs made it; stops with
    :class:`~lipmap.artifacts.StaleArtifactError` naming both settings when others did (a pipeline that
    keeps several variants maps each into :func:`map_variant_dir`). ``checkpoint(event)`` is called after
    each artifact is written (``"lines2d"``, ``"planes"``, ``"linemap"``): progress, or fault injection in tests.
    ``planes_root``: keep ``planes.h5`` in its own folder there (:func:`~lipmap.mapping.joint.planes_variant_dir`),
    shared by the maps that differ only after the plane optimization; default ``out_dir``.
    """
    from dataclasses import replace

    from ..frames import depth_maps

    conf = get_conf(conf)
    if method not in METHODS:
        raise InputError(f"unknown mapping method {method!r}; choose one of {', '.join(METHODS)}")
    out_dir = Path(out_dir)
    out = out_dir / "linemap.h5"
    stamp = mapping_stamp(scene, conf, method, lines_source)
    unmerged = (out_dir / UNMERGED) if conf.write_unmerged and method == "lipmap" else None
    unmerged_stamp = Stamp("linemap", {**stamp.settings, "map": "unmerged"})
    if reuse(out, stamp, overwrite, "mapping") and (unmerged is None or reuse(unmerged, unmerged_stamp, False, "mapping")):
        return out
    out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint = checkpoint or (lambda event: None)
    t0 = time.time()
    timings = {}
    n_views = len(scene.mapping)
    scene = replace(scene, mapping=keyframe_views(scene.mapping, conf.keyframes))
    lines_h5 = detect_or_import_lines(scene.mapping, out_dir, conf, lines_source, overwrite)
    timings["lines2d_s"] = time.time() - t0
    checkpoint("lines2d")
    if method == "lift":
        from ..lift import lift_linemap

        t = time.time()
        # the lifted detections that a merge fitted together, only where they agree with the merged line
        lm = verify_tracks(lift_linemap(scene.mapping, lines_h5, conf.lift), scene.mapping, conf.extract)
        timings["lift_s"] = time.time() - t
    else:
        lines_by_view = _lines_by_view(lines_h5, scene.mapping)
        t = time.time()
        planes_dir = out_dir if planes_root is None else planes_variant_dir(planes_root, scene, conf, lines_source)
        planes = fit_planes_with_lines(scene, lines_by_view, planes_dir, conf, lines_source, overwrite)
        timings["optimize_s"] = time.time() - t
        checkpoint("planes")
        t = time.time()
        depth = depth_maps(scene.mapping)  # read as needed: memory bounded
        lm = lipmap_linemap(scene, planes, lines_by_view, conf, depth)
        lm.metadata["map"] = "unmerged" if conf.extract.merge == "none" else "merged"
        timings["extract_s"] = time.time() - t
        from ..planes.check import plane_stats

        lm.metadata["plane_stats"] = plane_stats(planes, scene.mapping)
        lm.metadata["planes_file"] = os.path.relpath(planes_dir / "planes.h5", out_dir)  # shared when planes_root
        if unmerged is not None:  # written before linemap.h5: a linemap.h5 of this stamp implies it is there
            um = lipmap_linemap(scene, planes, lines_by_view, replace(conf, extract=replace(conf.extract, merge="none")),
                                depth)
            um.metadata.update({k: lm.metadata[k] for k in ("plane_stats", "planes_file")})
            um.metadata.update({"map": "unmerged", "scene": scene.name, "dataset": scene.dataset, "method": method,
                                "preset": conf.preset, "pose_source": scene.pose_source})
            um.save(unmerged, stamp=unmerged_stamp)
            um.to_ply(out_dir / "linemap_unmerged.ply")
            lm.metadata["unmerged_file"] = UNMERGED
    timings["total_s"] = time.time() - t0
    lm.metadata.update({"scene": scene.name, "dataset": scene.dataset, "pose_source": scene.pose_source,
                        "timings": timings, "method": method, "preset": conf.preset,
                        "keyframes": {"n_views": n_views, "n_keyframes": len(scene.mapping), **asdict(conf.keyframes)}})
    lm.save(out, stamp=stamp)
    lm.to_ply(out_dir / "linemap.ply")
    _render(lm, scene, out_dir)
    checkpoint("linemap")
    n_img = lm.supports[:, 0] if len(lm) else np.zeros(0)
    logger.info("Mapped %s with %s: %d lines (median %.0f views each) in %.1f s -> %s", scene.name, method, len(lm),
                np.median(n_img) if len(n_img) else 0, timings["total_s"], out)
    return out


def _render(lm, scene, out_dir: Path) -> None:
    """PNG renders and ``linemap.html`` (interactive 3D view) beside the map."""
    try:
        from ..viz import render_linemap_views

        render_linemap_views(lm, scene, out_dir)
    except Exception as e:  # noqa: BLE001 - a failed picture must not lose the map
        logger.warning("Could not render the line map: %s", e)
    try:
        from ..viz3d import save_linemap_html

        save_linemap_html(lm, out_dir / "linemap.html", views=scene.mapping)
    except Exception as e:  # noqa: BLE001
        logger.warning("Could not write the 3D view of the line map: %s", e)
