"""What the reference rasterizer's hit rule would change in the renders the plane optimization learns from.

    python benchmarks/hit_rule.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini --scene redkitchen \
        --out OUT [--views 10] [--lams 36.8,300,1500] [--tag TAG] NAME=PLANES [NAME2=PLANES2 ...]

PLANES is a ``planes.h5`` (its stored settings give the render's culling, near plane and hits per pixel), or
``init:PRESET``: the initial planes of a plane-optimization preset (``paper``: 10,000 planes from a 1 cm TSDF),
rendered with that preset's settings. Each set is rendered into ``--views`` mapping views spread evenly over the
scene, at each lambda of ``--lams`` (the splat sharpness: the ``paper`` schedule starts at 36.8, passes 300 at
iteration 1,000 and ends at 1,500), with the torch renderer twice: under this toolkit's rule (each pixel composites
its M nearest hits) and under the reference's (``hit_rule="reference"``: the tile's planes walked by their centres'
depth, a hit nearer than the last one taken skipped). Per set and lambda: the share of rendered pixels (alpha > 0.5
in either render) whose first plane differs, whose depth differs by more than 1 cm and 5 cm, whose normal turns by
more than 10 degrees, and the plane loss (the preset's depth and normal terms against the view's targets) under
each rule. Writes ``benchmarks/results/hit-rule-<dataset>-<scene>[-TAG].json``.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from lipmap.datasets import load_scene
from lipmap.planes.config import PlaneOptConfig
from lipmap.planes.init import init_planes
from lipmap.planes.io import load_planes, load_planes_meta
from lipmap.planes.losses import plane_loss
from lipmap.planes.render import rasterize_planes
from lipmap.planes.rotation import composed
from lipmap.planes.targets import TargetStore
from lipmap.planes.train import _rendered_subset

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["planes", "lambda", "views", "rendered pixels", "first plane differs", "depth > 1 cm", "depth > 5 cm",
          "normal > 10 deg", "plane loss: nearest / reference"]


def _planes_and_conf(spec: str, scene):
    """(Planes, PlaneOptConfig) of a NAME=... argument's value."""
    if spec.startswith("init:"):
        conf = PlaneOptConfig.preset(spec[5:])
        return init_planes(scene.mapping, conf.init), conf
    meta = load_planes_meta(spec)
    stored = dict(meta["config"])
    init = stored.pop("init", {})
    conf = PlaneOptConfig.preset({"preset": stored.pop("name", "fast"), **stored, "init": init})
    return load_planes(spec), conf


def _render(planes, tgt, lam, conf, rule):
    params = [planes.center.detach().clone().requires_grad_(), planes.quat.detach().clone(),
              planes.radii.detach().clone()]
    idx = _rendered_subset(params, tgt.cam_from_world, conf)
    p = [params[0], composed(params[1]), params[2]]
    p = p if idx is None else [t.index_select(0, idx) for t in p]
    out = rasterize_planes(p[0], p[1], p[2], tgt.cam_from_world, tgt.camera.params, tgt.camera.width,
                           tgt.camera.height, lam, conf.max_hits, conf.tile_size, backend="torch", near=conf.near,
                           hit_rule=rule)
    pl = plane_loss(out, tgt, conf)
    first = out.hits[..., 0] if idx is None else torch.where(out.hits[..., 0] >= 0, idx[out.hits[..., 0].clamp(min=0)], -1)
    return out, first, float(pl[0].detach()) if pl is not None else float("nan")


def compare(planes, conf, targets, view_ids, lam) -> dict:
    counts = dict(rendered=0, first=0, d1=0, d5=0, n10=0)
    losses = {"nearest": [], "reference": []}
    for i in tqdm(view_ids, desc=f"lambda {lam:g}", leave=False):
        tgt = targets[i]
        a, fa, la = _render(planes, tgt, lam, conf, "nearest")
        b, fb, lb = _render(planes, tgt, lam, conf, "reference")
        losses["nearest"].append(la)
        losses["reference"].append(lb)
        with torch.no_grad():
            rendered = (a.alpha > 0.5) | (b.alpha > 0.5)
            dd = (a.depth - b.depth).abs()
            na = torch.nn.functional.normalize(a.normal, dim=-1)
            nb = torch.nn.functional.normalize(b.normal, dim=-1)
            turned = (na * nb).sum(-1) < np.cos(np.radians(10))
            counts["rendered"] += int(rendered.sum())
            counts["first"] += int((rendered & (fa != fb)).sum())
            counts["d1"] += int((rendered & (dd > 0.01)).sum())
            counts["d5"] += int((rendered & (dd > 0.05)).sum())
            counts["n10"] += int((rendered & turned).sum())
    n = max(counts["rendered"], 1)
    return {"lambda": lam, "views": len(view_ids), "rendered_pixels": counts["rendered"],
            "first_plane_differs": counts["first"] / n, "depth_over_1cm": counts["d1"] / n,
            "depth_over_5cm": counts["d5"] / n, "normal_over_10deg": counts["n10"] / n,
            "plane_loss_nearest": float(np.nanmean(losses["nearest"])),
            "plane_loss_reference": float(np.nanmean(losses["reference"]))}


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--views", type=int, default=10, help="mapping views, spread evenly")
    ap.add_argument("--lams", default="36.8,300,1500", help="splat sharpness values, comma separated")
    ap.add_argument("--tag", default="")
    ap.add_argument("planes", nargs="+", help="NAME=planes.h5 or NAME=init:PRESET")
    args = ap.parse_args(argv)
    results.require_clean()
    torch.manual_seed(0)
    scene = load_scene(args.dataset, args.root, args.scene)
    name = f"hit-rule-{scene.dataset}-{scene.name}" + (f"-{args.tag}" if args.tag else "")
    lams = [float(x) for x in args.lams.split(",")]
    rows, data = [], {}
    for spec in args.planes:
        label, _, what = spec.partition("=")
        planes, conf = _planes_and_conf(what, scene)
        targets = TargetStore(scene.mapping, conf)
        view_ids = sorted(set(np.linspace(0, len(targets) - 1, min(args.views, len(targets))).round().astype(int)))
        data[label] = {"planes": what if what.startswith("init:") else results.portable_path(what),
                       "n_planes": len(planes), "preset": conf.name, "max_hits": conf.max_hits, "near": conf.near,
                       "by_lambda": []}
        for lam in lams:
            r = compare(planes, conf, targets, view_ids, lam)
            data[label]["by_lambda"].append(r)
            pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
            rows.append([f"{label} ({len(planes)} planes)", f"{lam:g}", r["views"], r["rendered_pixels"],
                         pct(r["first_plane_differs"]), pct(r["depth_over_1cm"]), pct(r["depth_over_5cm"]),
                         pct(r["normal_over_10deg"]), f"{r['plane_loss_nearest']:.4f} / {r['plane_loss_reference']:.4f}"])
            print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    results.write(name, {"sets": data, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
