"""Where a query's line stage spends its time, component by component, on one scene.

    python benchmarks/perf/bench_line_stage.py --dataset 7scenes --root DATA/heldout --scene redkitchen-heldout \
        --out OUT --pose-source sfm --matches 10 [--runs 3] [--match-seeds 0,1,2,3,4] [--config JSON --tag TAG]

The map, point map and query lines come from a ``lipmap-loc eval`` run into OUT with the default settings (built
there when missing), as in ``benchmarks/localization_variants.py``. Every query of every draw is localized with the
defaults while the parts of the line stage are timed:

* ``hypotheses``: P3P poses of the point matches scored by the map lines (weak queries only);
* ``rescue query`` / ``rescue PnPL``: the wide-gate line queries (with their visibility tests) and the PnPL RANSAC
  (``solver``: about the start, or PoseLib's) and robust refinements of each rescue start;
* ``visibility``, ``narrow query``, ``narrow PnPL``: the narrowing rounds every query goes through (a rescued
  pose's round only queries the lines that confirm it: no PnPL).

Per query the parts add up to its line stage (``line_stage_ms`` of the eval's records) up to the glue between them;
the rescue's starts run on ``LineRescueConfig.threads`` threads, and its parts sum their threads' time, which can
exceed the wall time they take.
Figures are medians over queries (rescued and not rescued apart), then the median of ``--runs`` runs; written to
``benchmarks/results/perf-line-stage-<scene>-<N>[-<tag>].json``.
"""
from __future__ import annotations

import json
import statistics
import sys
import threading
import time
from argparse import Namespace
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402

PARTS = ("hypotheses", "rescue query", "rescue PnPL", "visibility", "narrow query", "narrow PnPL")
HEADER = ["scene", "point matches", "queries (per run)", "line stage ms", *(f"{p} ms" for p in PARTS)]


class PartTimer:
    """Wraps the functions the line stage calls and sums their time per query, by part."""

    def __init__(self, lq):
        import localization.query as P

        self.P, self.lq, self.t, self.in_rescue = P, lq, defaultdict(float), False
        self.local, self.lock = threading.local(), threading.Lock()  # the rescue's starts run on threads
        self.saved = [(P, "line_verified_poses"), (P, "pnpl_pose"), (P, "local_pnpl_pose"), (P, "refine_pnpl_pose"),
                      (P, "pnpl_near_start"), (P, "rescue_pose"), (lq, "match"), (lq, "visible_lines")]
        self.originals = [getattr(o, n) for o, n in self.saved]
        self._wrap(P, "line_verified_poses", lambda: "hypotheses")
        self._wrap(P, "pnpl_pose", lambda: "rescue PnPL" if self.in_rescue else "narrow PnPL")
        self._wrap(P, "local_pnpl_pose", lambda: "narrow PnPL")
        self._wrap(lq, "match", lambda: "rescue query" if self.in_rescue else "narrow query")
        self._wrap(P, "refine_pnpl_pose", lambda: "rescue PnPL")
        self._wrap(P, "pnpl_near_start", lambda: "rescue PnPL")
        self._wrap(lq, "visible_lines", lambda: "rescue query" if self.in_rescue else "visibility")
        rescue = P.rescue_pose

        def flagged(*a, **k):
            self.in_rescue = True
            try:
                return rescue(*a, **k)
            finally:
                self.in_rescue = False

        P.rescue_pose = flagged

    def _wrap(self, owner, name, part):
        f = getattr(owner, name)

        def timed(*a, **k):
            depth = getattr(self.local, "depth", 0)
            key = part() if depth == 0 else None  # a call inside a timed one (visibility in a query) counts there
            self.local.depth = depth + 1
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                self.local.depth = depth
                if key is not None:
                    with self.lock:
                        self.t[key] += (time.perf_counter() - t) * 1000

        setattr(owner, name, timed)

    def take(self) -> dict:
        out = dict(self.t)
        self.t.clear()
        return out

    def restore(self):
        for (o, n), f in zip(self.saved, self.originals):
            setattr(o, n, f)


def run_once(scene, points, lq, lines, conf, seeds) -> dict:
    from localization.query import localize_query

    timer = PartTimer(lq)
    rows = {"rescued": defaultdict(list), "not rescued": defaultdict(list)}
    try:
        for seed in seeds:
            c = replace(conf, match_seed=seed)
            for v in scene.query:
                timer.take()
                rec = localize_query(v.name, v.camera, points, lines[v.name], lq, c)
                parts = timer.take()
                pl = rec["point+line"]
                if "line_stage_ms" not in pl:
                    continue
                # a weak query goes through the rescue, whether or not it finds a pose
                group = rows["rescued" if pl.get("rescued") or "hypotheses" in parts else "not rescued"]
                group["line stage"].append(pl["line_stage_ms"])
                for p in PARTS:
                    group[p].append(parts.get(p, 0.0))
    finally:
        timer.restore()
    return {g: {k: float(np.median(v)) for k, v in r.items()} | {"queries": len(r["line stage"])}
            for g, r in rows.items() if r}


def main(argv=None):
    from lipmap.datasets import load_scene
    from localization.cli import _mapping_conf
    from localization.config import LocalizationConfig
    from localization_variants import eval_inputs, variant_config

    ap = results.scene_parser(__doc__)
    ap.add_argument("--pose-source", default="posetxt")
    ap.add_argument("--matches", type=lambda s: None if s == "all" else int(s), default=10,
                    help="point matches per query ('all': every match)")
    ap.add_argument("--match-seeds", default="0,1,2,3,4")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--tag", default="", help="suffix of the results file (e.g. the commit of another checkout)")
    ap.add_argument("--config", default="{}", metavar="JSON",
                    help="overrides of LocalizationConfig, as a variant of localization_variants.py")
    args = ap.parse_args(argv)

    scene = load_scene(args.dataset, args.root, args.scene, pose_source=args.pose_source)
    scene_dir = args.out / args.dataset / args.scene
    base = LocalizationConfig(max_point_matches=args.matches,
                              mapping=_mapping_conf(Namespace(preset=LocalizationConfig().mapping, keyframes=None)))
    points, linemap, lq, lines = eval_inputs(scene, scene_dir, base)
    seeds = [int(s) for s in args.match_seeds.split(",")] if args.matches is not None else [0]
    over = json.loads(args.config)
    base = variant_config(base, over)
    run_once(scene, points, lq, lines, base, seeds[:1])  # warm-up: caches, imports
    runs = [run_once(scene, points, lq, lines, base, seeds) for _ in range(args.runs)]
    out, rows = {}, []
    for group in runs[0]:
        out[group] = {k: statistics.median(r[group][k] for r in runs) for k in runs[0][group]}
        rows.append([args.scene, "all" if args.matches is None else args.matches, f"{group} ({out[group]['queries']})",
                     *(f"{out[group][k]:.1f}" for k in ("line stage", *PARTS))])
        print(f"{args.scene}, {'all' if args.matches is None else args.matches} matches, {group} ({out[group]['queries']} per run): median ms "
              + ", ".join(f"{k} {out[group][k]:.1f}" for k in ("line stage", *PARTS)))
    results.write(f"perf-line-stage-{args.scene}-{'all' if args.matches is None else args.matches}" + (f"-{args.tag}" if args.tag else ""),
                  {"scene": args.scene, "dataset": args.dataset, "overrides": over, "pose_source": args.pose_source, "matches": args.matches,
                   "match_seeds": seeds, "runs": args.runs, "map_lines": len(linemap), "median_ms": out,
                   "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
