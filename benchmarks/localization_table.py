"""README localization rows for one scene: point-only vs point+line, with all point matches and with a seeded
random subset of N per query (lines can only show a gain where points are scarce).

    python benchmarks/localization_table.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--matches all,10,5] [--match-seeds 0,1,2,3,4] [--method lipmap|lift] \
        [--line-query projection|raycast] [--pose-source posetxt|sfm] [--preset fast] [--tag TAG]

Runs ``lipmap-loc eval`` once per match budget and draw into OUT (the map and the point artifacts are built once
and reused; each run has its own journal). A subset of N matches is one random draw per query: one draw makes a
median over 50 queries move by ~0.3 cm, more than lines gain, so a budget's figures pool the queries of all
``--match-seeds`` draws (median and accuracies over draws x queries; point-only and point+line see the same draws).
Prints a markdown table and writes it with the per-run summaries to
``benchmarks/results/localization-<dataset>-<scene>-<method>-<pose source>[-<tag>].json``.
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from localization.evaluate import paired_comparison
from localization.linequery import LineQueryConfig
from localization.config import LocalizationConfig
from localization.pipeline import run_eval

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["scene", "ground truth", "line map", "point matches",
          "point-only: cm / deg / % at 1 cm 1°, 2 cm 2°, 5 cm 5°", "point+line: same",
          "point+line against point-only, per query: better / worse, p(worse)",
          "line matches / correct (precision); PnPL inlier precision", "line stage ms"]
THRESHOLDS = ((1.0, 1.0), (2.0, 2.0), (5.0, 5.0))


def errors(runs: list[dict], key: str) -> np.ndarray:
    """Translation errors (cm; inf = failed) of every query of every run, draw-major, queries in results order."""
    return np.array([np.inf if q.get(key, {}).get("t_cm") is None else q[key]["t_cm"]
                     for res in runs for q in res["queries"].values()], dtype=float)


def pooled(runs: list[dict], key: str) -> dict:
    """Median errors and accuracies over the queries of every run (failed = infinitely wrong)."""
    t, r = [], []
    for res in runs:
        for q in res["queries"].values():
            e = q.get(key, {})
            t.append(np.inf if e.get("t_cm") is None else e["t_cm"])
            r.append(np.inf if e.get("R_deg") is None else e["R_deg"])
    t, r = np.array(t), np.array(r)
    out = {"n": int(len(t)), "median_t_cm": float(np.median(t)), "median_R_deg": float(np.median(r)),
           "failed": int(np.isinf(t).sum())}
    for tc, rd in THRESHOLDS:
        out[f"acc_{tc:g}cm_{rd:g}deg"] = float(100 * np.mean((t <= tc) & (r <= rd)))
    return out


def line_stats(runs: list[dict]) -> dict:
    pl = [q["point+line"] for res in runs for q in res["queries"].values() if "n_line_matches_correct" in q.get("point+line", {})]
    if not pl:
        return {}
    tot = {k: sum(p[k] for p in pl) for k in ("n_line_matches", "n_line_matches_correct", "n_line_inliers", "n_line_inliers_correct")}
    ms = [p["line_stage_ms"] for p in pl if p.get("line_stage_ms") is not None]
    return {"median_matches": float(np.median([p["n_line_matches"] for p in pl])),
            "median_correct": float(np.median([p["n_line_matches_correct"] for p in pl])),
            "match_precision": tot["n_line_matches_correct"] / max(tot["n_line_matches"], 1),
            "inlier_precision": tot["n_line_inliers_correct"] / max(tot["n_line_inliers"], 1),
            "median_ms_line_stage": float(np.median(ms)) if ms else None}


def cell(s: dict) -> str:
    if not np.isfinite(s["median_t_cm"]):
        return f"failed ({s['failed']} of {s['n']}) / {s['acc_1cm_1deg']:.0f}, {s['acc_2cm_2deg']:.0f}, {s['acc_5cm_5deg']:.0f}"
    return (f"{s['median_t_cm']:.2f} / {s['median_R_deg']:.2f} / "
            f"{s['acc_1cm_1deg']:.0f}, {s['acc_2cm_2deg']:.0f}, {s['acc_5cm_5deg']:.0f}")


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--matches", default="all,10", help="comma separated point-match budgets per query ('all' = no limit)")
    ap.add_argument("--match-seeds", default="0,1,2,3,4", help="draws of each finite budget, pooled")
    ap.add_argument("--method", default=LocalizationConfig().map_method)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--line-query", default="projection")
    ap.add_argument("--pose-source", default="posetxt")
    ap.add_argument("--points", default="sift-n4096")
    ap.add_argument("--label", default=None)
    ap.add_argument("--hloc", type=Path, default=None, help="points from hloc's output tree (as eval --hloc)")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    results.require_clean()  # before the run: figures from a dirty tree reproduce from no commit
    rows, runs = [], {}
    seeds = [int(s) for s in args.match_seeds.split(",")]
    for m in args.matches.split(","):
        n = None if m == "all" else int(m)
        per_seed = []
        for seed in ([0] if n is None else seeds):
            conf = LocalizationConfig(max_point_matches=n, match_seed=seed, map_method=args.method, mapping=args.preset,
                                      points=args.points, line_query=replace(LineQueryConfig(), method=args.line_query))
            path = run_eval(args.dataset, args.root, [args.scene], args.out, conf, pose_source=args.pose_source,
                            hloc_dir=args.hloc)
            per_seed.append(json.loads((path.parent / args.scene / "results.json").read_text()))
        pt, pl, ls = pooled(per_seed, "point"), pooled(per_seed, "point+line"), line_stats(per_seed)
        paired = paired_comparison(errors(per_seed, "point"), errors(per_seed, "point+line"))
        runs[m] = {"point": pt, "point+line": pl, "paired": paired, "lines": ls, "map": per_seed[0]["map"],
                   "match_seeds": None if n is None else seeds, "summaries": [r["summary"] for r in per_seed],
                   "t_cm": {k: errors(per_seed, k).tolist() for k in ("point", "point+line")}}
        n_q = len(per_seed[0]["queries"])
        map_cell = f"{args.method} `{args.preset}`" if args.method == "lipmap" else args.method
        if args.line_query != "projection":
            map_cell += f" ({args.line_query} query)"
        first = not rows
        rows.append([(args.label or f"{args.scene} ({n_q} queries)") if first else "", args.pose_source if first else "",
                     f"{map_cell}, {per_seed[0]['map']['n_lines']} lines" if first else "",
                     m if n is None else f"{m} ({len(seeds)} draws)", cell(pt), cell(pl),
                     f"{paired['b_better']} / {paired['b_worse']}, {paired['p_b_worse']:.2g}",
                     f"{ls['median_matches']:.0f} / {ls['median_correct']:.0f} ({100 * ls['match_precision']:.0f} %); "
                     f"{100 * ls['inlier_precision']:.0f} %" if ls else "", f"{ls.get('median_ms_line_stage') or 0:.0f}"])
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    name = f"localization-{args.dataset}-{args.scene}-{args.method}-{args.pose_source}" + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"scene": args.scene, "dataset": args.dataset, "runs": runs, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
