"""Rendering helpers for reports: line overlays, line-map and planar-mesh renders, PR curves.

Everything draws on :class:`matplotlib.figure.Figure` objects with the Agg canvas directly (no
pyplot, no display, no global figure registry), and images are shown in the COLMAP pixel
convention: ``imshow`` extent (0, W, H, 0), so the centre of pixel (i, j) sits at (i + 0.5, j + 0.5)
exactly like the segments we draw.

    render_linemap_views(linemap, scene, out_dir)  -> [linemap.png, planes.png]   (end of mapping)
    plot_pr_curve(linemap, gt, out_png)                                           (map-eval)
    overlay_figure / overlay_array / linemap_figure / planes_figure              (building blocks)

The virtual cameras the renders are seen from (overview camera, scene box, world up) are in :mod:`lipmap.viewpoints`.
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Optional, Sequence

import matplotlib
import matplotlib.ticker
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from . import geometry as geo
from . import logger
from .imageio import atomic_path
from .viewpoints import box_edges, look_at, overview_camera, scene_frame, up_direction

# Fonts sized for a report read at 100 % zoom; figures are ~1300 px wide.
RC = {
    "font.size": 12,
    "axes.titlesize": 13,
    "axes.labelsize": 12,
    "legend.fontsize": 11,
    "xtick.labelsize": 11,
    "ytick.labelsize": 11,
    "figure.titlesize": 14,
    "axes.grid": False,
}
DPI = 100
DETECTED_COLOR = "#1f4fff"  # blue: detected 2D lines
PROJECTED_COLOR = "#ff1a1a"  # red: projected map lines
BACKGROUND = (0.97, 0.97, 0.97)


@contextlib.contextmanager
def style():
    """Report style for the figures made inside the block (rcParams are read when artists are made)."""
    with matplotlib.rc_context(RC):
        yield


def new_figure(width_in: float, height_in: float, layout: Optional[str] = "constrained") -> Figure:
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path, dpi: int = DPI) -> Path:
    """Write ``fig`` as a PNG atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, facecolor="white")
    return path


def figure_to_array(fig: Figure, dpi: int = DPI) -> np.ndarray:
    """The figure rasterised exactly as :func:`save_figure` writes it: (H, W, 3) uint8."""
    fig.set_dpi(dpi)
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


# ----------------------------------------------------------------------------------------------
# images and segments
# ----------------------------------------------------------------------------------------------
def dimmed(image: Optional[np.ndarray], size, mode: str = "light", strength: float = 0.55) -> np.ndarray:
    """Grey version of ``image`` washed towards white (``light``) or black (``dark``): (H, W) uint8.

    Coloured lines stay readable on it. ``image`` None gives a flat grey canvas of ``size`` (W, H).
    """
    w, h = size
    if image is None:
        return np.full((h, w), 200 if mode == "light" else 40, np.uint8)
    g = np.asarray(image, dtype=np.float32)
    if g.ndim == 3:
        g = g[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    if mode == "light":
        g = g * (1 - strength) + 255 * strength
    else:
        g = g * (1 - strength)
    return np.clip(g, 0, 255).astype(np.uint8)


def show_image(ax, gray: np.ndarray, title: Optional[str] = None):
    """Show a (H, W) uint8 image in COLMAP pixel coordinates and hide the ticks."""
    h, w = gray.shape[:2]
    ax.imshow(gray, cmap="gray", vmin=0, vmax=255, extent=(0, w, h, 0), interpolation="antialiased")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title)


