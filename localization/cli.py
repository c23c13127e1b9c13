"""`lipmap-loc`: thin command-line front end; every command calls library functions.

Bad input (lipmap.InputError) is reported as one line naming the file and the problem, exit code 2.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from lipmap import InputError, logger


def _scene_names(dataset: str, root, scenes: str | None) -> list[str]:
    from lipmap.datasets import list_scenes
    from lipmap.datasets.sevenscenes import SEVENSCENES_SCENES

    if scenes and scenes != "all":
        return [s.strip() for s in scenes.split(",") if s.strip()]
    found = list_scenes(dataset, root)
    if not found:
        raise InputError(f"no scenes found (no <scene>/TrainSplit.txt)", root)
    if dataset == "7scenes" and scenes == "all":
        return [s for s in SEVENSCENES_SCENES if s in found] or found
    return found


def scene_info(scene) -> dict:
    """Per-scene summary used by `lipmap-loc info`."""
    import numpy as np

    v0 = scene.mapping[0]
    depth = v0.load_depth() if v0.depth_path is not None else None
    info = {
        "n_mapping": len(scene.mapping),
        "n_query": len(scene.query),
        "image_size": [v0.camera.width, v0.camera.height],
        "intrinsics": list(v0.camera.params),
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
        scene = load_scene(args.dataset, args.root, name, pose_source=args.pose_source, register_depth=not args.no_registration)
        out["scenes"][name] = scene_info(scene)
    if args.json:
        print(json.dumps(out, indent=2))
        return
    for name, s in out["scenes"].items():
        fx, fy, cx, cy = s["intrinsics"]
        print(f"{name}  ({s['root']})")
        print(f"  mapping views: {s['n_mapping']}   query views: {s['n_query']}")
        print(f"  image: {s['image_size'][0]}x{s['image_size'][1]}   intrinsics fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g}")
        if "depth_intrinsics" in s:
            print(f"  depth camera: fx={s['depth_intrinsics'][0]:g}")
        print(f"  depth: {s['depth']}  valid fraction (first frame) {s['depth_valid_fraction_first_frame']}  range {s.get('depth_range_m')} m")
        print(f"  normals: {'files' if s['normals'] else 'from depth'}   GT mesh: {s['gt_mesh'] or 'none (fused depth)'}")
        print(f"  pose source: {s['pose_source']}   mapping camera extent {s['mapping_extent_m']} m")


def _add_dataset_args(p, scenes=True):
    p.add_argument("--dataset", choices=["7scenes", "synthetic"], required=True)
    p.add_argument("--root", type=Path, required=True, help="dataset root (holds <scene>/TrainSplit.txt)")
    if scenes:
        p.add_argument("--scenes", default=None, help="comma-separated scene names, or 'all' (default: every scene found)")
    p.add_argument("--pose-source", default="posetxt", choices=["posetxt", "dslam", "sfm"],
                   help="poses for mapping AND evaluation (7-Scenes pose.txt or pseudo-GT lists)")
    p.add_argument("--no-registration", action="store_true", help="use raw depth as if it were the colour camera's")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="lipmap-loc", description=__doc__.splitlines()[0])
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="summarise the scenes of a dataset root")
    _add_dataset_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)

    for module, name in (("lipmap.datasets.synthetic", "synth"),):
        try:
            mod = __import__(module, fromlist=["_"])
        except ImportError:
            continue
        getattr(mod, f"add_{name}_parser")(sub)
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
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
