"""What each mapping setting is worth: lipmap maps of one scene with named overrides of a preset, side by side.

    python benchmarks/mapping_variants.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--preset fast] [--base NAME] [--tag TAG] NAME='{"line_weight": 1.0}' NAME2='{...}' ...

Each variant is mapped into OUT/<NAME> (reused when a map made with the same settings is there). A variant that
differs from ``--base`` only in extraction-side settings (``extract``, ``plane_depth_tol``, ``on_plane_lines``,
``lift``, ``refine``) starts from the planes of ``--base`` (copied: their stamp says they are the same planes), so it costs seconds, not a
plane optimization. Prints a table (full map and plane edges alone: F@5cm, R@50mm, images per line;
plane count and depth error) and writes it to ``benchmarks/results/mapping-variants-<dataset>-<scene>.json``.
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

from lipmap.datasets import load_scene
from lipmap.evaluation import evaluate_linemap, load_ground_truth, scene_ground_truth
from lipmap.linemap import LineMap
from lipmap.mapping.extract import ExtractConfig
from lipmap.mapping.pipeline import edge_line_mask, get_conf, map_scene
from lipmap.planes.io import load_planes_meta

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

EXTRACTION_ONLY = {"extract", "plane_depth_tol", "on_plane_lines", "lift", "refine"}
HEADER = ["variant", "overrides", "lines", "F@5cm", "R@50mm", "edge lines", "edges F@5cm", "edges R@50mm",
          "images per line: median / mean (edges)", "planes", "plane depth error median / > 5 cm", "plane optimization"]


def _conf(preset: str, over: dict):
    over = dict(over)
    if "extract" in over:  # overrides of the preset's extraction settings
        base = get_conf(preset).extract
        over["extract"] = ExtractConfig(**{**base.__dict__, **over["extract"]})
    return {"preset": preset, **over}


def _metrics(lm, gt) -> dict:
    r = evaluate_linemap(lm, gt)
    m1, m2 = r["M1"]["line"], r["M2"]
    return {"n": len(lm), "prec": m1["prec@0.05"], "recall": m1["recall@0.05"], "f": m1["f@0.05"], "r5": m2["R@5mm"],
            "r50": m2["R@50mm"], "median_images": float(np.median(lm.supports[:, 0])) if len(lm) else 0.0,
            "mean_images": float(np.mean(lm.supports[:, 0])) if len(lm) else 0.0}


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--base", default=None, help="the variant whose planes extraction-only variants reuse")
    ap.add_argument("--tag", default="", help="suffix of the results file, so that another question keeps its own table")
    ap.add_argument("variants", nargs="+", help="NAME=JSON overrides of the preset ('{}' for the preset itself)")
    args = ap.parse_args(argv)
    scene = load_scene(args.dataset, args.root, args.scene)
    gt = load_ground_truth(scene_ground_truth(scene))
    rows, data = [], {}
    specs = [(spec.partition("=")[0], json.loads(spec.partition("=")[2] or "{}")) for spec in args.variants]
    base_over = dict(specs).get(args.base, {})

    def plane_side(over):
        return {k: v for k, v in over.items() if k not in EXTRACTION_ONLY}

    for name, over in specs:
        out = args.out / name
        # same planes as the base: the overrides differ from the base's only in extraction-side settings
        reuses = bool(args.base) and name != args.base and plane_side(over) == plane_side(base_over)
        if reuses and not (out / "planes.h5").exists():
            out.mkdir(parents=True, exist_ok=True)
            for f in ("planes.h5", "lines2d.h5"):
                shutil.copy(args.out / args.base / f, out / f)
        lm = LineMap.load(map_scene(scene, out, _conf(args.preset, over), "lipmap"))
        full, edges = _metrics(lm, gt), _metrics(lm.subset(edge_line_mask(lm)), gt)
        ps = lm.metadata.get("plane_stats", {})
        # the plane optimization's own time (planes.h5), so that a variant reusing planes still shows it
        t = load_planes_meta(out / "planes.h5").get("history", {}).get("total_seconds")
        data[name] = {"overrides": over, "full": full, "edges": edges, "plane_stats": ps, "timings": lm.metadata.get("timings")}
        rows.append([name, f"`{json.dumps(over)}`" if over else f"preset `{args.preset}`", full["n"], f"{full['f']:.3f}",
                     f"{full['r50']:.0f}", edges["n"], f"{edges['f']:.3f}", f"{edges['r50']:.0f}",
                     f"{full['median_images']:.0f} / {full['mean_images']:.1f} ({edges['median_images']:.0f} / "
                     f"{edges['mean_images']:.1f})", ps.get("n_planes", ""),
                     f"{ps.get('depth_error_median_cm', float('nan')):.1f} cm / {100 * ps.get('depth_error_over_5cm', float('nan')):.0f} %",
                     "" if t is None or reuses else f"{t:.0f} s planes"])
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    results.write(f"mapping-variants-{scene.dataset}-{scene.name}" + (f"-{args.tag}" if args.tag else ""), {"preset": args.preset, "variants": data,
                                                                      "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
