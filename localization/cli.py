"""`lipmap-loc`: thin command-line front end; every command calls library functions.

Bad input (lipmap.InputError) is reported as one line naming the file and the problem, exit code 2.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from lipmap import InputError, logger
from lipmap.cliargs import OneLineParser, float_at_least, int_at_least, number_list


def _scene_names(dataset: str, root, scenes: str | None) -> list[str]:
    from lipmap.datasets import list_scenes
    from lipmap.datasets.sevenscenes import SEVENSCENES_SCENES

    if scenes and scenes != "all":
        return [s.strip() for s in scenes.split(",") if s.strip()]
    found = list_scenes(dataset, root)
    if not found:
        raise InputError("no scenes found (no <scene>/TrainSplit.txt)", root)
    if dataset == "7scenes" and scenes == "all":
        return [s for s in SEVENSCENES_SCENES if s in found] or found
    return found


def scene_info(scene) -> dict:
    """Per-scene summary used by `lipmap-loc info`."""
    from collections import Counter

    import numpy as np

    v0 = scene.mapping[0]
    depth = v0.load_depth() if v0.depth_path is not None else None
    info = {
        "n_mapping": len(scene.mapping),
        "n_query": len(scene.query),
        "image_size": [v0.camera.width, v0.camera.height],
        "intrinsics": list(v0.camera.params),
        "focal": {f"{f:g}": n for f, n in Counter(v.camera.fx for v in scene.all_views()).most_common()},
        "focal_source": scene.meta.get("focal_source"),
        "pose_source": scene.pose_source,
        "depth": "none" if depth is None else ("registered" if scene.depth_registered else "raw (not registered)"),
        "depth_valid_fraction_first_frame": None if depth is None else round(float((depth > 0).mean()), 4),
        "normals": v0.normal_path is not None,
        "gt_mesh": None if scene.gt_mesh is None else str(scene.gt_mesh),
        "root": str(scene.root),
    }
    if v0.depth_camera is not None:
        info["depth_intrinsics"] = list(v0.depth_camera.params)
    if depth is not None:
        info["depth_range_m"] = [round(float(depth[depth > 0].min()), 3), round(float(depth.max()), 3)] if (depth > 0).any() else None
    centers = np.array([v.center for v in scene.mapping])
    info["mapping_extent_m"] = np.round(centers.max(0) - centers.min(0), 3).tolist()
    return info


def cmd_info(args):
    from lipmap.datasets import load_scene

    out = {"dataset": args.dataset, "scenes": {}}
    for name in _scene_names(args.dataset, args.root, args.scenes):
        scene = load_scene(args.dataset, args.root, name, pose_source=args.pose_source, register_depth=not args.no_registration,
                           pgt_dir=args.pgt)
        out["scenes"][name] = scene_info(scene)
    if args.json:
        print(json.dumps(out, indent=2))
        return
    for name, s in out["scenes"].items():
        fx, fy, cx, cy = s["intrinsics"]
        print(f"{name}  ({s['root']})")
        print(f"  mapping views: {s['n_mapping']}   query views: {s['n_query']}")
        print(f"  image: {s['image_size'][0]}x{s['image_size'][1]}   intrinsics fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}")
        focals = ", ".join(f + (f" ({n} views)" if len(s["focal"]) > 1 else "") for f, n in s["focal"].items())
        print(f"  focal: {focals} px, from {s['focal_source']}")
        if "depth_intrinsics" in s:
            print(f"  depth camera: fx={s['depth_intrinsics'][0]:g}")
        print(f"  depth: {s['depth']}  valid fraction (first frame) {s['depth_valid_fraction_first_frame']}  range {s.get('depth_range_m')} m")
        print(f"  normals: {'files' if s['normals'] else 'from depth'}   GT mesh: {s['gt_mesh'] or 'none (fused depth)'}")
        print(f"  pose source: {s['pose_source']}   mapping camera extent {s['mapping_extent_m']} m")


def _max_line_step(text: str) -> tuple:
    """``--max-line-step M,DEG`` (both > 0) or ``off``."""
    if text.strip().lower() in ("off", "0"):
        return ()
    return number_list(0.0, True, 2, "METRES,DEGREES (both > 0, e.g. 0.3,5) or 'off'")(text)


def _point_budget(text: str):
    """``--max-point-matches``: ``all`` (None) or a number of matches >= 0 (0: lines only)."""
    if text.strip().lower() == "all":
        return None
    try:
        return int_at_least(0)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"takes 'all' or a number of matches >= 0, got {text!r}") from None


def _keyframes(text: str) -> tuple:
    """``--keyframes CM,DEG`` (both >= 0) or ``0``."""
    if text.strip() == "0":
        return (0.0, 0.0)
    return number_list(0.0, False, 2, "CM,DEG (both >= 0, e.g. 5,5) or 0")(text)


def _gate(example: str):
    """An argparse type for ``PX,RAD`` gates: PX > 0 and 0 < RAD < pi/2."""
    pair = number_list(0.0, True, 2, f"PX,RAD (PX > 0, 0 < RAD < pi/2; e.g. {example})")

    def parse(text: str) -> tuple:
        px, rad = pair(text)
        if not rad < math.pi / 2:
            raise argparse.ArgumentTypeError(f"takes PX,RAD with 0 < RAD < pi/2, got {text!r}")
        return px, rad

    parse.__name__ = "PX,RAD"
    return parse


def eval_config(args):
    """The :class:`~localization.pipeline.LocalizationConfig` of ``lipmap-loc eval``'s options."""
    from dataclasses import replace

    from .linequery import LineQueryConfig
    from .config import LocalizationConfig

    conf = LocalizationConfig(seed=args.seed, max_point_matches=args.max_point_matches, mapping=_mapping_conf(args),
                              map_method=args.method, points=args.points)
    if args.line_query:
        conf = replace(conf, line_query=replace(LineQueryConfig(), method=args.line_query))
    if args.min_support is not None:
        hyp = replace(conf.line_rescue.hypotheses, min_support=args.min_support)
        conf = replace(conf, line_query=replace(conf.line_query, min_support=args.min_support),
                       line_rescue=replace(conf.line_rescue, hypotheses=hyp))
    if args.line_rescue is not None:
        conf = replace(conf, line_rescue=replace(conf.line_rescue, weak_inliers=args.line_rescue))
    if args.rescue_solver:
        conf = replace(conf, line_rescue=replace(conf.line_rescue, solver=args.rescue_solver))
    if args.rescue_threads is not None:
        conf = replace(conf, line_rescue=replace(conf.line_rescue, threads=args.rescue_threads))
    if args.max_line_step is not None:
        conf = replace(conf, max_line_step=args.max_line_step)
    if args.no_vanishing_points:
        hyp = replace(conf.line_rescue.hypotheses, upright=False)
        conf = replace(conf, line_rescue=replace(conf.line_rescue, hypotheses=hyp))
    return conf


