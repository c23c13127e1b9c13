"""Point-only pose on the same 2D-3D matches: pycolmap's ``estimate_and_refine_absolute_pose`` with the options
hloc's ``localize_sfm`` passes, our PoseLib pose with the former defaults, and with the current ones.

    python benchmarks/point_pose_vs_pycolmap.py --hloc tests/data/hloc_7scenes/hloc_outputs/7scenes/room-s0 \
        --pairs tests/data/hloc_7scenes/datasets/7scenes/7scenes_densevlad_retrieval_top_10/room-s0_top10.txt \
        --gt tests/data/hloc_7scenes/datasets/7scenes/room-s0 --name fixture-hloc-sift --factors --seeds 5

    python benchmarks/point_pose_vs_pycolmap.py --hloc HLOC_OUT/7scenes/redkitchen-heldout \
        --pairs HLOC_DATA/7scenes_densevlad_retrieval_top_10/redkitchen-heldout_top10.txt \
        --gt DATA/redkitchen-heldout/pgt/sfm_redkitchen-heldout.txt --name redkitchen-heldout-hloc-sift \
        --factors --seeds 5 --factor-seeds 1

    python benchmarks/point_pose_vs_pycolmap.py --hloc OUT/7scenes/redkitchen-heldout/points-sift-n4096-<digest> \
        --pairs OUT/.../points-sift-n4096-<digest>/pairs-query-vlad64-top10_feats-sift-n4096.txt \
        --camera "PINHOLE 640 480 525.505 525.505 320 240" --gt DATA/redkitchen-heldout/pgt/sfm_redkitchen-heldout.txt \
        --name redkitchen-heldout-builtin-sift --factors --seeds 5 --factor-seeds 1

The matches of each query come from hloc-layout files (an SfM model, a features file, a query matches file and the
query pairs) through :func:`localization.points.point_matches_from_hloc`, the way ``localize_sfm`` builds them; every
method then sees the same 2D-3D matches and the same camera (``query_list_with_intrinsics.txt`` of the folder, or
``--camera``). Each method runs with RANSAC seeds ``0..seeds-1``; the errors of all (query, seed) runs are pooled
(a failure counts as infinitely wrong). ``--factors`` adds one row per factor of the difference (2D coordinates
rounded as hloc rounds them, match order, RANSAC threshold, refinement loss and scale, inliers vs all matches, each
library's RANSAC with the other's refinement). Ground truth: a pose list (``name qw qx qy qz tx ty tz [f]``,
cam_from_world: the 7-Scenes pseudo-GT lists, an hloc results file) or a scene folder whose ``pose.txt`` files are
the colour camera's (a depth-registered scene such as the synthetic ones). Written to
``benchmarks/results/point-pose-vs-pycolmap-<name>.json``.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402

from lipmap.errors import InputError  # noqa: E402
from lipmap.poses import invert_T, make_T, pose_errors  # noqa: E402
from lipmap.scene import Camera  # noqa: E402
from localization.estimate import PointPoseConfig, adaptive_loss_scale, estimate_pose_points  # noqa: E402
from localization.hloc_io import read_results  # noqa: E402

THRESHOLDS_CM = (1, 2, 5)
RANSAC_PX = 12.0  # hloc's localize_sfm ransac_thresh
OLD = PointPoseConfig(loss_scale=6.0)  # the former defaults: PoseLib's binding Cauchy scale, 0.5 x 12 px
NEW = PointPoseConfig()
RANSAC_ONLY = replace(OLD, bundle={"max_iterations": 0})  # PoseLib's LO-RANSAC pose (its LO already fits the inliers)


# ----------------------------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------------------------
def find_inputs(folder: Path, pairs: Path, sfm=None, features=None, matches=None) -> dict:
    """The model, features and query matches of an hloc scene folder (or of our ``points-*`` folder, same layout).

    Model: the one folder with images.bin other than ``sfm_sift`` (whose 2D points are not the features file's).
    Matches: the .h5 named after the pairs file (``*_<pairs stem>.h5``). Features: the .h5 whose name the matches
    file's starts with (``<features>_<matcher>_<pairs>.h5``).
    """
    folder = Path(folder)
    if sfm is None:
        models = sorted(p.parent for p in folder.glob("*/images.bin") if p.parent.name != "sfm_sift")
        if len(models) != 1:
            raise InputError(f"expected one SfM model besides sfm_sift, found {[m.name for m in models]}", folder,
                             "give one with --sfm")
        sfm = models[0]
    h5s = sorted(folder.glob("*.h5"))
    if matches is None:
        found = [p for p in h5s if p.stem.endswith("_" + Path(pairs).stem)]
        if len(found) != 1:
            raise InputError(f"no single matches file named after {Path(pairs).name}: {[p.name for p in found]}",
                             folder, "use --matches")
        matches = found[0]
    if features is None:
        found = [p for p in h5s if Path(matches).stem.startswith(p.stem + "_")]
        if len(found) != 1:
            raise InputError(f"no single features file that {Path(matches).name} is named after", folder,
                             "use --features")
        features = found[0]
    return {"sfm": Path(sfm), "features": Path(features), "matches": Path(matches), "pairs": Path(pairs)}


def read_cameras(folder: Path, camera: str | None) -> dict:
    """{query: Camera} from hloc's ``query_list_with_intrinsics.txt``, or one camera for all (``--camera``)."""
    if camera:
        return {None: parse_camera(camera.split(), "--camera")}
    path = Path(folder) / "query_list_with_intrinsics.txt"
    if not path.exists():
        raise InputError("no query_list_with_intrinsics.txt in the folder", path,
                         "give the camera with --camera 'PINHOLE w h fx fy cx cy'")
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    return {r[0]: parse_camera(r[1:], path) for r in rows}


def parse_camera(fields: list, where) -> Camera:
    model, w, h, *params = fields
    if model == "SIMPLE_PINHOLE" and len(params) == 3:
        params = [params[0], *params]
    elif model != "PINHOLE" or len(params) != 4:
        raise InputError(f"camera {' '.join(fields)!r}: only PINHOLE / SIMPLE_PINHOLE are supported", where)
    return Camera(int(w), int(h), tuple(float(p) for p in params))


def read_ground_truth(path: Path, names: list) -> dict:
    """{query: cam_from_world} from a pose list, or from the ``pose.txt`` files of a depth-registered scene folder."""
    from lipmap.datasets.sevenscenes import read_pgt, read_pose_txt

    path = Path(path)
    if not path.exists():
        raise InputError("ground truth (a pose list or a scene folder) is missing", path)
    if path.is_file():
        gt = read_pgt(path)
        return {n: gt.get(n.split(".")[0]) for n in names}
    meta = json.loads((path / "scene.json").read_text()) if (path / "scene.json").exists() else {}
    if not meta.get("depth_registered"):
        raise InputError("pose.txt files are the colour camera's only in a depth-registered scene (scene.json)", path,
                         "give a pose list (pgt/sfm_<scene>.txt) instead")
    return {n: invert_T(read_pose_txt(path / (n.split(".")[0] + ".pose.txt"))) for n in names}


def load_matches(inp: dict) -> dict:
    """{query: PointMatches} for every query of the pairs file."""
    from localization.hloc_io import ModelIndex, pairs_by_query, read_pairs, read_sfm
    from localization.points import point_matches_from_hloc

    pairs = read_pairs(inp["pairs"])
    model = ModelIndex(read_sfm(inp["sfm"]), inp["sfm"])
    return {q: point_matches_from_hloc(q, inp["sfm"], inp["features"], inp["matches"], pairs, model=model,
                                       pairs_name=inp["pairs"]) for q in pairs_by_query(pairs)}


# ----------------------------------------------------------------------------------------------
# the methods: (p2d, p3d, camera, seed) -> cam_from_world (4, 4) or None
# ----------------------------------------------------------------------------------------------
def _T(rigid) -> np.ndarray:
    T = np.eye(4)
    T[:3] = rigid.matrix()
    return T


def pycolmap_hloc(p2d, p3d, camera, seed, refine=True):
    """``pycolmap.estimate_and_refine_absolute_pose`` as hloc's localize_sfm calls it: estimation options
    ``{"ransac": {"max_error": 12}}``, default refinement (Cauchy loss, scale 1 px, inliers only); seeded here."""
    import pycolmap

    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = RANSAC_PX
    est.ransac.random_seed = int(seed)
    if refine:
        ret = pycolmap.estimate_and_refine_absolute_pose(p2d, p3d, camera.to_pycolmap(), est,
                                                         pycolmap.AbsolutePoseRefinementOptions())
    else:
        ret = pycolmap.estimate_absolute_pose(p2d, p3d, camera.to_pycolmap(), est)
    return (None, None) if ret is None else (_T(ret["cam_from_world"]), np.asarray(ret["inlier_mask"]).ravel())


def poselib_conf(conf: PointPoseConfig):
    def run(p2d, p3d, camera, seed):
        r = estimate_pose_points(p2d, p3d, camera, replace(conf, seed=int(seed)))
        return (r["cam_from_world"] if r["success"] else None), r["inliers"]
    return run


def poselib_then_pycolmap_refine(p2d, p3d, camera, seed):
    """PoseLib's RANSAC (no bundle), then COLMAP's refinement of hloc's call on PoseLib's inliers."""
    import pycolmap

    T, inl = poselib_conf(RANSAC_ONLY)(p2d, p3d, camera, seed)
    if T is None:
        return None, None
    ret = pycolmap.refine_absolute_pose(pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3]), p2d, p3d,
                                        inl, camera.to_pycolmap(), pycolmap.AbsolutePoseRefinementOptions())
    return (None, None) if ret is None else (_T(ret["cam_from_world"]), inl)


