"""Where the line rescue of weak queries loses them: the point matches, the starts, RANSAC, or the choice.

    python benchmarks/rescue_starts.py --dataset 7scenes --root DATA/heldout --scene redkitchen-heldout --out OUT \
        --pose-source sfm --matches 10 [--method lipmap|lift] [--match-seeds 0,1,2,3,4] [--config JSON --tag TAG] \
        [--truth-start]

The inputs come from a ``lipmap-loc eval`` run into OUT (built there when missing), as in
``benchmarks/localization_variants.py``. Every query of every draw is localized with the defaults (or ``--config``)
and its line rescue traced (``localize_query(trace=...)``). For the queries that go through the rescue, checked
against the ground-truth pose, each row gives the share with:

* at least 3 / 2 right point matches (within the rescue's point threshold at the ground truth): what P3P and the
  two-point hypotheses need;
* a start within 5 / 15 cm (the point-only pose and the hypotheses, after ``distinct_poses``);
* some start whose rescued pose (after the rescue's last stage) lies within 5 cm (the best the choice among starts
  could do);
* the chosen (highest-scoring) rescued pose within 5 cm, and the final point+line pose within 5 cm;

the starts per query, and the rescued poses that stood split by their last round's line inliers (fewer than 20 or
not: how many, and the share within 5 cm; run with ``min_final_lines`` 0 to see them all). With ``--truth-start`` the true pose is one more start: what the rescue and the narrowing
rounds make of a perfect start (the starts' share of the loss is the difference). Written to
``benchmarks/results/rescue-starts-<scene>-<method>-<N>[-<tag>].json``.
"""
from __future__ import annotations

import json
import sys
from argparse import Namespace
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402

FINAL_LINES = 20  # the split of the rescued poses by their last round's line inliers (LineRescueConfig.min_final_lines)
HEADER = ["scene", "line map", "point matches", "weak queries", "≥3 / ≥2 right point matches", "a start within 5 / 15 cm",
          "some start's rescued pose within 5 cm", "chosen rescued pose within 5 cm", "final within 5 cm (median cm)", "starts per query",
          f"rescued poses with < / >= {FINAL_LINES} line inliers: n (within 5 cm)"]


def query_outcome(rec: dict, trace: list, T_gt: np.ndarray, camera, point_px: float) -> dict | None:
    """What one query's traced rescue reached, against its ground-truth pose (None: no rescue ran)."""
    from lipmap import geometry as geo
    from lipmap.poses import pose_errors

    stage0 = [(i, t) for i, t in enumerate(trace) if t.get("stage") == 0]
    if not stage0:
        return None
    pm = next(t["point_matches"] for t in trace if "point_matches" in t)
    uv, z = geo.project_points(pm.p3d, T_gt, camera)
    right = int(np.sum((z > 0) & (np.linalg.norm(uv - pm.p2d, axis=1) <= point_px)))

    def err(T):
        return pose_errors(T_gt, np.asarray(T))[0] if T is not None else np.inf

    last = {t["origin"]: t for t in trace if "origin" in t}  # each start's last stage: its rescued pose and score
    ends = [last.get(i, t) for i, t in stage0]
    starts = [err(t["start"]) for _, t in stage0]
    pnpl = [err(t["result"]["cam_from_world"]) if t["kept"] else np.inf for t in ends]
    scores = [t["score"] for t in ends]
    chosen = pnpl[int(np.argmax(scores))] if max(scores) >= 0 else np.inf
    final = rec["point+line"].get("cam_from_world")
    pl = rec["point+line"]
    return {"right_points": right, "start_m": min(starts), "best_pnpl_m": min(pnpl), "chosen_pnpl_m": chosen,
            "final_m": err(final), "starts": len(stage0),
            "final_lines": pl.get("n_line_inliers", 0) if pl.get("success") and pl.get("rescued") else -1}


def summarize(outcomes: list) -> dict:
    """Shares (%) over the traced queries, as in the table's columns."""
    o = [x for x in outcomes if x is not None]
    if not o:
        return {"weak_queries": 0}
    col = {k: np.array([x[k] for x in o], dtype=float) for k in o[0]}
    pct = lambda m: float(100 * np.mean(m))  # noqa: E731
    return {"weak_queries": len(o), "right_points_ge3": pct(col["right_points"] >= 3),
            "right_points_ge2": pct(col["right_points"] >= 2), "start_5cm": pct(col["start_m"] <= 0.05),
            "start_15cm": pct(col["start_m"] <= 0.15), "best_pnpl_5cm": pct(col["best_pnpl_m"] <= 0.05),
            "chosen_pnpl_5cm": pct(col["chosen_pnpl_m"] <= 0.05), "final_5cm": pct(col["final_m"] <= 0.05),
            "final_median_cm": float(100 * np.median(col["final_m"])),
            "starts_per_query": float(np.mean(col["starts"])), **_by_final_lines(col)}