def _hloc_outputs(args):
    """``--hloc DIR`` and its overrides as :class:`~localization.hloc_outputs.HlocOutputs` (None without --hloc)."""
    from .hloc_outputs import HlocOutputs

    given = {k: getattr(args, f"hloc_{k}") for k in ("sfm", "features", "matches", "pairs")}
    if args.hloc is None:
        if any(v is not None for v in given.values()):
            raise InputError("--hloc-sfm, --hloc-features, --hloc-matches and --hloc-pairs go with --hloc DIR")
        return None
    return HlocOutputs(args.hloc, **given)


def cmd_eval(args):
    from .pipeline import run_eval

    runner = None
    if args.ray is not None:  # before any work: a missing Ray or a bad option stops the run at once
        from .scaleout import RayRunner, import_ray

        import_ray()
        runner = RayRunner(address=args.ray or None, num_cpus=args.ray_cpus,
                           chunk=RayRunner.chunk if args.ray_chunk is None else args.ray_chunk)
    elif args.ray_cpus is not None or args.ray_chunk is not None:
        raise InputError("--ray-cpus and --ray-chunk go with --ray")
    conf = eval_config(args)
    if args.dataset == "synthetic" and args.root is None:
        from lipmap.datasets.synthetic import generate_scene

        root = Path(args.out) / "synthetic-data"
        scene_dir = generate_scene(root, seed=args.seed, preset=args.synth_preset)
        scenes = [scene_dir.name]
    else:
        if args.root is None:
            raise InputError("--root is required for --dataset 7scenes")
        root = args.root
        scenes = _scene_names(args.dataset, root, args.scenes)
    path = run_eval(args.dataset, root, scenes, args.out, conf, hloc_dir=_hloc_outputs(args), pose_source=args.pose_source,
                    register_depth=not args.no_registration, overwrite=args.overwrite, mapping_step=args.mapping_step,
                    skip_bad_frames=args.skip_bad_frames, runner=runner, pgt_dir=args.pgt, linemap=args.linemap)
    summary = path.parent / "summary.md"
    print(summary.read_text())
    print(f"results: {path}\nsummary: {summary}")
    from .report import html_report_of, write_report

    report = write_report(args.out, args.dataset, root=root)
    print(f"report: {report}\nreport.html: {html_report_of(report)}")