def then_poselib_refine(ransac, scale, all_matches=False):
    """``ransac``'s pose, then PoseLib's Cauchy refinement at ``scale`` px (None: the inliers' median error, as the
    new defaults) on its inliers, or on all matches."""
    def run(p2d, p3d, camera, seed):
        import poselib

        T, inl = ransac(p2d, p3d, camera, seed)
        if T is None:
            return None, None
        pose = poselib.CameraPose()
        pose.R, pose.t = T[:3, :3], T[:3, 3]
        s = adaptive_loss_scale(pose, p2d[inl], p3d[inl], camera.to_dict(), NEW) if scale is None else scale
        keep = np.ones(len(p2d), bool) if all_matches else inl
        pose, _ = poselib.refine_absolute_pose(p2d[keep], p3d[keep], pose, camera.to_dict(),
                                               {"loss_type": "CAUCHY", "loss_scale": float(s)})
        return make_T(np.asarray(pose.R), np.asarray(pose.t)), inl
    return run


def with_input(method, transform):
    """``method`` on matches changed by ``transform(p2d, p3d, seed) -> (p2d, p3d)``."""
    def run(p2d, p3d, camera, seed):
        a, b = transform(p2d, p3d, seed)
        return method(a, b, camera, seed)
    return run


def hloc_rounding(p2d, p3d, seed):
    """2D points as hloc hands them to pycolmap: the float16 keypoints of the file plus 0.5, added in float16."""
    stored = (p2d - 0.5).astype(np.float16)
    return (stored + np.float16(0.5)).astype(np.float64), p3d


