"""Median cross-view depth disagreement on a 7-Scenes scene with and without depth registration.

    python benchmarks/depth_registration.py --root ../shared/data/7scenes-redkitchen-mini --scene redkitchen

Back-projects frame i's depth, re-projects it into frame i+gap, and compares with frame i+gap's depth.
Writes ``benchmarks/results/depth-registration-<scene>.json``.
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lipmap.datasets import load_scene
from lipmap.datasets.registration import cross_view_depth_residuals

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402


def measure(root, scene, register, gap, **kw):
    s = load_scene("7scenes", root, scene, register_depth=register, **kw)
    views = s.mapping
    depths = [v.load_depth(register=register) for v in views]
    res = [cross_view_depth_residuals(depths[i], views[i], depths[i + gap], views[i + gap]) for i in range(len(views) - gap)]
    res = np.concatenate(res)
    return {"median_mm": float(np.median(res) * 1000), "p90_mm": float(np.percentile(res, 90) * 1000), "n": int(res.size)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default="../shared/data/7scenes-redkitchen-mini")
    ap.add_argument("--scene", default="redkitchen")
    ap.add_argument("--gap", type=int, default=1, help="frame gap between the two views")
    a = ap.parse_args()
    from lipmap.datasets.sevenscenes import estimate_color_from_depth, find_scene_dir

    out = {
        "registered (Kinect extrinsic)": measure(a.root, a.scene, True, a.gap),
        "not registered": measure(a.root, a.scene, False, a.gap),
    }
    est = estimate_color_from_depth(find_scene_dir(a.root, a.scene))
    if est is not None:
        t_only = np.eye(4)
        t_only[:3, 3] = est[:3, 3]
        out["registered (translation only)"] = measure(a.root, a.scene, True, a.gap, color_from_depth=t_only)
    for k, v in out.items():
        print(json.dumps({"scene": a.scene, "gap": a.gap, "depth": k, **v}))
    rows = [[a.scene, k, f"{v['median_mm']:.1f}", f"{v['p90_mm']:.1f}"] for k, v in out.items()]
    results.write(f"depth-registration-{a.scene}", {"gap": a.gap, "measured": out, "table": {
        "header": ["scene", "depth", "median cross-view residual (mm)", "90th percentile (mm)"], "rows": rows}})


if __name__ == "__main__":
    main()