def cmd_map(args):
    import numpy as np

    from lipmap.datasets import load_scene
    from lipmap.mapping.pipeline import map_scene

    from lipmap.datasets.validate import check_scene

    over = {}
    if args.plane_depth_tol is not None:
        over["plane_depth_tol"] = args.plane_depth_tol
    conf = _mapping_conf(args, **over)
    scene = load_scene(args.dataset, args.root, args.scene, pose_source=args.pose_source,
                       register_depth=not args.no_registration, mapping_step=args.mapping_step,
                       skip_bad_frames=args.skip_bad_frames, pgt_dir=args.pgt)
    scene, _ = check_scene(scene, args.skip_bad_frames)
    path = map_scene(scene, args.out, conf, args.method, args.lines, args.overwrite)
    from lipmap.linemap import LineMap

    lm = LineMap.load(path)
    t = lm.metadata.get("timings", {})
    kinds = ""
    if "n_on_plane_lines" in lm.metadata:
        kinds = f" ({lm.metadata['n_edge_lines']} plane edges + {lm.metadata['n_on_plane_lines']} on-plane lines)"
    print(f"{len(lm)} lines{kinds} -> {path}")
    kf = lm.metadata.get("keyframes")
    if kf:
        print(f"keyframes: {kf['n_keyframes']} of {kf['n_views']} mapping views")
    if len(lm):
        n0 = int((lm.supports[:, 0] == 0).sum())
        print(f"supports (detections passing the track test): median {np.median(lm.supports[:, 0]):.0f} images "
              f"(mean {lm.supports[:, 0].mean():.1f}), {np.median(lm.supports[:, 1]):.0f} 2D lines per line; "
              f"{n0} lines no image verifies")
    ps = lm.metadata.get("plane_stats")
    if ps:
        print(f"planes: {ps['n_planes']}, area-weighted median {ps.get('area_weighted_median_area_m2', float('nan')):.3f} m2 "
              f"(longer side {ps.get('area_weighted_median_side_m', float('nan')):.2f} m); depth vs sensor: median "
              f"{ps.get('depth_error_median_cm', float('nan')):.1f} cm, {100 * ps.get('depth_error_over_5cm', float('nan')):.0f} % "
              f"of pixels > 5 cm")
    print(f"mapping time: {t.get('total_s', float('nan')):.1f} s ({json.dumps({k: round(v, 1) for k, v in t.items()})})")
    html = path.with_name("linemap.html")
    if not html.exists():  # a map reused from before map_scene wrote the 3D view
        from lipmap.viz3d import save_linemap_html

        save_linemap_html(lm, html, views=scene.mapping)
    print(f"3D view: {html}")