def _by_final_lines(col: dict, cut: int = FINAL_LINES) -> dict:
    """The rescued poses (those that stood) with fewer / at least ``cut`` line inliers in their last narrowing round:
    how many, and the share of them within 5 cm."""
    out = {}
    for key, m in (("few", (col["final_lines"] >= 0) & (col["final_lines"] < cut)), ("many", col["final_lines"] >= cut)):
        out[f"final_lines_{key}"] = int(m.sum())
        out[f"final_lines_{key}_5cm"] = float(100 * np.mean(col["final_m"][m] <= 0.05)) if m.any() else 0.0
    return out


def row(scene: str, method: str, matches, s: dict) -> list:
    if not s["weak_queries"]:
        return [scene, method, str(matches), "0", "", "", "", "", "", "", ""]
    return [scene, method, str(matches), str(s["weak_queries"]), f"{s['right_points_ge3']:.0f} / {s['right_points_ge2']:.0f} %",
            f"{s['start_5cm']:.0f} / {s['start_15cm']:.0f} %", f"{s['best_pnpl_5cm']:.0f} %", f"{s['chosen_pnpl_5cm']:.0f} %",
            f"{s['final_5cm']:.0f} % ({s['final_median_cm']:.2f})", f"{s['starts_per_query']:.1f}",
            f"{s['final_lines_few']} ({s['final_lines_few_5cm']:.0f} %) / {s['final_lines_many']} ({s['final_lines_many_5cm']:.0f} %)"]


def trace_scene(scene, points, lq, lines, conf, seeds, truth_start: bool = False) -> list:
    """:func:`query_outcome` of every query of every draw (``truth_start``: the true pose is a start too)."""
    from localization.query import localize_query

    out = []
    for seed in seeds:
        c = replace(conf, match_seed=seed)
        for v in scene.query:
            trace = []
            rec = localize_query(v.name, v.camera, points, lines[v.name], lq, c, trace=trace,
                                 priors=[v.cam_from_world] if truth_start else ())
            out.append(query_outcome(rec, trace, v.cam_from_world, v.camera, c.line_rescue.max_point_error))
    return out


def main(argv=None):
    from lipmap.datasets import load_scene
    from localization.cli import _mapping_conf
    from localization.config import LocalizationConfig
    from localization_variants import eval_inputs, variant_config

    ap = results.scene_parser(__doc__)
    ap.add_argument("--method", default=LocalizationConfig().map_method)
    ap.add_argument("--pose-source", default="posetxt")
    ap.add_argument("--matches", type=int, default=10, help="point matches per query")
    ap.add_argument("--match-seeds", default="0,1,2,3,4")
    ap.add_argument("--config", default="{}", metavar="JSON", help="overrides of LocalizationConfig (as a variant)")
    ap.add_argument("--truth-start", action="store_true",
                    help="the true pose is a start too: what the rescue and the rounds make of a perfect start")
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)

    scene = load_scene(args.dataset, args.root, args.scene, pose_source=args.pose_source)
    base = LocalizationConfig(max_point_matches=args.matches, map_method=args.method,
                              mapping=_mapping_conf(Namespace(preset=LocalizationConfig().mapping, keyframes=None)))
    points, _, lq, lines = eval_inputs(scene, args.out / args.dataset / args.scene, base)
    over = json.loads(args.config)
    seeds = [int(s) for s in args.match_seeds.split(",")]
    s = summarize(trace_scene(scene, points, lq, lines, variant_config(base, over), seeds, args.truth_start))
    r = row(args.scene, args.method, args.matches, s)
    print("| " + " | ".join(HEADER) + " |\n| " + " | ".join(r) + " |")
    results.write(f"rescue-starts-{args.scene}-{args.method}-{args.matches}" + (f"-{args.tag}" if args.tag else ""),
                  {"scene": args.scene, "dataset": args.dataset, "method": args.method, "pose_source": args.pose_source,
                   "matches": args.matches, "match_seeds": seeds, "overrides": over, "truth_start": args.truth_start,
                   "summary": s,
                   "table": {"header": HEADER, "rows": [r]}})


if __name__ == "__main__":
    main()