def draw_segments(ax, segments2d, color, linewidth: float = 1.2, alpha: float = 1.0, label=None, zorder: int = 3,
                  cmap=None, norm=None, values=None):
    """Draw 2D segments :math:`(N, 2, 2)` (or (N, 4)) as one LineCollection; NaN rows are skipped.

    With ``values`` (N,), ``cmap`` and ``norm`` the segments are coloured by value.
    """
    s = np.asarray(geo.as_segments2d(np.asarray(segments2d, dtype=float)), dtype=float).reshape(-1, 2, 2)
    ok = np.isfinite(s).all(axis=(1, 2))
    if np.ndim(linewidth):  # per-segment widths
        linewidth = np.asarray(linewidth, dtype=float)[ok]
    kw = dict(linewidths=linewidth, alpha=alpha, zorder=zorder, label=label, capstyle="round")
    if values is not None:
        lc = LineCollection(s[ok], cmap=cmap, norm=norm, **kw)
        lc.set_array(np.asarray(values, dtype=float)[ok])
    else:
        lc = LineCollection(s[ok], colors=color, **kw)
    lc.set_snap(False)  # Agg's snapping moves a line at pixel centre y = j + 0.5 to row j + 1
    ax.add_collection(lc)
    return lc


def project_to_image(lines3d, cam_from_world, camera):
    """Project world segments :math:`(N, 2, 3)` into ``camera`` and clip them to the image.

    Returns:
        **segments2d** :math:`(N, 2, 2)` clipped to [0, W] x [0, H] (NaN where not drawable) and
        **drawable** :math:`(N,)` bool (some part in front of the camera and inside the image).
    """
    proj, valid = geo.project_segments(np.asarray(lines3d, dtype=float).reshape(-1, 2, 3), cam_from_world, camera)
    clipped, inside = geo.clip_segments_to_image(np.where(valid[:, None, None], proj, 0.0), camera.width, camera.height)
    ok = valid & inside
    return np.where(ok[:, None, None], clipped, np.nan), ok


def visible_line_indices(lines3d, cam_from_world, camera, corners=None, depth=None, tol: float = 0.05,
                         line_query=None) -> np.ndarray:
    """Indices of map lines in front of the camera, inside the image and, when possible, not occluded.

    Occlusion test, first available of: the map's planes (``corners`` (K, 4, 3) or a built
    ``lipmap.mapping.assign.LineVisibility`` - the line query's own visibility test), the view's depth
    map ``depth`` (H, W) (metres, 0 unknown; ``lipmap.mapping.extract.visible_mask`` on 5 samples per
    line, 3 must pass, as the track builder does), else none.
    """
    lines3d = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    T = np.asarray(cam_from_world, dtype=float)
    if line_query is not None or corners is not None:
        if line_query is None:
            from .mapping.assign import LineVisibility

            line_query = LineVisibility(lines3d, corners)
        return line_query.visible_lines(T, camera, tol)
    _, ok = project_to_image(lines3d, T, camera)
    idx = np.flatnonzero(ok)
    if depth is None or len(idx) == 0:
        return idx
    from types import SimpleNamespace

    from .mapping.extract import visible_mask

    samples = geo.sample_segments(lines3d[idx], 5).reshape(-1, 3)
    vis = visible_mask(samples, SimpleNamespace(cam_from_world=T, camera=camera), depth, tol).reshape(len(idx), 5)
    return idx[vis.sum(1) >= 3]


# ----------------------------------------------------------------------------------------------
# overlays: detected 2D lines (blue) and projected map lines (red)
# ----------------------------------------------------------------------------------------------
def draw_overlay(ax, image, camera, detected2d=None, projected2d=None, title=None, legend: bool = True,
                 detected_width: float = 2.0, projected_width: float = 1.1, projected_label: Optional[str] = None):
    """One overlay panel: dimmed image, detected lines (blue) under projected map lines (red)."""
    show_image(ax, dimmed(image, (camera.width, camera.height)), title)
    handles = []
    if detected2d is not None:
        n = len(np.asarray(detected2d).reshape(-1, 4))
        handles.append(draw_segments(ax, detected2d, DETECTED_COLOR, detected_width, 0.85, f"detected 2D lines ({n})", 3))
    if projected2d is not None:
        n = int(np.isfinite(np.asarray(projected2d, dtype=float).reshape(-1, 4)).all(1).sum())
        handles.append(draw_segments(ax, projected2d, PROJECTED_COLOR, projected_width, 0.95,
                                     projected_label or f"map lines, projected ({n})", 4))
    if legend and handles:
        ax.legend(handles=handles, loc="lower left", framealpha=0.85, fontsize=10)