def cmd_map_eval(args):
    from lipmap.evaluation import evaluate_linemap, format_metrics, scene_ground_truth
    from lipmap.linemap import LineMap

    path = Path(args.linemap)
    if args.unmerged:
        from lipmap.mapping.pipeline import UNMERGED

        if path.is_dir() or not path.with_name(UNMERGED).exists():
            raise InputError(f"--unmerged: no {UNMERGED} beside {path} (written by presets with write_unmerged, "
                             "e.g. paper)", path)
        path = path.with_name(UNMERGED)
    lm = LineMap.from_limap(path) if path.is_dir() else LineMap.load(path)
    which = lm.metadata.get("map")
    if which is None:  # maps written before the key, and other methods' maps
        merge = lm.metadata.get("config", {}).get("extract", {}).get("merge") if lm.metadata.get("method") == "lipmap" else None
        which = {None: "as written", "none": "unmerged"}.get(merge, "merged")
    print(f"map: {path} ({which}, {len(lm)} lines)")
    if args.min_support > 0:
        n_all = len(lm)
        lm = lm.subset(lm.supports[:, 0] >= args.min_support)
        print(f"{len(lm)} of {n_all} lines are seen in >= {args.min_support} images")
    if args.gt is not None:
        gt = args.gt
    else:
        if not (args.dataset and args.root and args.scene):
            raise InputError("give --gt MESH_OR_PLY, or --dataset, --root and --scene")
        from lipmap.datasets import load_scene

        scene = load_scene(args.dataset, args.root, args.scene, pose_source=args.pose_source, pgt_dir=args.pgt)
        gt = scene_ground_truth(scene)
    overrides = {}
    if args.thresholds:
        overrides["m1_thresholds"] = args.thresholds
    res = evaluate_linemap(lm, gt, **overrides)
    res["min_support"] = args.min_support
    res["map"], res["linemap"] = which, str(path)
    print(format_metrics(res))
    lines_h5 = path.with_name("lines2d.h5")
    if args.gt is None and path.is_file() and lines_h5.exists():
        res["image_support"] = _image_support(lm, scene, lines_h5)
        print(f"shown by the mapping images: {100 * res['image_support']:.0f} % of the lines' visible length "
              "(within 2 px and 1 deg of a detection; lipmap.image_support)")
    from lipmap.viz import plot_pr_curve

    png = path.with_name(path.stem + "_pr.png")
    plot_pr_curve(lm, gt, png)
    print(f"precision/recall plot: {png}")
    if args.json:
        from lipmap.imageio import write_text_atomic

        write_text_atomic(args.json, json.dumps(res, indent=1, default=float))
        print(f"metrics: {args.json}")


def _image_support(lm, scene, lines_h5: Path) -> float:
    """:func:`lipmap.image_support.image_support` of ``lm`` over the mapping views whose lines ``lines_h5`` holds."""
    import h5py

    from lipmap.frames import depth_maps
    from lipmap.image_support import image_support
    from lipmap.lines2d import load_lines

    with h5py.File(lines_h5, "r") as f:
        views = [v for v in scene.mapping if v.name in f and "lines" in f[v.name]]
    return image_support(lm, views, {v.name: load_lines(lines_h5, v.name) for v in views}, depth_maps(views))["shown"]


POSE_SOURCES = ("posetxt", "dslam", "sfm")


def _add_dataset_args(p, scenes=True):
    p.add_argument("--dataset", choices=["7scenes", "synthetic"], required=True,
                   help="7scenes (the official layout, or scenes cut from it) or synthetic (scenes made by `lipmap-loc synth`)")
    p.add_argument("--root", type=Path, required=True, help="dataset root (holds <scene>/TrainSplit.txt)")
    if scenes:
        p.add_argument("--scenes", default=None, help="comma-separated scene names, or 'all' (default: every scene found)")
    _add_pose_args(p)


def _add_pose_args(p, registration: bool = True):
    p.add_argument("--pose-source", default="posetxt", choices=POSE_SOURCES,
                   help="poses for mapping AND evaluation (7-Scenes pose.txt or pseudo-GT lists); sfm and dslam also "
                        "set each view's focal length to its list's")
    p.add_argument("--pgt", type=Path, default=None, metavar="DIR",
                   help="the published pseudo-GT lists <scene>_{train,test}.txt of --pose-source sfm|dslam: a clone of "
                        "github.com/tsattler/visloc_pseudo_gt_limitations, its pgt/ folder, or its pgt/SOURCE/7scenes/ "
                        "(default: ROOT/pgt when it holds SOURCE/7scenes/, else ROOT/<scene>/pgt/SOURCE_<scene>.txt; "
                        "docs/usage.md)")
    if registration:
        p.add_argument("--no-registration", action="store_true", help="use raw depth as if it were the colour camera's")