def shuffled(p2d, p3d, seed):
    """The same matches in another order (hloc lists them by database image, we by keypoint)."""
    perm = np.random.default_rng(1000 + int(seed)).permutation(len(p2d))
    return p2d[perm], p3d[perm]


MAIN = {
    "pycolmap (hloc's call)": pycolmap_hloc,
    "ours, old defaults (Cauchy 6 px)": poselib_conf(OLD),
    "ours, new defaults (Cauchy at the inliers' median error)": poselib_conf(NEW),
}


def factors() -> dict:
    """One row per factor of the difference, each on the same matches."""
    colmap_ransac = lambda *a: pycolmap_hloc(*a, refine=False)  # noqa: E731
    poselib_ransac = poselib_conf(RANSAC_ONLY)
    return {
        # correspondences: the same set; only hloc's float16 rounding and the order differ
        "pycolmap, 2D rounded as hloc (float16 + 0.5)": with_input(pycolmap_hloc, hloc_rounding),
        "pycolmap, matches shuffled": with_input(pycolmap_hloc, shuffled),
        "ours old, 2D rounded as hloc": with_input(poselib_conf(OLD), hloc_rounding),
        "ours new, matches shuffled": with_input(poselib_conf(NEW), shuffled),
        # RANSAC alone, and each library's RANSAC with the other's refinement
        "COLMAP RANSAC, no refinement": colmap_ransac,
        "PoseLib RANSAC, no refinement": poselib_ransac,
        "PoseLib RANSAC + COLMAP refinement (Cauchy 1 px)": poselib_then_pycolmap_refine,
        "COLMAP RANSAC + PoseLib Cauchy 1 px": then_poselib_refine(colmap_ransac, 1.0),
        "COLMAP RANSAC + PoseLib Cauchy 6 px": then_poselib_refine(colmap_ransac, 6.0),
        "COLMAP RANSAC + PoseLib Cauchy at the inliers' median": then_poselib_refine(colmap_ransac, None),
        # RANSAC threshold (the old Cauchy scale follows it: half the threshold)
        "ours old, 8 px (Cauchy 4 px)": poselib_conf(replace(OLD, max_reproj_error=8.0, loss_scale=4.0)),
        "ours old, 4 px (Cauchy 2 px)": poselib_conf(replace(OLD, max_reproj_error=4.0, loss_scale=2.0)),
        "ours new, 4 px": poselib_conf(replace(NEW, max_reproj_error=4.0)),
        # refinement loss and scale (RANSAC at 12 px, refinement on the inliers)
        **{f"ours, Cauchy {s:g} px": poselib_conf(replace(NEW, loss_scale=s)) for s in (0.5, 1.0, 2.0, 3.0)},
        "ours, Huber 1 px": poselib_conf(replace(NEW, loss_scale=1.0, bundle={"loss_type": "HUBER"})),
        "ours, least squares on the inliers": poselib_conf(replace(NEW, loss_scale=1.0,
                                                                    bundle={"loss_type": "TRIVIAL"})),
        "ours new, 1000 refinement iterations": poselib_conf(replace(NEW, bundle={"max_iterations": 1000})),
        # inliers only vs all matches in the refinement
        "PoseLib RANSAC + Cauchy 6 px on all matches": then_poselib_refine(poselib_ransac, 6.0, all_matches=True),
        "PoseLib RANSAC + Cauchy 1 px on all matches": then_poselib_refine(poselib_ransac, 1.0, all_matches=True),
        "PoseLib RANSAC + Cauchy at the inliers' median, all matches": then_poselib_refine(poselib_ransac, None, True),
    }