def overlay_figure(image, camera, detected2d, panels: Sequence[tuple], suptitle: Optional[str] = None) -> Figure:
    """Side-by-side overlays sharing one image and its detected lines.

    Args:
        image: (H, W, 3) or (H, W) uint8, or None (grey canvas).
        camera: the image's :class:`~lipmap.scene.Camera`.
        detected2d: :math:`(M, 4)` detected segments (COLMAP pixels).
        panels: ``(title, projected2d (N, 2, 2)[, legend label])`` per panel.
    """
    n = len(panels)
    aspect = camera.height / camera.width
    with style():
        fig = new_figure(6.6 * n, 6.6 * aspect + (1.0 if suptitle else 0.7))
        axes = fig.subplots(1, n, squeeze=False)[0]
        for ax, panel in zip(axes, panels):
            title, proj = panel[:2]
            draw_overlay(ax, image, camera, detected2d, proj, title, projected_label=panel[2] if len(panel) > 2 else None)
        if suptitle:
            fig.suptitle(suptitle, fontweight="bold")
            fig.get_layout_engine().set(h_pad=0.08)
    return fig


def overlay_array(image, camera, layers: Sequence[tuple]) -> np.ndarray:
    """Draw segment layers onto the image at its native resolution: (H, W, 3) uint8.

    Args:
        layers: ``(segments (N, 2, 2) or (N, 4), colour, linewidth)`` drawn in order.

    Pixel (i, j) of the result is pixel (i, j) of the image (COLMAP convention), so a segment at
    y = j + 0.5 lights row j: this is what the pixel tests check.
    """
    w, h = camera.width, camera.height
    with style():
        fig = new_figure(w / DPI, h / DPI, layout=None)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        show_image(ax, dimmed(image, (w, h)))
        for segs, color, lw in layers:
            draw_segments(ax, segs, color, lw, 1.0)
    arr = figure_to_array(fig)
    return arr[:h, :w]