def _add_mapping_args(p, method_default: str):
    from lipmap.mapping.pipeline import METHODS
    from lipmap.mapping.pipeline import confs as mapping_confs

    p.add_argument("--preset", default="fast", choices=list(mapping_confs),
                   help="mapping preset: fast (CPU; plane edges + lines lifted onto the planes), quick (tests, small "
                        "scenes), paper (reference settings, plane edges only, merged and unmerged maps; hours on a CPU)")
    p.add_argument("--method", default=method_default, choices=list(METHODS), help="line map method")
    p.add_argument("--mapping-step", type=int_at_least(1), default=1, help="use every k-th mapping frame")
    p.add_argument("--keyframes", default=None, type=_keyframes, metavar="CM,DEG",
                   help="map the views where the camera moved more than CM centimetres or turned more than DEG "
                        "degrees since the last one, and at least every 5th frame (default 5,5; 0 = every view)")
    from lipmap.mapping.refine import REFINE_LINES

    p.add_argument("--refine-lines", nargs="?", const="all", default=None, choices=list(REFINE_LINES),
                   help="lipmap: refine these lines (no value: all) against every mapping view that sees them, then "
                        "track them again (default: the preset's; fast refines all, quick and paper none)")
    p.add_argument("--full-resolution", nargs="?", const=-1, default=None, type=int_at_least(0), metavar="N",
                   help="lipmap: train the planes at the views' own resolution instead of the preset's (fast: half): "
                        "throughout (no value; what a GPU does at about the same cost), or only the last N iterations "
                        "(coarse to fine; fast: the last 900, ~80 s of the RedKitchen mini on 2 CPU cores; 0: none)")
    p.add_argument("--extract-gate", default=None, type=_gate("3,0.03"), metavar="PX,RAD",
                   help="lipmap: extract a plane edge where its projection lies within PX pixels and RAD radians of a "
                        "detected line (fast: 3,0.03; paper: 1,0.01). Wider gates give more plane edges and fewer "
                        "on-plane lines: at 10,0.1 the RedKitchen mini's edges reach F@5cm 0.65 and its full map drops "
                        "(docs/design.md)")
    p.add_argument("--track-gate", default=None, type=_gate("2,0.01"), metavar="PX,RAD",
                   help="lipmap: a line's track takes a detection its projection lies within PX pixels and RAD radians "
                        "of (default: the paper's 2,0.01)")
    p.add_argument("--explain-gate", default=None, type=_gate("2,0.01"), metavar="PX,RAD",
                   help="lipmap: a detection in a plane edge's track stays out of the on-plane lines only where the edge "
                        "projects within PX and RAD of it (default: every detection an edge tracks). With --track-gate "
                        "4,0.05, --extract-gate 4,0.04, --explain-gate 2,0.01 and --aggregate the RedKitchen mini's map reaches "
                        "F@5cm 0.821 / R@50mm 1,047 and 3 images per line, and localizes its held-out weak queries worse "
                        "(docs/design.md)")
    p.add_argument("--aggregate", action="store_true",
                   help="lipmap: one line per physical line: lines sharing detections merged, each spanning its track's "
                        "detections, single-image lines along a tracked one absorbed (off in every preset: the RedKitchen "
                        "mini's edges reach R@50mm 495 and its full map 876, and the held-out split's weak queries "
                        "localize worse; docs/design.md)")
    p.add_argument("--skip-bad-frames", action="store_true", help="skip unreadable mapping frames (default: stop with an error)")
    p.add_argument("--overwrite", action="store_true", help="remake the artifacts instead of reusing them")


