"""What each localization setting is worth: named overrides of ``LocalizationConfig``, side by side, on one scene.

    python benchmarks/localization_variants.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--method lipmap|lift] [--pose-source posetxt|sfm] [--matches 10] \
        [--match-seeds 0,1,2,3,4] [--tag TAG] [--keyframes CM,DEG|0] [--hloc DIR] 'default={}' 'margin0={"line_query": {"min_margin": 0}}' ...

The map, point map and query lines come from a ``lipmap-loc eval`` run into OUT with the default settings (built
there when missing). Each variant then localizes every query in memory, without journals, for every draw of the
point budget, and the figures pool the draws (as ``localization_table.py``). A ``--mapping`` override that changes
only what is made from the planes (extraction, tracks, on-plane lines) reuses the default map's planes, as ``eval`` does. Overrides are JSON objects of
``LocalizationConfig`` fields; ``line_query`` and ``point_line_pose`` take dicts of their own fields. Prints a
table and writes ``benchmarks/results/localization-variants-<dataset>-<scene>-<method>-<pose source>-<N>.json``.

Each variant is compared per localization (``localization.evaluate.paired_comparison``): its point+line against its
point-only pose, and against the first variant's point+line: how many each wins, and the one-sided signed-rank p that
it is worse. ``--hloc DIR`` takes the points from hloc's output tree, as ``eval --hloc``.
"""
from __future__ import annotations

import json
import sys
from argparse import Namespace
from dataclasses import replace
from pathlib import Path

import numpy as np

from lipmap.datasets import load_scene
from lipmap.lines2d import load_lines
from lipmap.poses import pose_errors
from localization.cli import _keyframes, _mapping_conf
from localization.config import LocalizationConfig
from localization.evaluate import paired_comparison
from localization.linequery import LineQuery
from localization.pipeline import open_points, query_lines_file, scene_linemap
from localization.query import localize_query

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["variant", "overrides", "point-only: median cm / % at 1, 2, 5 cm", "point+line: same",
          "point+line against point-only: better / worse, p(worse)", "against the first variant: same",
          "line matches / correct (precision)", "line stage ms"]


def variant_config(base: LocalizationConfig, over: dict) -> LocalizationConfig:
    over = dict(over)
    lq, pl, rs = over.pop("line_query", {}), over.pop("point_line_pose", {}), dict(over.pop("line_rescue", {}))
    if "hypotheses" in rs:
        hyp = dict(rs["hypotheses"])
        if "lines_first" in hyp:
            hyp["lines_first"] = replace(base.line_rescue.hypotheses.lines_first, **hyp["lines_first"])
        rs["hypotheses"] = replace(base.line_rescue.hypotheses, **hyp)
    if "near" in rs:
        rs["near"] = replace(base.line_rescue.near, **rs["near"])
    for key in ("line_gates", "strong_gates"):
        if key in over:
            over[key] = tuple(tuple(float(x) for x in g) for g in over[key])
    return replace(base, **over, line_query=replace(base.line_query, **lq),
                   point_line_pose=replace(base.point_line_pose, **pl), line_rescue=replace(base.line_rescue, **rs))


def _cell(t: np.ndarray) -> str:
    med = np.median(t)
    acc = " / ".join(f"{100 * np.mean(t <= c):.0f}" for c in (1.0, 2.0, 5.0))
    return f"{med:.2f} / {acc}" if np.isfinite(med) else f"failed / {acc}"


def run_variant(scene, points, lq, lines, conf: LocalizationConfig, seeds) -> dict:
    t = {"point": [], "point+line": []}
    r = {"point": [], "point+line": []}
    ms, n_m, n_ok, rescued = [], 0, 0, []
    for seed in seeds:
        c = replace(conf, match_seed=seed)
        for v in scene.query:
            rec = localize_query(v.name, v.camera, points, lines[v.name], lq, c, cam_from_world_gt=v.cam_from_world)
            for key in t:
                T = rec[key].get("cam_from_world") if rec[key].get("success") else None
                dt, dr = pose_errors(v.cam_from_world, np.array(T)) if T else (np.inf, np.inf)
                t[key].append(dt * 100)
                r[key].append(dr)
            pl = rec["point+line"]
            if "line_stage_ms" in pl:
                ms.append(pl["line_stage_ms"])
            rescued.append(bool(pl.get("rescued")))
            n_m += pl.get("n_line_matches", 0)
            n_ok += pl.get("n_line_matches_correct", 0)
    return {"t_cm": {k: np.asarray(x) for k, x in t.items()}, "R_deg": {k: np.asarray(x) for k, x in r.items()},
            "line_ms": float(np.median(ms)) if ms else None, "line_ms_all": ms, "rescued": rescued,
            "line_matches": n_m, "line_matches_correct": n_ok}


