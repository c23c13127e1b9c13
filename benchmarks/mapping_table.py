"""The README's mapping table for one scene: lipmap (full map, its plane edges and its on-plane lines alone) vs lift.

    python benchmarks/mapping_table.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--preset fast] [--methods lipmap,lift] [--plane-depth-tols 0] \
        [--pose-source posetxt|dslam|sfm] [--unmerged]

Maps with each method into OUT/<method> (an existing linemap.h5 made with the same settings is reused, as
`lipmap-loc map` does), evaluates against the scene's ground truth (its mesh, else fused depth: the same as
`lipmap-loc map-eval`), prints a markdown table and writes it with the metrics to
``benchmarks/results/mapping-<dataset>-<scene>[-<tag>].json`` (the README's mapping table is generated from
there); the times are the mapping runs' own (linemap.h5 metadata).
``--plane-depth-tols`` adds lipmap rows with other ``MappingConfig.plane_depth_tol`` values, built on the
same planes (OUT/lipmap-tol<value>, reusing OUT/lipmap's planes.h5 and lines2d.h5).
``--pose-source`` maps (and fuses the ground truth) with another pose source of a 7-Scenes scene: pose.txt
drifts by centimetres along a sequence, which blurs the fused ground truth and breaks multi-view line tracks;
the result file then ends in ``-<pose source>``.
A lipmap row scores ``linemap.h5``; where the preset also writes the unmerged map (``paper``, as the reference
code does) the row says "merged map", and ``--unmerged`` adds a row for ``linemap_unmerged.h5``.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

from lipmap.datasets import load_scene
from lipmap.evaluation import evaluate_linemap, load_ground_truth, scene_ground_truth
from lipmap.linemap import LineMap
from lipmap.mapping.pipeline import UNMERGED, edge_line_mask, map_scene
from lipmap.planes.io import load_planes_meta

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402


HEADER = ["scene (ground truth)", "method", "lines", "PREC@5cm", "RECALL@5cm", "F@5cm", "R@5mm", "R@50mm",
          "supports (images / 2D lines)", "mapping time"]


def mapping_seconds(lm: LineMap, folder: Path):
    """The map's cost: its own steps, with the plane optimization's time read from planes.h5 (which a run
    that reused the planes did not spend itself)."""
    t = dict(lm.metadata.get("timings", {}))
    if (folder / "planes.h5").exists():
        planes_s = load_planes_meta(folder / "planes.h5").get("history", {}).get("total_seconds")
        if planes_s is not None:
            t["total_s"] = t.get("total_s", 0.0) - t.get("optimize_s", 0.0) + planes_s
    return t.get("total_s")


def row(label: str, name: str, lm: LineMap, gt, seconds) -> tuple[list, dict]:
    res = evaluate_linemap(lm, gt)
    m1, m2 = res["M1"]["line"], res["M2"]
    t = "" if seconds is None else f"{seconds:.0f} s"
    cells = [label, name, len(lm), f"{m1['prec@0.05']:.3f}", f"{m1['recall@0.05']:.3f}", f"{m1['f@0.05']:.3f}",
             f"{m2['R@5mm']:.0f}", f"{m2['R@50mm']:.0f}", f"{m2['supports_images']:.1f} / {m2['supports_lines']:.1f}", t]
    return cells, res


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--preset", default="fast", help="mapping preset of the lipmap run")
    ap.add_argument("--methods", default="lipmap,lift")
    ap.add_argument("--plane-depth-tols", default="", help="extra lipmap rows, comma separated metres")
    ap.add_argument("--label", default=None, help="the scene's name in the table (default: scene (ground truth kind))")
    ap.add_argument("--tag", default="", help="suffix of the results file name (e.g. noisy-depth)")
    ap.add_argument("--pose-source", default="posetxt", help="7-Scenes poses: posetxt | dslam | sfm")
    ap.add_argument("--unmerged", action="store_true",
                    help="also score lipmap's unmerged map (linemap_unmerged.h5, where the preset writes it)")
    args = ap.parse_args(argv)
    results.require_clean()  # before the run: figures from a dirty tree reproduce from no commit
    kw = {} if args.pose_source == "posetxt" else {"pose_source": args.pose_source}
    scene = load_scene(args.dataset, args.root, args.scene, **kw)
    gt_source = scene_ground_truth(scene)
    gt = load_ground_truth(gt_source)
    gt_kind = "mesh" if scene.gt_mesh is not None else "fused depth" + ("" if not kw else f", {args.pose_source} poses")
    label = args.label or f"{scene.name} ({gt_kind})"
    rows, metrics = [], {}

    def add(name, lm, seconds=None):
        cells, metrics[name] = row(label if not rows else "", name, lm, gt, seconds)
        rows.append(cells)

    for method in args.methods.split(","):
        path = map_scene(scene, args.out / method, args.preset, method)
        lm = LineMap.load(path)
        both = method == "lipmap" and (path.parent / UNMERGED).exists()
        name = f"{method} `{args.preset}`" + (" (merged map)" if both else "") if method == "lipmap" else method
        add(name, lm, mapping_seconds(lm, args.out / method))
        if args.unmerged and method == "lipmap":
            if not both:
                raise SystemExit(f"--unmerged: preset {args.preset} writes no {UNMERGED}")
            add("(its unmerged map)", LineMap.load(path.parent / UNMERGED))
        if method == "lipmap":
            edges = edge_line_mask(lm)
            if not edges.all():
                add("(its plane edges only)", lm.subset(edges))
                add("(its on-plane lines only)", lm.subset(~edges))
            for tol in filter(None, args.plane_depth_tols.split(",")):
                out = args.out / f"lipmap-tol{tol}"
                out.mkdir(parents=True, exist_ok=True)
                for name in ("planes.h5", "lines2d.h5"):  # the same planes: their stamps match this conf's
                    if not (out / name).exists():
                        shutil.copy(args.out / method / name, out / name)
                conf = {"preset": args.preset, "plane_depth_tol": float(tol)}
                add(f"`--plane-depth-tol {tol}`", LineMap.load(map_scene(scene, out, conf, method)))
    print(f"{scene.dataset} {scene.name}:")
    print("\n".join("| " + " | ".join(map(str, r)) + " |" for r in [HEADER, *rows]))
    name = f"mapping-{scene.dataset}-{scene.name}" + "".join(f"-{t}" for t in (args.tag, kw.get("pose_source")) if t)
    results.write(name, {"scene": scene.name, "dataset": scene.dataset, "ground_truth": str(gt_source),
                         "pose_source": args.pose_source,
                         "metrics": metrics, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