def _full_resolution_planes(preset: str, n: int) -> dict:
    """The plane settings of mapping ``preset`` trained at the views' resolution: throughout (``n`` < 0) or for the
    last ``n`` iterations."""
    from lipmap.mapping.pipeline import confs as mapping_confs

    base = mapping_confs[preset].planes
    planes = dict(base) if isinstance(base, dict) else {"preset": base}
    planes.update({"downscale": 1} if n < 0 else {"fine_iterations": n, "fine_downscale": 1})
    return planes


def _mapping_conf(args, **overrides):
    """The mapping settings the command line asks for: the preset name, or a dict of overrides of it."""
    if args.keyframes is not None:
        cm, deg = args.keyframes
        overrides["keyframes"] = {"min_translation": cm / 100.0, "min_rotation_deg": deg}
    if getattr(args, "refine_lines", None):
        overrides["refine"] = {"enabled": True, "lines": args.refine_lines}
    if getattr(args, "full_resolution", None) is not None:
        overrides["planes"] = _full_resolution_planes(args.preset, args.full_resolution)
    if getattr(args, "extract_gate", None) is not None:
        px, rad = args.extract_gate
        overrides["extract"] = {"max_dist": px, "max_angle": rad}
    if getattr(args, "track_gate", None) is not None:
        px, rad = args.track_gate
        overrides["extract"] = {**overrides.get("extract", {}), "track_max_dist": px, "track_max_angle": rad}
    if getattr(args, "explain_gate", None) is not None:
        overrides["explain_gate"] = tuple(args.explain_gate)
    if getattr(args, "aggregate", False):
        overrides["aggregate"] = {"enabled": True}
    return {"preset": args.preset, **overrides} if overrides else args.preset


def _add_info_parser(sub):
    p = sub.add_parser("info", help="summarise the scenes of a dataset root")
    _add_dataset_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)


