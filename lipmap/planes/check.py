"""Quality checks for fitted planes: rendered vs. sensor depth, and pictures to look at.

    python -m lipmap.planes.check --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini \\
        --scene redkitchen --planes OUT/planes.h5 --png OUT/planes_check.png

prints the depth agreement on the mapping and query views and writes a PNG with, per view: the
image, the planar mesh (``planes.ply`` ray-cast with embree, faces coloured by world normal), the
rendered normals and depth (differentiable renderer at lambda 1500), the sensor depth and the
absolute depth error (black 0, white >= 10 cm).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .init import resize_nearest
from .io import load_planes
from .primitives import Planes, triangle_mesh
from .render import render_view


def _working_downscale(view, max_width: int) -> int:
    return max(1, int(np.ceil(view.camera.width / max_width)))


def rendered_depth_errors(planes: Planes, views, max_width: int = 320, lam: float = 1500.0) -> dict:
    """|rendered z-depth - sensor depth| over the pixels with valid sensor depth, in metres.

    Rendering at <= ``max_width`` px wide; the sensor depth is sampled at the same pixel centres.
    Returns median, mean, p90 (metres), coverage (fraction of valid pixels with alpha > 0.5), views.
    """
    views = [v for v in views if v.depth_path is not None and v.cam_from_world is not None]
    e = _depth_errors(planes, views, max_width, lam)
    if not len(e["all"]):
        return {"median": float("nan"), "mean": float("nan"), "p90": float("nan"), "coverage": float("nan"), "views": 0}
    a = e["all"]
    return {"median": float(np.median(a)), "mean": float(a.mean()), "p90": float(np.percentile(a, 90)),
            "coverage": e["coverage"], "views": len(views)}


def plane_stats(planes: Planes, views=(), max_views: int = 10, max_width: int = 320) -> dict:
    """How coherent a plane set is: how many planes, how large (area-weighted, so a wall made of one plane
    counts as much as the same wall in 1000 patches), and how far it is from the sensor depth.

    Returns:
        ``n_planes``, ``total_area_m2``, ``area_weighted_median_area_m2`` (half the planes' area lies in planes
        at least this large), ``area_weighted_median_side_m`` (of the longer side), and over at most
        ``max_views`` evenly spread ``views``: ``depth_error_median_cm``, ``depth_error_p90_cm``,
        ``depth_error_over_5cm`` (fraction of pixels), ``coverage``.
    """
    r = planes.radii.detach().clamp(min=0).cpu().numpy().astype(np.float64)
    w, h = r[:, 0] + r[:, 1], r[:, 2] + r[:, 3]
    area, side = w * h, np.maximum(w, h)
    out = {"n_planes": int(len(r)), "total_area_m2": float(area.sum())}
    if len(r):
        order = np.argsort(area)
        cum = np.cumsum(area[order])
        k = order[np.searchsorted(cum, 0.5 * cum[-1])]
        out["area_weighted_median_area_m2"] = float(area[k])
        order = np.argsort(side)
        cum = np.cumsum(area[order])
        out["area_weighted_median_side_m"] = float(side[order[np.searchsorted(cum, 0.5 * cum[-1])]])
    views = [v for v in views if v.depth_path is not None and v.cam_from_world is not None]
    if views:
        pick = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).astype(int))]
        errs = _depth_errors(planes, pick, max_width)
        if len(errs["all"]):
            out.update({"depth_error_median_cm": float(np.median(errs["all"]) * 100),
                        "depth_error_p90_cm": float(np.percentile(errs["all"], 90) * 100),
                        "depth_error_over_5cm": float(np.mean(errs["all"] > 0.05)), "coverage": errs["coverage"],
                        "depth_views": len(pick)})
    return out


def _depth_errors(planes: Planes, views, max_width: int, lam: float = 1500.0) -> dict:
    errs, cov = [], []
    for v in views:
        with torch.no_grad():
            r = render_view(planes, v, lam=lam, downscale=_working_downscale(v, max_width))
        gt = resize_nearest(v.load_depth(), r.depth.shape[1], r.depth.shape[0])
        ok = gt > 0
        if ok.any():
            errs.append(np.abs(r.depth.cpu().numpy() - gt)[ok])
            cov.append(float((r.alpha.cpu().numpy()[ok] > 0.5).mean()))
    return {"all": np.concatenate(errs) if errs else np.zeros(0), "coverage": float(np.mean(cov)) if cov else float("nan")}


def raycast_mesh(planes: Planes, view, max_width: int = 320) -> np.ndarray:
    """(h, w, 3) uint8 picture of the planar mesh (as written to planes.ply) seen from ``view``."""
    import trimesh

    V, F = triangle_mesh(planes)
    mesh = trimesh.Trimesh(V, F, process=False)
    with torch.no_grad():
        n = planes.normal.detach().cpu().numpy()
    colors = np.repeat(np.clip((n + 1.0) * 127.5, 0, 255), 2, axis=0)
    cam = view.camera.scaled(1.0 / _working_downscale(view, max_width))
    R, t = view.cam_from_world[:3, :3], view.cam_from_world[:3, 3]
    d = cam.pixel_rays().reshape(-1, 3) @ R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.repeat((-R.T @ t)[None], len(d), 0)
    img = np.zeros((len(d), 3))
    if len(F):
        _, ri, ti = mesh.ray.intersects_location(o, d, multiple_hits=False)
        shade = np.abs((mesh.face_normals[ti] * d[ri]).sum(1))
        img[ri] = colors[ti] * (0.35 + 0.65 * shade[:, None])
    return img.reshape(cam.height, cam.width, 3).clip(0, 255).astype(np.uint8)


def check_png(planes: Planes, views, path, max_width: int = 320, depth_max: Optional[float] = None) -> Path:
    """Write the comparison picture (one row per view) to ``path``."""
    import cv2

    from ..imageio import write_color

    rows = []
    for v in views:
        with torch.no_grad():
            r = render_view(planes, v, lam=1500.0, downscale=_working_downscale(v, max_width))
        h, w = r.depth.shape
        rgb = cv2.resize(v.load_color(), (w, h), interpolation=cv2.INTER_AREA)
        normal = ((r.normal.cpu().numpy() * [1, -1, -1] + 1) * 127.5).clip(0, 255).astype(np.uint8)
        gt = resize_nearest(v.load_depth(), w, h)
        d = r.depth.cpu().numpy()
        vmax = depth_max or max(1.0, float(np.percentile(gt[gt > 0], 99)) if (gt > 0).any() else 4.0)

        def cmap(x, scale, name=cv2.COLORMAP_VIRIDIS):
            return cv2.applyColorMap((np.clip(x / scale, 0, 1) * 255).astype(np.uint8), name)[..., ::-1]

        err = np.where(gt > 0, np.abs(d - gt), 0)
        rows.append(np.concatenate([rgb, raycast_mesh(planes, v, max_width), normal, cmap(d, vmax), cmap(gt, vmax),
                                    cmap(err, 0.1, cv2.COLORMAP_HOT)], 1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    path = Path(path)
    write_color(path, np.concatenate(rows, 0))
    return path


def main(argv=None):
    from ..datasets import load_scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="synthetic")
    ap.add_argument("--root", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--planes", required=True, help="planes.h5")
    ap.add_argument("--png", default=None, help="comparison picture to write")
    ap.add_argument("--views", default="0,25", help="mapping view indices for the picture")
    ap.add_argument("--max-width", type=int, default=320)
    args = ap.parse_args(argv)
    scene = load_scene(args.dataset, args.root, args.scene)
    planes = load_planes(args.planes)
    for split in ("mapping", "query"):
        e = rendered_depth_errors(planes, getattr(scene, split), args.max_width)
        print(f"{split}: median |depth - sensor| {100 * e['median']:.2f} cm, mean {100 * e['mean']:.2f} cm, "
              f"p90 {100 * e['p90']:.2f} cm, coverage {e['coverage']:.3f} ({e['views']} views, {len(planes)} planes)")
    if args.png:
        idx = [int(i) for i in args.views.split(",") if int(i) < len(scene.mapping)]
        print("wrote", check_png(planes, [scene.mapping[i] for i in idx], args.png, args.max_width))


if __name__ == "__main__":
    main()
