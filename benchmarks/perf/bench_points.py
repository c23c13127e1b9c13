"""Time the built-in point pipeline's scale-out, old path vs new, on this machine.

    python benchmarks/perf/bench_points.py --images DATA/synth/room-s0 --num-images 24

* extraction (images/s): one process (the former loop) vs ``workers`` processes;
* matching (pairs/s): every pair read and matched in the given (shuffled) order vs the blocked schedule;
* pairs_from_poses (s): the dense all-pairs test vs the pruned one on a synthetic walk (dense is only
  run up to ``--dense-max`` poses and extrapolated as N^2 beyond);
* retrieval top_k (s): the former full sort vs the blocked partial sort, 5000 x 7000 random globals.

Medians of ``--runs`` runs; written to benchmarks/results/perf-points.json.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tests"))  # the synthetic walk of tests/test_points_scale.py
import results  # noqa: E402


def median_time(fn, runs):
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def image_views(folder: Path, n: int):
    from lipmap.imageio import read_color
    from lipmap.scene import Camera, View

    files = sorted(folder.rglob("*.color.png"))[:n] or sorted(folder.rglob("*.png"))[:n]
    h, w = read_color(files[0], gray=True).shape
    cam = Camera(w, h, (w * 0.82, w * 0.82, w / 2, h / 2))
    return [View(name=str(f.relative_to(folder)), camera=cam, cam_from_world=np.eye(4), color_path=f) for f in files]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, required=True, help="a folder of images (searched recursively)")
    ap.add_argument("--num-images", type=int, default=24)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--poses", type=int, nargs="+", default=[300, 1500, 7000])
    ap.add_argument("--dense-max", type=int, default=300)
    ap.add_argument("--queries", type=int, default=5000)
    ap.add_argument("--db", type=int, default=7000)
    ap.add_argument("--global-dim", type=int, default=1024)
    args = ap.parse_args(argv)

    from localization import points
    from localization.points import features as pfeatures
    from localization.points import matching as pmatching, pairs as ppairs, retrieval
    from localization.points import SiftConfig
    from test_points_scale import trajectory_views

    out = {"images": str(args.images), "runs": args.runs}
    views = image_views(args.images, args.num_images)
    out["image_size"] = [views[0].camera.width, views[0].camera.height]
    conf = SiftConfig()
    workers = pfeatures.default_workers()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ext = {}
        for label, w in (("old_1_process", 1), (f"new_{workers}_processes", workers)):
            t = median_time(lambda: points.extract_sift(views, tmp / f"{label}.h5", conf, overwrite=True, workers=w,
                                                        device="cpu"), args.runs)
            ext[label] = {"s": t, "images_per_s": len(views) / t}
        out["extraction"] = ext
        print("extraction", ext)

        feats = tmp / f"new_{workers}_processes.h5"
        names = [v.name for v in views]
        rng = np.random.default_rng(0)
        pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 : i + 6]]
        pairs = [pairs[k] for k in rng.permutation(len(pairs))]

        def old_match():  # the former loop's cost when no pair's images are cached: read both, match
            for a, b in pairs:
                cache = pmatching._DescriptorCache(feats)
                points.mutual_nn_ratio(cache(a), cache(b))

        t_old = median_time(old_match, args.runs)
        t_new = median_time(lambda: points.match_features(pairs, feats, tmp / "m.h5", overwrite=True), args.runs)
        out["matching"] = {"pairs": len(pairs), "old_pairs_per_s": len(pairs) / t_old, "new_pairs_per_s": len(pairs) / t_new}
        print("matching", out["matching"])

    pp = {}
    t_dense_ref = None
    for n in args.poses:
        pv = trajectory_views(n, length=n / 5.0)  # ~0.2 m between frames along a winding walk
        row = {"new_s": median_time(lambda: points.pairs_from_poses(pv), 1 if n > 2000 else args.runs)}
        if n <= args.dense_max:
            row["old_s"] = median_time(lambda: ppairs._pairs_from_poses_dense(pv), 1)
            t_dense_ref = (n, row["old_s"])
        elif t_dense_ref:
            row["old_s_extrapolated_n2"] = t_dense_ref[1] * (n / t_dense_ref[0]) ** 2
        pp[str(n)] = row
        print("pairs_from_poses", n, row)
    out["pairs_from_poses"] = pp

    rng = np.random.default_rng(0)
    q = rng.normal(size=(args.queries, args.global_dim)).astype(np.float32)
    d = rng.normal(size=(args.db, args.global_dim)).astype(np.float32)
    out["top_k"] = {"queries": args.queries, "db": args.db, "dim": args.global_dim,
                    "old_full_sort_s": median_time(lambda: retrieval._top_k_full_sort(q, d, 10), 1),
                    "new_blocked_s": median_time(lambda: retrieval.top_k(q, d, 10), 1)}
    print("top_k", out["top_k"])
    results.write("perf-points", out, argv=[sys.argv[0], *(argv if argv is not None else sys.argv[1:])])


if __name__ == "__main__":
    main()