# ----------------------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------------------
def stats(errors: list) -> dict:
    """Median translation (cm) / rotation (deg) and % within 1/2/5 cm of pooled (t_m, R_deg) errors."""
    e = np.array(errors, dtype=float).reshape(-1, 2)
    t = e[:, 0] * 100
    out = {"median_t_cm": float(np.median(t)), "median_R_deg": float(np.median(e[:, 1])), "n_runs": len(e),
           "n_failed": int(np.sum(~np.isfinite(t)))}
    out |= {f"within_{c}cm": float(100 * np.mean(t <= c)) for c in THRESHOLDS_CM}
    return out


def evaluate(method, matches: dict, cameras: dict, gt: dict, seeds: int) -> dict:
    """Errors of ``method`` (or of fixed poses: a dict {query: cam_from_world}) over queries x seeds."""
    errors, per_seed, per_query = [], [], {}
    t0 = time.perf_counter()
    for seed in range(seeds if callable(method) else 1):
        seed_errors = []
        for q, pm in matches.items():
            if gt.get(q) is None:
                continue
            if callable(method):
                T, _ = method(pm.p2d, pm.p3d, cameras.get(q, cameras.get(None)), seed)
            else:
                T = method.get(q)
            e = (np.inf, np.inf) if T is None or not np.all(np.isfinite(T)) else pose_errors(gt[q], T)
            seed_errors.append(e)
            per_query.setdefault(q, []).append(float(e[0] * 100))
        errors += seed_errors
        per_seed.append(float(np.median([e[0] for e in seed_errors]) * 100))
    ms = (time.perf_counter() - t0) * 1000 / max(len(errors), 1)
    return stats(errors) | {"median_t_cm_per_seed": per_seed, "ms_per_query": ms,
                            "per_query_t_cm": {q: statistics.median(v) for q, v in per_query.items()}}


