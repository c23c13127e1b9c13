"""Where a map's plane edges sit against the sensor depth of the views that track them, and where the ones that
float come from.

    python benchmarks/edge_depth.py --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \
        --scene redkitchen --out OUT [--tag TAG] NAME=MAP_DIR [NAME2=MAP_DIR2 ...]

Each MAP_DIR holds a lipmap ``linemap.h5`` (whose ``planes.h5`` it names). Per map: the plane edges' median |depth - sensor
depth| over their tracked views (:func:`lipmap.mapping.extract.depth_residuals`, the nearer side of a depth step
counts) in three bins, and for the edges more than 30 cm off: how far the interior of their planes is from the
sensor depth (signed: negative = in front of the surface), how far they are from the camera, and how many of
their samples fall near the image's bottom or left border (where 7-Scenes' registered depth has holes). Writes
``benchmarks/results/edge-depth-<dataset>-<scene>[-TAG].json`` and a picture of the first map's floating edges
(``.png``, each row: the image with the edge (red) and its planes (green), and the sensor depth).
"""
from __future__ import annotations

import sys
from dataclasses import fields, replace
from pathlib import Path

import cv2
import numpy as np

from lipmap import geometry as geo
from lipmap.datasets import load_scene
from lipmap.frames import depth_maps
from lipmap.linemap import LineMap
from lipmap.mapping.depth_lookup import depth_pixels
from lipmap.mapping.extract import depth_residuals
from lipmap.mapping.keyframes import KeyframeConfig, keyframe_views
from lipmap.planes.io import load_planes

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

HEADER = ["map", "edge lines", "within 5 cm", "5-30 cm", "> 30 cm", "floating: their planes' interior vs sensor depth",
          "floating: distance from camera (edges within 5 cm)", "floating / within-5-cm edges: samples near the bottom or left border"]
FLOAT, NEAR = 0.30, 0.05


def _views(scene, lm):
    """The mapping views the map was built from (its keyframes), in the order its track indices use."""
    kf = lm.metadata.get("keyframes", {})
    conf = KeyframeConfig(**{f.name: kf[f.name] for f in fields(KeyframeConfig) if f.name in kf})
    return keyframe_views(scene.mapping, conf)


def _interior(planes, k: int, frac: float = 0.5) -> np.ndarray:
    """5 x 5 points over the central ``frac`` of plane ``k``'s rectangle."""
    R = planes["R"][k]
    xp, xm, yp, ym = planes["radii"][k]
    U, V = np.meshgrid(np.linspace(-xm * frac, xp * frac, 5), np.linspace(-ym * frac, yp * frac, 5))
    return planes["center"][k] + U.reshape(-1, 1) * R[:, 0] + V.reshape(-1, 1) * R[:, 1]


def _signed_off(points, views, vis, depth) -> np.ndarray:
    """z - sensor depth of ``points`` in the views ``vis`` (valid depth only)."""
    out = []
    for vi in vis:
        v = views[vi]
        d = depth[v.name]
        uv, z = geo.project_points(points, v.cam_from_world, v.camera)
        r, c, ok = depth_pixels(uv, z, v.camera, d.shape)
        dd = d[r[ok], c[ok]]
        out.append((z[ok] - dd)[dd > 0])
    return np.concatenate(out) if out else np.zeros(0)