def _add_eval_parser(sub):
    from lipmap.datasets.synthetic import SYNTH_PRESETS

    from .linequery import LINE_QUERY_METHODS, LineQueryConfig
    from .config import RESCUE_SOLVERS, LocalizationConfig
    from .points import confs as point_confs

    p = sub.add_parser("eval", help="localization benchmark: map, localize point-only and point+line, evaluate")
    p.add_argument("--dataset", choices=["7scenes", "synthetic"], required=True,
                   help="7scenes (the official layout, or scenes cut from it) or synthetic (scenes made by `lipmap-loc synth`)")
    p.add_argument("--root", type=Path, default=None, help="dataset root (synthetic: generated under OUT when omitted)")
    p.add_argument("--scenes", default=None, help="comma-separated scenes or 'all'")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: OUT/<dataset>/ gets summary.md, results.json, report.html and a folder per scene")
    p.add_argument("--hloc", type=Path, default=None, metavar="DIR",
                   help="2D-3D points from hloc's outputs: DIR holds one folder per scene, as hloc's outputs/7scenes/ "
                        "(the model, features and query matches are chosen by rule and printed; the query pairs come "
                        "from that folder or the dataset's 7scenes_densevlad_retrieval_top_10/)")
    for what, example in (("sfm", "sfm_superpoint+superglue"), ("features", "feats-superpoint-n4096-r1024.h5"),
                          ("matches", "feats-superpoint-n4096-r1024_matches-superglue_{scene}_top10.h5"),
                          ("pairs", "DATA/7scenes_densevlad_retrieval_top_10/{scene}_top10.txt")):
        p.add_argument(f"--hloc-{what}", default=None, metavar="PATH",
                       help=f"with --hloc: use this {'SfM model folder' if what == 'sfm' else what + ' file'} instead "
                            f"of the one the rule picks ({{scene}} becomes the scene; relative to the scene's hloc "
                            f"folder or the current directory), e.g. {example}")
    p.add_argument("--linemap", default=None, metavar="PATH",
                   help="localize against this line map (linemap.h5 from `lipmap-loc map`) instead of mapping here; "
                        "{scene} in PATH becomes each scene's name")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="seed of every random step (RANSAC, the point-match draws)")
    p.add_argument("--max-point-matches", type=_point_budget, default=None, metavar="N|all",
                   help="a seeded random subset of N 2D-3D point matches per query, the same for point-only and "
                        "point+line: 0 is lines only, below 3 the lines go first (default all)")
    _add_mapping_args(p, method_default=LocalizationConfig().map_method)
    p.add_argument("--line-query", default=None, choices=list(LINE_QUERY_METHODS),
                   help="how a query's 2D lines find their map lines: projection (default: the map lines visible from "
                        "the pose, projected and matched by angle and distance) or raycast (the paper's: rays of each "
                        "line's 1-px region cast against the planes; lipmap maps only, slower)"),
    p.add_argument("--min-support", type=int_at_least(0), default=None, metavar="N",
                   help="map lines seen in fewer than N mapping images (by the track test) are left out of the line "
                        f"query and the rescue (default {LineQueryConfig().min_support}: the lines no image verifies; "
                        "0: every line)")
    p.add_argument("--line-rescue", type=int_at_least(0), default=None, metavar="N",
                   help="a query whose point-only pose has fewer than N inliers (or none) starts its lines from wide "
                        "gates around the P3P poses of its matches that the map lines agree with "
                        f"(default {LocalizationConfig().line_rescue.weak_inliers}; 0: off)")
    p.add_argument("--rescue-solver", default=None, choices=RESCUE_SOLVERS,
                   help="how the rescue estimates a pose from each start: a PnPL RANSAC about the start (near, the "
                        "default) or PoseLib's (ransac), then robust refinements in narrowing gates; or the refinements "
                        "alone: faster, less accurate (docs/localization.md)")
    p.add_argument("--rescue-threads", type=int_at_least(1), default=None, metavar="N",
                   help="threads a weak query's rescue starts run on (default "
                        f"{LocalizationConfig().line_rescue.threads}; the poses are the same on any number; 1 where "
                        "every core already localizes a query of its own)")
    p.add_argument("--max-line-step", default=None, type=_max_line_step, metavar="M,DEG",
                   help="a line refinement round whose pose moves farther than M metres or DEG degrees from its start "
                        "is refused and the rounds stop (default %s; 'off': every round is taken)"
                        % ",".join(f"{x:g}" for x in LocalizationConfig().max_line_step))
    p.add_argument("--no-vanishing-points", action="store_true",
                   help="the rescue starts from P3P poses only, without the two-point poses aligned by vanishing points "
                        "(for scenes whose lines do not run along a few dominant directions; docs/localization.md)")
    p.add_argument("--points", default="sift-n4096", choices=list(point_confs), help="built-in point preset")
    p.add_argument("--synth-preset", default="small", choices=list(SYNTH_PRESETS),
                   help="the synthetic scene generated when --dataset synthetic has no --root (default small)")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run on Ray (pip install \"lipmap[ray]\"): each scene's mapping and chunks of its queries are "
                        "tasks. No ADDRESS: a local Ray instance; 'auto', 'ray://HOST:PORT' or 'HOST:PORT': a cluster whose "
                        "workers see OUT and the data at the same paths and run the same Python environment")
    p.add_argument("--ray-cpus", type=int_at_least(1), default=None, metavar="N", help="CPUs of the local Ray instance (default: all)")
    p.add_argument("--ray-chunk", type=int_at_least(1), default=None, metavar="N", help="queries per Ray task (default 50)")
    _add_pose_args(p)
    p.set_defaults(func=cmd_eval)


