"""The README's headline table: our point-only and point+line localization beside the paper's rows.

    python benchmarks/headline_table.py [--runs NAME,NAME] [--scene redkitchen]

Reads the ``localization_table.py`` results named by ``--runs`` (``benchmarks/results/<NAME>.json``) and the
paper's table (``benchmarks/7scenes/paper_table.json``) and writes ``benchmarks/results/headline-7scenes.json``.
Cells are the paper's: median translation cm / median rotation deg / % within 5 cm and 5 deg. The paper's rows are
its full test split of the scene (thousands of queries, SuperPoint + SuperGlue points, pose.txt ground truth); ours
are the scenes the runs name, so the two sides share a method, not a query set. A run made on a tree with
uncommitted changes is refused (it reproduces from no commit).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

PAPER = Path(__file__).resolve().parent / "7scenes" / "paper_table.json"
DEFAULT_RUNS = ("localization-7scenes-redkitchen-lipmap-posetxt,localization-7scenes-redkitchen-heldout-lipmap-sfm,"
                "localization-synthetic-room-s0-lipmap-posetxt-hloc")
PAPER_COLUMNS = ("Hloc (point)", "LiP-Map (point+line)")


def cell(s: dict) -> str:
    if s["median_t_cm"] == float("inf") or s["median_t_cm"] != s["median_t_cm"]:
        return f"failed ({s['failed']} of {s['n']}) / {s['acc_5cm_5deg']:.0f} %"
    return f"{s['median_t_cm']:.2f} / {s['median_R_deg']:.2f} / {s['acc_5cm_5deg']:.0f} %"


def paired_cell(p) -> str:
    """Queries point+line localizes better / worse than point-only, and the one-sided signed-rank p that it is worse."""
    return "" if not p else f"{p['b_better']} / {p['b_worse']} (p {p['p_b_worse']:.2g})"


def paper_cell(v) -> str:
    return f"{v[0]:g} / {v[1]:g} / {v[2]:g} %"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default=DEFAULT_RUNS, help="localization_table.py results, comma separated")
    ap.add_argument("--scene", default="redkitchen", help="the paper's scene shown beside them")
    args = ap.parse_args(argv)
    results.require_clean()
    paper = json.loads(PAPER.read_text())["scenes"][args.scene]
    header = ["queries", "ground truth", "point matches", "ours, point-only", "ours, point+line",
              "per query: point+line better / worse", *(f"paper ({args.scene}, full test split): {c}" for c in PAPER_COLUMNS)]
    rows, sources = [], {}
    for name in args.runs.split(","):
        r = results.read(name)
        prov = r["provenance"]
        if prov.get("dirty") and results.os.environ.get(results.ALLOW_DIRTY_ENV) != "1":
            raise SystemExit(f"{name} was measured on a tree with uncommitted changes (commit {prov['commit']}): "
                             "measure it again from a clean commit")
        sources[name] = {"commit": prov["commit"], "dirty": bool(prov.get("dirty"))}
        first_row = r["table"]["rows"][0]
        for i, (budget, run) in enumerate(r["runs"].items()):
            draws = run.get("match_seeds")
            rows.append([first_row[0] if i == 0 else "", first_row[1] if i == 0 else "",
                         budget if not draws else f"{budget} ({len(draws)} draws)", cell(run["point"]),
                         cell(run["point+line"]), paired_cell(run.get("paired")),
                         *((paper_cell(paper[c]) for c in PAPER_COLUMNS) if not rows else ("", ""))])
    results.write("headline-7scenes", {"scene": args.scene, "runs": sources, "table": {"header": header, "rows": rows}})


if __name__ == "__main__":
    main()