# ----------------------------------------------------------------------------------------------
# the view to show
# ----------------------------------------------------------------------------------------------
def pick_view(views, lines3d, max_candidates: int = 60):
    """The mapping view that sees the most map-line length (drawable part, in pixels)."""
    views = [v for v in views if v.cam_from_world is not None]
    if not views:
        return None
    step = max(1, len(views) // max_candidates)
    best, best_score = views[0], -1.0
    for v in views[::step]:
        segs, ok = project_to_image(lines3d, v.cam_from_world, v.camera)
        score = float(np.nansum(geo.segment_lengths(segs[ok]))) if ok.any() else 0.0
        if score > best_score:
            best, best_score = v, score
    return best


# ----------------------------------------------------------------------------------------------
# line map renders
# ----------------------------------------------------------------------------------------------
_SUPPORT_CMAP = matplotlib.colors.LinearSegmentedColormap.from_list(
    "support", matplotlib.colormaps["plasma"](np.linspace(0.0, 0.82, 256)))


def _support_norm(values):
    vmax = max(2.0, float(np.max(values)) if len(values) else 2.0)
    return LogNorm(vmin=1.0, vmax=vmax)


def draw_lines_by_support(ax, segments2d, support, norm, linewidth=1.2):
    """Segments coloured by support, best-supported drawn on top."""
    order = np.argsort(support, kind="stable")
    return draw_segments(ax, segments2d[order], None, linewidth, 1.0, None, 3, _SUPPORT_CMAP, norm,
                         np.maximum(support[order], 1))


def draw_linemap_overview(ax, lines3d, support, up, norm, views=None, title=None):
    """Oblique overview of all lines from outside the scene's bounding box (grey), nearer lines
    drawn thicker, plus the mapping camera centres."""
    lines3d = np.asarray(lines3d, dtype=float).reshape(-1, 2, 3)
    T, cam, frame = overview_camera(lines3d.reshape(-1, 3), up)
    segs, ok = project_to_image(lines3d, T, cam)
    ax.set_facecolor("white")
    ax.set_xlim(0, cam.width)
    ax.set_ylim(cam.height, 0)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    box, box_ok = project_to_image(box_edges(frame), T, cam)
    draw_segments(ax, box[box_ok], "0.6", 0.8, 1.0, None, 1)
    z = geo.transform_points(T, lines3d[ok].mean(1))[:, 2]
    near = 1 - (z - z.min()) / max(np.ptp(z), 1e-9) if len(z) else z
    support = np.asarray(support, dtype=float)[ok]
    order = np.argsort(support, kind="stable")
    lc = draw_segments(ax, segs[ok][order], None, 0.5 + 1.1 * near[order], 1.0, None, 3, _SUPPORT_CMAP, norm,
                       np.maximum(support[order], 1))
    if views:
        c = np.array([v.center for v in views if v.cam_from_world is not None])
        uv, zc = geo.project_points(c, T, cam)
        m = zc > 0
        ax.scatter(uv[m, 0], uv[m, 1], s=10, c="#2ca02c", marker="o", zorder=5, label="mapping cameras")
        ax.legend(loc="lower left", framealpha=0.85, fontsize=10)
    if title:
        ax.set_title(title)
    return lc, T, cam


def support_colorbar(fig, mappable, axes, norm):
    cb = fig.colorbar(mappable, ax=list(axes), shrink=0.85, pad=0.01)
    ticks = [t for t in (1, 2, 3, 5, 10, 20, 50, 100, 200, 500, 1000) if t <= norm.vmax]
    cb.set_ticks(ticks)
    # a line no detection verifies (support 0) is drawn in the colour of 1: a log scale has no 0
    cb.set_ticklabels(["0-1" if t == 1 else str(t) for t in ticks])
    cb.ax.minorticks_off()
    cb.set_label("support (images passing the track test)")
    return cb


def linemap_figure(linemap, view=None, views=None, corners=None, line_query=None, up=None) -> Figure:
    """Two panels: the map's lines in a mapping camera over its dimmed image, and an oblique
    overview; both coloured by support (number of images). ``view`` None: overview only."""
    lines = linemap.lines
    support = linemap.supports[:, 0].astype(float) if len(linemap) else np.zeros(0)
    norm = _support_norm(support)
    if up is None:
        up = up_direction(views, lines.reshape(-1, 3))
    method = linemap.metadata.get("method", "?")
    if "n_on_plane_lines" in linemap.metadata:  # lipmap with on-plane lines: say how many are plane edges
        method += f"; {linemap.metadata.get('n_edge_lines', '?')} plane edges"
    n = 2 if view is not None else 1
    with style():
        fig = new_figure(6.8 * n + 0.9, 6.0)
        axes = fig.subplots(1, n, squeeze=False)[0]
        lc = None
        if view is not None:
            cam = view.camera
            try:
                img = view.load_color()
            except Exception as e:  # noqa: BLE001 - a missing image still gives a line render
                logger.warning("No image for %s: %s", view.name, e)
                img = None
            depth, how = None, "planes" if (corners is not None or line_query is not None) else "none"
            if how == "none" and view.depth_path is not None:
                try:
                    depth, how = view.load_depth(), "depth map"
                except Exception as e:  # noqa: BLE001
                    logger.warning("No depth for %s: %s", view.name, e)
            idx = visible_line_indices(lines, view.cam_from_world, cam, corners, depth, line_query=line_query)
            segs, ok = project_to_image(lines[idx], view.cam_from_world, cam)
            show_image(axes[0], dimmed(img, (cam.width, cam.height), "light", 0.5),
                       f"mapping view {view.name}\n{len(idx)} visible lines (occlusion test: {how})")
            lc = draw_lines_by_support(axes[0], segs[ok], support[idx][ok], norm, 1.5)
        lc2, _, _ = draw_linemap_overview(axes[-1], lines, support, up, norm, views,
                                          f"overview: all {len(lines)} lines ({method})")
        support_colorbar(fig, lc2 if lc is None else lc, axes, norm)
    return fig


# ----------------------------------------------------------------------------------------------
# planar mesh renders (ray casting with embree)
# ----------------------------------------------------------------------------------------------
def plane_normals(corners) -> np.ndarray:
    c = np.asarray(corners, dtype=float).reshape(-1, 4, 3)
    n = np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def corners_from_ply(path) -> np.ndarray:
    """Plane corners (K, 4, 3) from a ``planes.ply`` written by ``lipmap.planes.io.export_planes_ply``."""
    import trimesh

    from .errors import InputError

    mesh = trimesh.load(path, process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(V) % 4 or len(F) != len(V) // 2:
        raise InputError(f"not a planar-mesh PLY of 4 vertices and 2 faces per plane ({len(V)} vertices, {len(F)} faces)", path)
    return V.reshape(-1, 4, 3)


def render_planes(corners, cam_from_world, camera, caster=None, background=BACKGROUND):
    """Ray-cast the rectangles into ``camera``: shaded by normal, plane borders outlined.

    Colour = (n + 1) / 2 of the world normal turned towards the camera (as in planes.ply), times a
    headlight Lambert term; one ray per pixel centre.

    Returns:
        **rgb** :math:`(H, W, 3)` float in [0, 1] and **plane** :math:`(H, W)` int (-1 = background).
    """
    from .mapping.assign import PlaneRaycaster, pixel_rays_world

    corners = np.asarray(corners, dtype=float).reshape(-1, 4, 3)
    w, h = camera.width, camera.height
    rgb = np.empty((h, w, 3))
    rgb[:] = background
    plane = np.full((h, w), -1, dtype=np.int64)
    if len(corners) == 0:
        return rgb, plane
    caster = caster or PlaneRaycaster(corners)
    jj, ii = np.mgrid[0:h, 0:w]
    pix = np.stack([ii.ravel(), jj.ravel()], -1)
    o, d = pixel_rays_world(pix, np.asarray(cam_from_world, dtype=float), camera)
    k, _ = caster.first_hit(o, d)
    hit = k >= 0
    n = plane_normals(corners)[k[hit]]
    cosang = np.einsum("ij,ij->i", n, d[hit])
    n = np.where(cosang[:, None] > 0, -n, n)
    shade = 0.45 + 0.55 * np.abs(cosang)
    col = (n + 1) / 2 * shade[:, None]
    flat = rgb.reshape(-1, 3)
    flat[hit] = col
    plane.reshape(-1)[hit] = k[hit]
    border = np.zeros((h, w), bool)
    border[:, 1:] |= plane[:, 1:] != plane[:, :-1]
    border[1:, :] |= plane[1:, :] != plane[:-1, :]
    rgb[border] *= 0.35
    return np.clip(rgb, 0, 1), plane


def planes_figure(corners, view=None, views=None, up=None, frame_points=None, caster=None) -> Figure:
    """Planar mesh from a mapping camera (beside its image) and from an oblique overview camera
    (framed on ``frame_points``, default the corners, with that box drawn in grey)."""
    corners = np.asarray(corners, dtype=float).reshape(-1, 4, 3)
    if caster is None and len(corners):
        from .mapping.assign import PlaneRaycaster

        caster = PlaneRaycaster(corners)
    pts = corners.reshape(-1, 3) if frame_points is None else np.asarray(frame_points, dtype=float).reshape(-1, 3)
    if up is None:
        up = up_direction(views, pts)
    panels = []
    if view is not None:
        try:
            img = view.load_color()
        except Exception as e:  # noqa: BLE001
            logger.warning("No image for %s: %s", view.name, e)
            img = None
        if img is not None:
            panels.append((img, view.camera, f"mapping view {view.name}", None))
        rgb, pl = render_planes(corners, view.cam_from_world, view.camera, caster)
        panels.append((rgb, view.camera, f"planes seen from it ({len(np.unique(pl[pl >= 0]))} visible)", None))
    T, cam, frame = overview_camera(pts, up, 800, 600)
    rgb, _ = render_planes(corners, T, cam, caster)
    box, box_ok = project_to_image(box_edges(frame), T, cam)
    panels.append((rgb, cam, f"overview: all {len(corners)} planes", box[box_ok]))
    with style():
        fig = new_figure(5.6 * len(panels), 5.0)
        axes = fig.subplots(1, len(panels), squeeze=False)[0]
        for ax, (arr, cam_i, title, box_i) in zip(axes, panels):
            ax.imshow(arr, extent=(0, cam_i.width, cam_i.height, 0), interpolation="antialiased")
            ax.set_xlim(0, cam_i.width)
            ax.set_ylim(cam_i.height, 0)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(title)
            if box_i is not None:
                draw_segments(ax, box_i, "0.55", 0.8, 1.0, None, 1)
        fig.suptitle("planar mesh, coloured by world normal ((n+1)/2: red x, green y, blue z), "
                     "dark outlines = plane borders", fontsize=11)
    return fig


def linemap_corners(linemap, folder=None) -> Optional[np.ndarray]:
    """The map's plane corners: from the line map (lipmap method) or ``folder/planes.ply``; else None."""
    planes = linemap.planes or {}
    if "corners" in planes and len(planes["corners"]):
        return np.asarray(planes["corners"], dtype=float).reshape(-1, 4, 3)
    if folder is not None and (Path(folder) / "planes.ply").exists():
        try:
            return corners_from_ply(Path(folder) / "planes.ply")
        except Exception as e:  # noqa: BLE001 - a bad PLY only costs the render
            logger.warning("Cannot read %s: %s", Path(folder) / "planes.ply", e)
    return None


def render_linemap_views(linemap, scene, out_dir, linemap_png: str = "linemap.png", planes_png: str = "planes.png",
                         map_dir=None) -> list:
    """Write ``linemap.png`` (and ``planes.png`` when the map has planes) into ``out_dir``.

    Args:
        linemap: :class:`~lipmap.linemap.LineMap`.
        scene: :class:`~lipmap.scene.Scene` (its mapping views give the camera, image and depth),
            or None for the overview only.
        out_dir: where the PNGs go (for ``map``: the folder of ``linemap.h5``).
        map_dir: folder of ``linemap.h5`` whose ``planes.ply`` is used when the map holds no
            planes (default ``out_dir``).

    Returns:
        the written paths.
    """
    out_dir = Path(out_dir)
    views = list(scene.mapping) if scene is not None else None
    written = []
    if len(linemap) == 0:
        logger.warning("Empty line map: no renders written to %s.", out_dir)
        return written
    view = pick_view(views, linemap.lines) if views else None
    corners = linemap_corners(linemap, map_dir or out_dir)
    up = up_direction(views, linemap.lines.reshape(-1, 3))
    line_query = None
    if corners is not None:
        from .mapping.assign import LineVisibility

        line_query = LineVisibility(linemap.lines, corners)
    fig = linemap_figure(linemap, view, views, corners, line_query, up)
    written.append(save_figure(fig, out_dir / linemap_png))
    if corners is not None:
        fig = planes_figure(corners, view, views, up, frame_points=linemap.lines.reshape(-1, 3),
                            caster=line_query.caster)
        written.append(save_figure(fig, out_dir / planes_png))
    return written


# ----------------------------------------------------------------------------------------------
# mapping metrics: precision / recall against the distance threshold
# ----------------------------------------------------------------------------------------------
def pr_curve(linemap, gt, thresholds=None, conf=None) -> dict:
    """Line-level and junction-level precision, recall and F-score at each threshold (M1 metrics).

    Uses ``lipmap.evaluation.m1_metrics`` on the same samples as ``evaluate_linemap`` (100 points per
    line; junctions = endpoints), so the curve at 5 cm equals map-eval's PREC/RECALL@0.05.

    Returns:
        ``{"thresholds": (T,), "line": {"precision", "recall", "f"}, "junction": {...}}`` (arrays).
    """
    from .evaluation import get_conf, load_ground_truth, m1_metrics
    from .linemap import LineMap

    conf = get_conf(conf)
    if isinstance(linemap, (str, Path)):
        linemap = LineMap.load(linemap)
    lines = linemap.lines if isinstance(linemap, LineMap) else np.asarray(linemap, dtype=float).reshape(-1, 2, 3)
    th = np.asarray(thresholds if thresholds is not None else np.geomspace(0.001, 0.2, 31), dtype=float)
    gt = load_ground_truth(gt, conf)
    out = {"thresholds": th}
    for level, pts in (("line", geo.sample_segments(lines, conf.m1_line_samples).reshape(-1, 3)),
                       ("junction", lines.reshape(-1, 3))):
        m = m1_metrics(pts, gt, tuple(th))
        out[level] = {k: np.array([m[f"{key}@{t:g}"] for t in th]) for k, key in
                      (("precision", "prec"), ("recall", "recall"), ("f", "f"))}
    out["n_lines"] = len(lines)
    out["gt_kind"] = "mesh" if gt.mesh is not None else "points"
    out["n_gt"] = int(len(gt.points))
    return out


def plot_pr_curve(linemap, gt, out_png, thresholds=None, conf=None, title: Optional[str] = None) -> Path:
    """Precision / recall / F (line level; junction level dashed) against the distance threshold,
    log x axis from 1 mm to 20 cm by default. Returns the PNG path."""
    d = pr_curve(linemap, gt, thresholds, conf)
    th_cm = d["thresholds"] * 100
    with style():
        fig = new_figure(10.5, 5.4)
        ax = fig.add_subplot(1, 1, 1)
        colors = {"precision": "#1f77b4", "recall": "#d62728", "f": "#2ca02c"}
        for k, c in colors.items():
            ax.plot(th_cm, 100 * d["line"][k], color=c, lw=2.2, label=f"{k} (line level)")
            ax.plot(th_cm, 100 * d["junction"][k], color=c, lw=1.3, ls="--", alpha=0.8, label=f"{k} (junctions)")
        ax.axvline(5.0, color="0.4", ls=":", lw=1.2)
        ax.text(5.0, 50, "5 cm ", color="0.3", fontsize=10, rotation=90, ha="right", va="center")
        ax.set_xscale("log")
        ax.set_xlim(th_cm[0], th_cm[-1])
        ax.set_ylim(0, 101)
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("distance threshold (cm, log scale)")
        ax.set_ylabel("percent")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), framealpha=0.9, fontsize=10)
        ax.set_title(title or f"Line map vs ground truth ({d['gt_kind']}): {d['n_lines']} lines")
        if d["gt_kind"] == "points":
            ax.text(1.02, 0.0, f"GT: point cloud of\n{d['n_gt']} points; below\nits point spacing the\ncurves "
                    "measure the\nground truth, not the map", transform=ax.transAxes, fontsize=9, color="0.35",
                    ha="left", va="bottom")
    return save_figure(fig, out_png)


__all__ = [
    "style",
    "new_figure",
    "save_figure",
    "figure_to_array",
    "dimmed",
    "show_image",
    "draw_segments",
    "project_to_image",
    "visible_line_indices",
    "draw_overlay",
    "overlay_figure",
    "overlay_array",
    "up_direction",
    "look_at",
    "scene_frame",
    "box_edges",
    "overview_camera",
    "pick_view",
    "linemap_figure",
    "planes_figure",
    "render_planes",
    "plane_normals",
    "corners_from_ply",
    "linemap_corners",
    "render_linemap_views",
    "pr_curve",
    "plot_pr_curve",
]
