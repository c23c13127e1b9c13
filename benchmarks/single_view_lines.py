"""Why a lipmap map's on-plane lines are seen in one image: where the track builder looks for them, and what it finds.

    python benchmarks/single_view_lines.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out MAP_DIR

``MAP_DIR`` is a ``lipmap-loc map`` output (``linemap.h5`` and ``lines2d.h5``). For every on-plane line tracked in one
image, each other mapping view where it is visible (inside the image, not hidden by the planes: the track builder's
own test) is searched for a detection that overlaps its projection by more than 0.2; the table gives the share of
those (line, view) pairs whose nearest such detection lies within each angle / distance gate (the track builder
uses 0.01 rad and 2 px). Then the map with and without the single-image on-plane lines against the scene's ground
truth (F@5cm, R@50mm, median images per line). Writes ``benchmarks/results/single-view-lines-<scene>.json``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

GATES = ((0.01, 2.0), (0.02, 2.0), (0.03, 3.0), (0.05, 4.0), (0.1, 6.0))


def nearest_in_view(lines: np.ndarray, cand: np.ndarray, view, det: np.ndarray, caster):
    """Of the lines ``cand`` (indices into ``lines`` (N, 2, 3)), those visible in ``view`` (inside the image, not hidden
    by the planes: the track builder's own test), and per such line the angle (rad) and max endpoint distance (px) to
    the detection of ``det`` (M, 4) that overlaps its projection (> 0.2) and is nearest in max(angle / 0.01,
    distance / 2); inf where none overlaps."""
    from lipmap import geometry as geo
    from lipmap.mapping.assign import visible_lines

    cand = np.asarray(cand, dtype=np.int64)
    vis = cand[visible_lines(lines[cand], view.cam_from_world, view.camera, caster, 0.05)] if len(cand) else cand
    if not len(vis) or not len(det):
        return vis, np.full(len(vis), np.inf), np.full(len(vis), np.inf)
    proj, _ = geo.project_segments(lines[vis], view.cam_from_world, view.camera)
    with np.errstate(invalid="ignore"):
        ov = geo.pairwise_overlap_ratio(proj, det) > 0.2
        A = np.where(ov, geo.pairwise_angle_distance(proj, det), np.inf)
        D = np.where(ov, geo.pairwise_perpendicular_distance(proj, det, "max"), np.inf)
    j = np.argmin(np.maximum(A / 0.01, D / 2.0), 1)
    return vis, A[np.arange(len(vis)), j], D[np.arange(len(vis)), j]


def nearest_detections(lines: np.ndarray, source: list, views, lines_by_view: dict, caster):
    """Per (line, other view where it is visible): :func:`nearest_in_view`'s angle and distance; a line is not looked
    for in its ``source`` view."""
    ang, dist, n_vis = [], [], np.zeros(len(lines), int)
    source = np.asarray(source, dtype=object)
    for v in views:
        det = np.asarray(lines_by_view.get(v.name, np.zeros((0, 4))), float)
        if not len(det):
            continue
        vis, a, d = nearest_in_view(lines, np.flatnonzero(source != v.name), v, det, caster)
        n_vis[vis] += 1
        ang.append(a)
        dist.append(d)
    return np.concatenate(ang) if ang else np.zeros(0), np.concatenate(dist) if dist else np.zeros(0), n_vis


def main(argv=None):
    from lipmap.datasets import load_scene
    from lipmap.evaluation import evaluate_linemap, load_ground_truth, scene_ground_truth
    from lipmap.lines2d import list_names, load_lines
    from lipmap.linemap import LineMap, edge_line_mask
    from lipmap.mapping.assign import PlaneRaycaster

    args = results.scene_parser(__doc__).parse_args(argv)
    lm = LineMap.load(args.out / "linemap.h5")
    names = set(list_names(args.out / "lines2d.h5"))
    scene = load_scene(args.dataset, args.root, args.scene, pose_source=lm.metadata.get("pose_source", "posetxt"))
    views = [v for v in scene.mapping if v.name in names]
    lines_by_view = {v.name: load_lines(args.out / "lines2d.h5", v.name) for v in views}
    edges, n_img = edge_line_mask(lm), lm.supports[:, 0]
    single = np.flatnonzero(~edges & (n_img == 1))
    on_plane = int((~edges).sum())
    ang, dist, n_vis = nearest_detections(lm.lines[single], [lm.tracks[i][0][0] for i in single], views, lines_by_view,
                                          PlaneRaycaster(lm.planes["corners"]))
    share = {f"{a:g} rad / {d:g} px": float(np.mean((ang < a) & (dist < d))) if len(ang) else 0.0 for a, d in GATES}
    length = np.linalg.norm(lm.lines[:, 1] - lm.lines[:, 0], axis=1)
    gt = load_ground_truth(scene_ground_truth(scene))
    maps = {}
    for name, keep in (("map", np.ones(len(lm), bool)), ("without single-image on-plane lines", edges | (n_img > 1))):
        r = evaluate_linemap(lm.subset(keep), gt)
        maps[name] = {"lines": int(keep.sum()), "F@5cm": r["M1"]["line"]["f@0.05"], "R@50mm": r["M2"]["R@50mm"],
                      "median images": float(np.median(n_img[keep]))}
    summary = {"on_plane_lines": on_plane, "single_image": int(len(single)), "pairs": int(len(ang)),
               "median_other_views_visible": float(np.median(n_vis)) if len(n_vis) else 0.0,
               "median_length_m_single": float(np.median(length[single])) if len(single) else 0.0,
               "median_length_m_tracked_on_plane": float(np.median(length[~edges & (n_img > 1)])),
               "share_with_a_detection_within": share, "maps": maps}
    header = ["on-plane lines", "seen in one image", "other views where visible (median)", "(line, view) pairs",
              *(f"detection within {k}" for k in share)]
    row = [on_plane, len(single), f"{summary['median_other_views_visible']:.0f}", len(ang), *(f"{100 * v:.1f} %" for v in share.values())]
    for k, m in maps.items():
        print(f"{k}: {m['lines']} lines, F@5cm {m['F@5cm']:.3f}, R@50mm {m['R@50mm']:.0f}, median images {m['median images']:.0f}")
    print(" | ".join(header) + "\n" + " | ".join(map(str, row)))
    results.write(f"single-view-lines-{args.scene}", {**summary, "table": {"header": header, "rows": [row]}})


if __name__ == "__main__":
    main()