def _paired(c: dict) -> str:
    return f"{c['b_better']} / {c['b_worse']}, {c['p_b_worse']:.2g}"


def eval_inputs(scene, scene_dir: Path, base: LocalizationConfig, hloc_dir=None):
    """(point source, line map, its LineQuery, {query name: 2D lines}) of a ``lipmap-loc eval`` run with ``base`` into
    ``scene_dir`` (built there when missing)."""
    points = open_points(scene, scene_dir, base, hloc_dir)
    qlines = query_lines_file(scene, scene_dir, base)
    linemap, _ = scene_linemap(scene, scene_dir, base)
    return points, linemap, LineQuery.from_linemap(linemap), {v.name: load_lines(qlines, v.name) for v in scene.query}


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--method", default=LocalizationConfig().map_method)
    ap.add_argument("--pose-source", default="posetxt")
    ap.add_argument("--matches", type=lambda s: None if s == "all" else int(s), default=10,
                    help="point matches per query ('all': every match)")
    ap.add_argument("--hloc", type=Path, default=None, help="points from hloc's output tree (as eval --hloc)")
    ap.add_argument("--match-seeds", default="0,1,2,3,4")
    ap.add_argument("--tag", default="", help="suffix of the results file, to keep another set of variants beside")
    ap.add_argument("--keyframes", default=None, type=_keyframes, help="the map's keyframe thresholds CM,DEG, or 0 for every view "
                                                      "(as lipmap-loc eval; default: the preset's)")
    ap.add_argument("--mapping", default=None, metavar="JSON",
                    help="overrides of the map's settings, e.g. '{\"refine\": {\"enabled\": true}}' (default: the preset's)")
    ap.add_argument("variants", nargs="+", help="NAME=JSON overrides of LocalizationConfig ('{}' for the defaults)")
    args = ap.parse_args(argv)
    results.require_clean()  # before the run: figures from a dirty tree reproduce from no commit

    scene = load_scene(args.dataset, args.root, args.scene, pose_source=args.pose_source)
    scene_dir = args.out / args.dataset / args.scene
    base = LocalizationConfig(max_point_matches=args.matches, map_method=args.method,
                              mapping=_mapping_conf(Namespace(preset=LocalizationConfig().mapping, keyframes=args.keyframes),
                                                    **json.loads(args.mapping or "{}")))
    points, linemap, lq, lines = eval_inputs(scene, scene_dir, base, args.hloc)
    seeds = [int(s) for s in args.match_seeds.split(",")] if args.matches is not None else [0]

    rows, out, first = [], {}, None
    for spec in args.variants:
        name, _, js = spec.partition("=")
        over = json.loads(js or "{}")
        r = run_variant(scene, points, lq, lines, variant_config(base, over), seeds)
        prec = r["line_matches_correct"] / max(r["line_matches"], 1)
        n_loc = len(r["t_cm"]["point"])
        first = first or r
        vs_point = paired_comparison(r["t_cm"]["point"], r["t_cm"]["point+line"])
        vs_first = paired_comparison(first["t_cm"]["point+line"], r["t_cm"]["point+line"])
        rows.append([name, f"`{json.dumps(over)}`" if over else "defaults", _cell(r["t_cm"]["point"]),
                     _cell(r["t_cm"]["point+line"]), _paired(vs_point), _paired(vs_first) if r is not first else "",
                     f"{r['line_matches'] / n_loc:.0f} / {100 * prec:.0f} %",
                     f"{r['line_ms']:.0f}" if r["line_ms"] is not None else ""])
        out[name] = {"overrides": over, "median_t_cm": {k: float(np.median(x)) for k, x in r["t_cm"].items()},
                     "line_matches_per_query": r["line_matches"] / n_loc, "line_match_precision": prec,
                     "median_ms_line_stage": r["line_ms"], "vs_point_only": vs_point, "vs_first": vs_first,
                     "R_deg": {k: x.tolist() for k, x in r["R_deg"].items()}, "rescued": r["rescued"],
                     # per localization (draw-major, queries in scene order; inf: no pose), for localization_cdf.py
                     "t_cm": {k: x.tolist() for k, x in r["t_cm"].items()}}
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    name = f"localization-variants-{args.dataset}-{args.scene}-{args.method}-{args.pose_source}-{args.matches if args.matches is not None else 'all'}"
    name += f"-{args.tag}" if args.tag else ""
    results.write(name, {"scene": args.scene, "dataset": args.dataset, "method": args.method, "matches": args.matches,
                         "points": "hloc" if args.hloc else "built-in",
                         "match_seeds": seeds, "variants": out, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