def analyse(scene, map_dir: Path) -> dict:
    import torch

    lm = LineMap.load(map_dir / "linemap.h5")
    p = load_planes(map_dir / lm.metadata.get("planes_file", "planes.h5"), dtype=torch.float64)  # eval: shared planes
    planes = {"R": p.rotation().numpy(), "center": p.center.numpy(), "radii": p.radii_clamped().numpy()}
    views = _views(scene, lm)
    index = {v.name: i for i, v in enumerate(views)}
    ne = int(lm.metadata.get("n_edge_lines", len(lm)))
    rows = np.array([(l, index[o.image_name], o.line2d_index) for l in range(ne) for o in lm.tracks[l]],
                    dtype=np.int64).reshape(-1, 3)
    depth = depth_maps(views)
    res = depth_residuals(lm.lines[:ne], rows, views, depth)
    edge_line = lm.planes["edge_line"]
    samples = geo.sample_segments(lm.lines[:ne], 16)

    def describe(sel):
        off, dist, border, n = [], [], 0, 0
        for l in np.flatnonzero(sel):
            vis = np.unique(rows[rows[:, 0] == l, 1])
            ks = np.unique(np.nonzero(edge_line == l)[0])
            o = _signed_off(np.concatenate([_interior(planes, k) for k in ks]), views, vis, depth)
            if len(o):
                off.append(np.median(o))
            for vi in vis:
                v = views[vi]
                uv, z = geo.project_points(samples[l], v.cam_from_world, v.camera)
                border += int(((uv[:, 1] > 0.85 * v.camera.height) | (uv[:, 0] < 0.1 * v.camera.width)).sum())
                n += len(uv)
                dist.append(float(np.median(z)))
        return {"interior_off_m": float(np.median(off)) if off else None,
                "distance_m": float(np.median(dist)) if dist else None, "border_frac": border / max(n, 1)}

    floating, near = res > FLOAT, res < NEAR
    return {"n_edges": ne, "near": int(near.sum()), "mid": int(((res >= NEAR) & (res <= FLOAT)).sum()),
            "floating": int(floating.sum()), "floating_stats": describe(floating), "near_stats": describe(near),
            "_res": res, "_rows": rows, "_views": views, "_lm": lm, "_planes": p, "_depth": depth}


def picture(a: dict, path: Path, n: int = 3, seed: int = 0) -> Path:
    fl = np.flatnonzero(a["_res"] > FLOAT)
    if not len(fl):
        return path
    pick = np.random.default_rng(seed).choice(fl, min(n, len(fl)), replace=False)
    corners = a["_planes"].corners().numpy()
    tiles = []
    for l in pick:
        vi = np.unique(a["_rows"][a["_rows"][:, 0] == l, 1])[0]
        v = a["_views"][vi]
        img = cv2.imread(str(v.color_path))
        d = a["_depth"][v.name]
        dv = cv2.applyColorMap(np.clip(d / 3.0 * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
        dv[d <= 0] = 0
        dv = cv2.resize(dv, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
        for k in np.unique(np.nonzero(a["_lm"].planes["edge_line"] == l)[0]):
            uv, _ = geo.project_points(corners[k], v.cam_from_world, v.camera)
            for im in (img, dv):
                cv2.polylines(im, [np.round(uv).astype(np.int32).reshape(-1, 1, 2)], True, (0, 255, 0), 2)
        uv, z = geo.project_points(a["_lm"].lines[l], v.cam_from_world, v.camera)
        for im in (img, dv):
            cv2.line(im, tuple(np.round(uv[0]).astype(int)), tuple(np.round(uv[1]).astype(int)), (0, 0, 255), 2)
        cv2.putText(img, f"{v.name}: edge {l}, {100 * a['_res'][l]:.0f} cm off the sensor depth, {z.mean():.2f} m away",
                    (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([img, dv], 1))
    cv2.imwrite(str(path), cv2.resize(np.concatenate(tiles, 0), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return path


def main(argv=None):
    ap = results.scene_parser(__doc__)
    ap.add_argument("--tag", default="")
    ap.add_argument("maps", nargs="+", help="NAME=MAP_DIR")
    args = ap.parse_args(argv)
    scene = load_scene(args.dataset, args.root, args.scene)
    name = f"edge-depth-{scene.dataset}-{scene.name}" + (f"-{args.tag}" if args.tag else "")
    rows, data, first = [], {}, None
    for spec in args.maps:
        label, _, folder = spec.partition("=")
        a = analyse(scene, Path(folder))
        first = first or a
        f, o = a["floating_stats"], a["near_stats"]
        data[label] = {k: v for k, v in a.items() if not k.startswith("_")}
        pct = lambda x: f"{x} ({100 * x / max(a['n_edges'], 1):.0f} %)"  # noqa: E731
        rows.append([label, a["n_edges"], pct(a["near"]), pct(a["mid"]), pct(a["floating"]),
                     "" if f["interior_off_m"] is None else f"{100 * f['interior_off_m']:+.0f} cm",
                     "" if f["distance_m"] is None else f"{f['distance_m']:.2f} m ({o['distance_m']:.2f})",
                     f"{100 * f['border_frac']:.0f} / {100 * o['border_frac']:.0f} %"])
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    png = picture(first, results.RESULTS / f"{name}.png")
    results.write(name, {"maps": data, "picture": png.name, "table": {"header": HEADER, "rows": rows}})


if __name__ == "__main__":
    main()