def paired(row: dict, ref: dict) -> dict:
    """Per query against ``ref`` (pycolmap's call), on the queries both put within 5 cm: the geometric mean of the
    error ratios, and the share of queries where ``row`` is closer. Medians over a scene whose queries are partly
    lost move with the few queries near the median; this uses all the localized ones."""
    a, b = row["per_query_t_cm"], ref["per_query_t_cm"]
    qs = [q for q in b if a.get(q, np.inf) <= 5 and b[q] <= 5 and min(a[q], b[q]) > 0]
    if not qs:
        return {"n_paired": 0, "ratio_to_pycolmap": None, "closer_than_pycolmap": None}
    return {"n_paired": len(qs), "ratio_to_pycolmap": float(np.exp(np.mean([np.log(a[q] / b[q]) for q in qs]))),
            "closer_than_pycolmap": float(100 * np.mean([a[q] < b[q] for q in qs]))}


def table(rows: dict) -> str:
    lines = ["| method | median t (cm) | median R (deg) | <= 1 cm | <= 2 cm | <= 5 cm | failed | error / pycolmap's "
             "(geo. mean) | closer than pycolmap | per-seed median t (cm) |", "|" + " --- |" * 10]
    for name, r in rows.items():
        seeds = " / ".join(f"{v:.3f}" for v in r["median_t_cm_per_seed"])
        ratio = "n/a" if r["ratio_to_pycolmap"] is None else f"{r['ratio_to_pycolmap']:.3f} ({r['n_paired']} queries)"
        closer = "n/a" if r["closer_than_pycolmap"] is None else f"{r['closer_than_pycolmap']:.0f} %"
        lines.append(f"| {name} | {r['median_t_cm']:.3f} | {r['median_R_deg']:.3f} | {r['within_1cm']:.1f} % | "
                     f"{r['within_2cm']:.1f} % | {r['within_5cm']:.1f} % | {r['n_failed']} | {ratio} | {closer} | "
                     f"{seeds} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hloc", type=Path, required=True, help="hloc's output folder of one scene (or our points-*)")
    ap.add_argument("--pairs", type=Path, required=True, help="the query pairs file (hloc's <scene>_top10.txt)")
    ap.add_argument("--gt", type=Path, required=True, help="pose list, or a depth-registered scene folder")
    ap.add_argument("--name", required=True, help="results name: point-pose-vs-pycolmap-<name>")
    ap.add_argument("--sfm", type=Path)
    ap.add_argument("--features", type=Path)
    ap.add_argument("--matches", type=Path)
    ap.add_argument("--camera", help="'PINHOLE w h fx fy cx cy' for every query (default: the folder's query list)")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--factors", action="store_true", help="also measure each factor of the difference")
    ap.add_argument("--factor-seeds", type=int, help="seeds of the factor rows (default: --seeds)")
    ap.add_argument("--hloc-results", type=Path,
                    help="hloc's own localize_sfm poses (default: results_sparse.txt of the folder, when there)")
    args = ap.parse_args(argv)
    results.require_clean()
    try:
        inp = find_inputs(args.hloc, args.pairs, args.sfm, args.features, args.matches)
        matches = load_matches(inp)
        cameras = read_cameras(args.hloc, args.camera)
        gt = read_ground_truth(args.gt, list(matches))
    except InputError as e:
        raise SystemExit(f"error: {e}") from None
    todo = dict(MAIN)
    hloc_results = args.hloc_results or args.hloc / "results_sparse.txt"
    if hloc_results.exists():  # hloc's own run of the same call: unseeded, its own match order and rounding
        todo["hloc's localize_sfm (its results file)"] = read_results(hloc_results)
    rows = {}
    extra = factors() if args.factors else {}
    for name, method in (todo | extra).items():
        seeds = (args.factor_seeds or args.seeds) if name in extra else args.seeds
        rows[name] = evaluate(method, matches, cameras, gt, seeds)
        print(f"{name}: {rows[name]['median_t_cm']:.3f} cm, {rows[name]['median_R_deg']:.3f} deg", flush=True)
    ref = rows["pycolmap (hloc's call)"]
    rows = {name: r | paired(r, ref) for name, r in rows.items()}
    print(table(rows))
    results.write(f"point-pose-vs-pycolmap-{args.name}", {
        "inputs": {k: str(v) for k, v in inp.items()}, "gt": str(args.gt), "seeds": args.seeds,
        "factor_seeds": (args.factor_seeds or args.seeds) if args.factors else None,
        "n_queries": len(matches), "n_matches_median": float(np.median([len(m) for m in matches.values()])),
        "configs": {"old": vars(OLD), "new": vars(NEW)}, "methods": rows, "table": table(rows)})


if __name__ == "__main__":
    main()