def _add_map_parser(sub):
    p = sub.add_parser(
        "map", help="build a line map (linemap.h5, linemap.ply, planes.ply, linemap.html: interactive 3D view)",
        description="Build a line map. Method lipmap fits planes to each mapping view's depth and normals: the normals "
                    "are read from frame-*.normal.png (camera frame, lipmap.imageio) where the scene has them, else "
                    "computed from the depth. The paper's planes were fitted to normals predicted by Omnidata, which "
                    "this command does not run: write them as frame-*.normal.png to map as the paper did. Preset "
                    "paper also writes linemap_unmerged.h5 (one line per accepted plane edge) beside the merged "
                    "linemap.h5, as the reference code does.")
    p.add_argument("--dataset", choices=["7scenes", "synthetic"], required=True,
                   help="7scenes (the official layout, or scenes cut from it) or synthetic (scenes made by `lipmap-loc synth`)")
    p.add_argument("--root", type=Path, required=True, help="dataset root (holds <scene>/TrainSplit.txt)")
    p.add_argument("--scene", required=True, help="the scene to map (a folder under --root)")
    p.add_argument("--out", type=Path, required=True, help="folder for linemap.h5 and its companions (made if missing)")
    _add_mapping_args(p, method_default="lipmap")
    p.add_argument("--lines", type=Path, default=None,
                   help="2D lines made elsewhere instead of LSD: hloc/DeepLSD/SOLD2 lines2d.h5, or a folder of HAWP "
                        "WireframeGraph JSON / npz files, one per mapping image (lipmap.lines2d)")
    p.add_argument("--plane-depth-tol", type=float_at_least(0.0), default=None, metavar="METRES",
                   help="lipmap: lines inside a surface follow the input depth where the planes are more than this "
                        "far from it (preset default 0.03, for sensor depth); 0 = on the planes only (noisy or "
                        "predicted depth)")
    _add_pose_args(p)
    p.set_defaults(func=cmd_map)


def _add_map_eval_parser(sub):
    p = sub.add_parser("map-eval", help="mapping metrics M1 / M2 of a line map against a mesh or point cloud")
    p.add_argument("--linemap", type=Path, required=True, help="linemap.h5, or a LIMAP folder holding finaltracks/")
    p.add_argument("--unmerged", action="store_true",
                   help="evaluate the unmerged map beside --linemap (linemap_unmerged.h5: one line per accepted plane "
                        "edge, written by the paper preset as the reference code does) instead of the merged one; "
                        "the output names the map it scores")
    p.add_argument("--gt", type=Path, default=None, help="GT mesh or point cloud (PLY)")
    p.add_argument("--thresholds", default=None, type=number_list(0.0, True, None, "metres > 0 separated by commas, e.g. 0.02,0.05"),
                   help="M1 thresholds in metres, comma separated (default 0.05)")
    p.add_argument("--min-support", type=int_at_least(0), default=0, metavar="N",
                   help="evaluate only the lines seen in at least N images (LIMAP's n_visible_views; default 0: all, "
                        "also the lines no image's detection agrees with)")
    p.add_argument("--dataset", choices=["7scenes", "synthetic"],
                   help="with --root and --scene: score against the scene's own ground truth (its mesh, or its depth fused)")
    p.add_argument("--root", type=Path, help="dataset root (with --dataset and --scene)")
    p.add_argument("--scene", help="the scene the map was made of (with --dataset and --root)")
    _add_pose_args(p, registration=False)
    p.add_argument("--json", type=Path, default=None, help="also write the metrics to this JSON file")
    p.set_defaults(func=cmd_map_eval)


# subcommands whose parsers live beside their library code: (module, name of add_<name>_parser)
_PLUGGED = (("lipmap.datasets.synthetic", "synth"), ("localization.report", "report"), ("lipmap.linemap", "linemap_export"),
            ("localization.download", "download"))


def build_parser() -> argparse.ArgumentParser:
    import importlib

    ap = OneLineParser(prog="lipmap-loc", description=__doc__.splitlines()[0])
    ap.add_argument("-v", "--verbose", action="store_true", help="log debug messages too")
    sub = ap.add_subparsers(dest="command", required=True)
    for add in (_add_info_parser, _add_eval_parser, _add_map_parser, _add_map_eval_parser):
        add(sub)
    for module, name in _PLUGGED:
        getattr(importlib.import_module(module), f"add_{name}_parser")(sub)
    return ap


def main(argv=None) -> int:
    """Run ``lipmap-loc``; returns the exit code (2 for bad input: a one-line message, no traceback)."""
    ap = build_parser()
    try:
        args = ap.parse_args(argv)
    except SystemExit as e:  # an argparse error (2) or --help (0): the code, as for any other outcome
        return e.code if isinstance(e.code, int) else 2
    if args.verbose:
        logger.setLevel(logging.DEBUG)
    try:
        args.func(args)
    except InputError as e:
        print(f"lipmap-loc: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
