"""README localization rows for one scene: point-only vs point+line, with all point matches and with a
seeded subset of N per query (lines can only show a gain where points are scarce).

    python benchmarks/localization_table.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--matches all,10,5] [--method lift|lipmap] [--line-query projection] \
        [--pose-source posetxt|sfm] [--preset fast] [--tag TAG]

Runs ``lipmap-loc eval`` once per match budget into OUT (the map and the point artifacts are built once and
reused; each budget has its own journal), prints a markdown table and writes it with the per-run summaries to
``benchmarks/results/localization-<dataset>-<scene>-<method>-<pose source>[-<tag>].json``.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from localization.linequery import LineQueryConfig
from localization.pipeline import LocalizationConfig, run_eval

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["scene", "ground truth", "line map", "point matches",
          "point-only: cm / deg / % at 1 cm 1°, 2 cm 2°, 5 cm 5°", "point+line: same", "line stage ms"]


def cell(s: dict) -> str:
    if not s or s.get("median_t_cm") is None:
        return "failed"
    return (f"{s['median_t_cm']:.2f} / {s['median_R_deg']:.2f} / "
            f"{s['acc_1cm_1deg']:.0f}, {s['acc_2cm_2deg']:.0f}, {s['acc_5cm_5deg']:.0f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True, choices=["7scenes", "synthetic"])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--matches", default="all,10", help="comma separated point-match budgets per query ('all' = no limit)")
    ap.add_argument("--method", default=LocalizationConfig().map_method)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--line-query", default="projection")
    ap.add_argument("--pose-source", default="posetxt")
    ap.add_argument("--points", default="sift-n4096")
    ap.add_argument("--label", default=None)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    rows, runs = [], {}
    for m in args.matches.split(","):
        n = None if m == "all" else int(m)
        conf = LocalizationConfig(max_point_matches=n, map_method=args.method, mapping=args.preset, points=args.points,
                                  line_query=replace(LineQueryConfig(), method=args.line_query))
        path = run_eval(args.dataset, args.root, [args.scene], args.out, conf, pose_source=args.pose_source)
        scene_res = json.loads((path.parent / args.scene / "results.json").read_text())
        s = scene_res["summary"]
        runs[m] = {"summary": s, "map": scene_res["map"], "n_queries": s["point"]["n_queries"]}
        map_cell = f"{args.method} `{args.preset}`, {args.line_query}" if args.method == "lipmap" else f"{args.method}, {args.line_query}"
        rows.append([(args.label or f"{args.scene} ({s['point']['n_queries']} queries)") if not rows else "",
                     args.pose_source if not rows else "", map_cell if not rows else "", m, cell(s["point"]),
                     cell(s["point+line"]), f"{s['point+line'].get('median_ms_line_stage') or 0:.0f}"])
    print("\n".join("| " + " | ".join(map(str, r)) + " |" for r in [HEADER, *rows]))
    name = f"localization-{args.dataset}-{args.scene}-{args.method}-{args.pose_source}" + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"scene": args.scene, "dataset": args.dataset, "runs": runs, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
