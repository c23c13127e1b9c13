"""How many of a line map's track observations pass the paper's track test against the lines as they are.

    python benchmarks/track_audit.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out MAP_DIR [--label NAME] [--tag TAG]

``MAP_DIR`` holds a ``linemap.h5`` (a ``lipmap-loc map`` output; maps made before tracks were verified, or a
LIMAP import, show the difference). Each observation's detection is tested against the line's projection in its
image by the track builder's thresholds (0.01 rad, 2 px, overlap 0.2;
:func:`lipmap.mapping.extract.verify_tracks`), and the supports (images per line: median / mean) are given as
stored and as verified, for the whole map and, for a LiP-Map map, its plane edges and its on-plane lines.
Writes ``benchmarks/results/track-audit-<scene>[-<tag>].json``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["map", "lines", "observations", "pass the paper's test", "images per line, stored: median / mean",
          "verified: median / mean", "lines no image verifies"]


def audit(lm, views) -> tuple[list, dict]:
    """Rows (whole map, then its plane edges and on-plane lines when it has both) and their figures."""
    from lipmap.linemap import edge_line_mask
    from lipmap.mapping.extract import ExtractConfig, verify_tracks

    out = verify_tracks(lm, views, ExtractConfig())  # the paper's track thresholds
    edges = edge_line_mask(lm)
    parts = [("all", np.ones(len(lm), bool))]
    if edges.any() and not edges.all():
        parts += [("plane edges", edges), ("on-plane lines", ~edges)]
    rows, figures = [], {}
    for name, m in parts:
        before, after = lm.supports[m, 0], out.supports[m, 0]
        n_obs = int(lm.supports[m, 1].sum())
        f = {"lines": int(m.sum()), "observations": n_obs, "verified_observations": int(out.supports[m, 1].sum()),
             "images_median": float(np.median(before)), "images_mean": float(before.mean()),
             "verified_images_median": float(np.median(after)), "verified_images_mean": float(after.mean()),
             "lines_without_verified_support": int((after == 0).sum())}
        figures[name] = f
        rows.append([name, f["lines"], n_obs, f"{100 * f['verified_observations'] / max(n_obs, 1):.0f} %",
                     f"{f['images_median']:.0f} / {f['images_mean']:.1f}",
                     f"{f['verified_images_median']:.0f} / {f['verified_images_mean']:.1f}",
                     f["lines_without_verified_support"]])
    return rows, figures


def main(argv=None):
    from lipmap.datasets import load_scene
    from lipmap.linemap import LineMap

    ap = results.scene_parser(__doc__)
    ap.add_argument("--label", default=None, help="the map's name in the table (default: its method)")
    ap.add_argument("--tag", default="", help="suffix of the results file name")
    args = ap.parse_args(argv)
    lm = LineMap.load(args.out / "linemap.h5")
    scene = load_scene(args.dataset, args.root, args.scene, pose_source=lm.metadata.get("pose_source", "posetxt"))
    rows, figures = audit(lm, scene.mapping)
    label = args.label or f"{args.scene} {lm.metadata.get('method', 'map')}"
    rows = [[f"{label}: {r[0]}", *r[1:]] for r in rows]
    print(" | ".join(HEADER))
    print("\n".join(" | ".join(map(str, r)) for r in rows))
    name = f"track-audit-{args.scene}" + (f"-{args.tag}" if args.tag else "")
    results.write(name, {"scene": args.scene, "map": str(args.out / "linemap.h5"), "figures": figures,
                         "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
