"""What each mapping setting is worth: lipmap maps of one scene with named overrides of a preset, side by side.

    python benchmarks/mapping_variants.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--preset fast] [--base NAME] [--tag TAG] NAME='{"line_weight": 1.0}' NAME2='{...}' ...

Each variant is mapped into OUT/<NAME> (reused when a map made with the same settings is there), and its planes into
OUT/planes-<preset>-<digest>: variants whose plane optimization is the same (by its stamp: settings and the code that
shapes planes) share one, so a variant that changes only extraction, tracks or on-plane lines costs seconds.
Prints a table (full map and plane edges alone: F@5cm, R@50mm, images per line, and the length-weighted share of
the lines' visible length that the mapping views' detections show, ``lipmap.image_support``; plane count and depth
error) and writes it to ``benchmarks/results/mapping-variants-<dataset>-<scene>.json``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from lipmap.datasets import load_scene
from lipmap.evaluation import evaluate_linemap, load_ground_truth, scene_ground_truth
from lipmap.image_support import image_support
from lipmap.frames import depth_maps
from lipmap.lines2d import load_lines
from lipmap.mapping.keyframes import keyframe_views
from lipmap.linemap import LineMap
from lipmap.mapping.extract import ExtractConfig
from lipmap.mapping.pipeline import edge_line_mask, get_conf, map_scene
from lipmap.planes.io import load_planes_meta

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["variant", "overrides", "lines", "F@5cm", "R@50mm", "edge lines", "edges F@5cm", "edges R@50mm",
          "images per line: median / mean (edges)", "shown by its images (edges)", "planes", "plane depth error median / > 5 cm", "plane optimization"]


def _conf(preset: str, over: dict):
    over = dict(over)
    if "extract" in over:  # overrides of the preset's extraction settings
        base = get_conf(preset).extract
        over["extract"] = ExtractConfig(**{**base.__dict__, **over["extract"]})
    return {"preset": preset, **over}


def _metrics(lm, gt, views, lines_by_view, depth) -> dict:
    r = evaluate_linemap(lm, gt)
    m1, m2 = r["M1"]["line"], r["M2"]
    return {"shown": image_support(lm, views, lines_by_view, depth)["shown"], "n": len(lm), "prec": m1["prec@0.05"], "recall": m1["recall@0.05"], "f": m1["f@0.05"], "r5": m2["R@5mm"],
            "r50": m2["R@50mm"], "median_images": float(np.median(lm.supports[:, 0])) if len(lm) else 0.0,
            "mean_images": float(np.mean(lm.supports[:, 0])) if len(lm) else 0.0}


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--base", default=None, help="ignored (kept so that recorded commands run): variants share "
                    "planes through their stamp")
    ap.add_argument("--tag", default="", help="suffix of the results file, so that another question keeps its own table")
    ap.add_argument("variants", nargs="+", help="NAME=JSON overrides of the preset ('{}' for the preset itself)")
    args = ap.parse_args(argv)
    results.require_clean()  # before the run: figures from a dirty tree reproduce from no commit
    scene = load_scene(args.dataset, args.root, args.scene)
    gt = load_ground_truth(scene_ground_truth(scene))
    depth = depth_maps(scene.mapping)
    rows, data = [], {}
    specs = [(spec.partition("=")[0], json.loads(spec.partition("=")[2] or "{}")) for spec in args.variants]
    seen_planes = set()
    for name, over in specs:
        lm = LineMap.load(map_scene(scene, args.out / name, _conf(args.preset, over), "lipmap", planes_root=args.out))
        planes_h5 = (args.out / name / lm.metadata["planes_file"]).resolve()
        reuses = planes_h5 in seen_planes  # another variant of this run made (or reused) the same planes
        seen_planes.add(planes_h5)
        views = keyframe_views(scene.mapping, get_conf(_conf(args.preset, over)).keyframes)  # the views of lines2d.h5
        lines_by_view = {v.name: load_lines(args.out / name / "lines2d.h5", v.name) for v in views}
        full = _metrics(lm, gt, views, lines_by_view, depth)
        edges = _metrics(lm.subset(edge_line_mask(lm)), gt, views, lines_by_view, depth)
        ps = lm.metadata.get("plane_stats", {})
        # the plane optimization's own time (planes.h5), so that a variant reusing planes still shows it
        t = load_planes_meta(planes_h5).get("history", {}).get("total_seconds")
        data[name] = {"overrides": over, "full": full, "edges": edges, "plane_stats": ps, "timings": lm.metadata.get("timings")}
        rows.append([name, f"`{json.dumps(over)}`" if over else f"preset `{args.preset}`", full["n"], f"{full['f']:.3f}",
                     f"{full['r50']:.0f}", edges["n"], f"{edges['f']:.3f}", f"{edges['r50']:.0f}",
                     f"{full['median_images']:.0f} / {full['mean_images']:.1f} ({edges['median_images']:.0f} / "
                     f"{edges['mean_images']:.1f})", f"{100 * full['shown']:.0f} % ({100 * edges['shown']:.0f} %)",
                     ps.get("n_planes", ""),
                     f"{ps.get('depth_error_median_cm', float('nan')):.1f} cm / {100 * ps.get('depth_error_over_5cm', float('nan')):.0f} %",
                     "" if t is None or reuses else f"{t:.0f} s planes"])
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    results.write(f"mapping-variants-{scene.dataset}-{scene.name}" + (f"-{args.tag}" if args.tag else ""), {"preset": args.preset, "variants": data,
                                                                      "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
