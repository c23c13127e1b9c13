"""Interactive 3D views (plotly) of line maps, planes and cameras, in hloc's ``viz_3d`` habit.

    fig = init_figure()
    plot_linemap(fig, linemap)                   # lines by kind; buttons switch the colour to support
    plot_planes(fig, linemap_corners(linemap))   # lipmap.viz.linemap_corners
    plot_cameras(fig, poses, camera, name="mapping cameras")
    fig.show()                                   # in a notebook; or save_html(fig, "linemap.html")

Large maps stay usable: each ``plot_*`` call adds ONE trace whatever the number of items (lines of a
kind, planes, a group of cameras), its segments separated by NaN gaps in one array, so the browser
draws one WebGL object per trace and the page stores one binary array per coordinate. Every trace
carries ``meta = {"role": ...}`` (``lines``, ``planes``, ``cameras``) so pages and tests can find it.

Poses are ``cam_from_world``; cameras are :class:`lipmap.scene.Camera` (COLMAP pixel convention).
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from . import geometry as geo
from .errors import InputError
from .imageio import write_text_atomic
from .poses import invert_T

KIND_COLORS = {"plane edge": "#d62728", "on-plane": "#1f77b4", "lift": "#2ca02c", "line": "#7f7f7f"}
KIND_NAMES = {"plane edge": "plane edges", "on-plane": "on-plane lines", "lift": "lifted lines", "line": "lines"}
SUPPORT_COLORSCALE = "Plasma"
SUPPORT_TICKS = (1, 2, 3, 5, 10, 20, 50, 100, 200, 500, 1000)
CAMERA_COLOR = "#555555"


def _plotly():
    try:
        import plotly.graph_objects as go
    except ImportError as e:  # a dependency, but the message should say what to install
        raise ImportError("lipmap.viz3d needs plotly: pip install 'plotly>=7.1'") from e
    return go


# ----------------------------------------------------------------------------------------------
# figure and view
# ----------------------------------------------------------------------------------------------
def init_figure(height: int = 720, title: Optional[str] = None):
    """An empty 3D figure: white background, hidden axes, equal scale on all axes, legend top left.

    Returns:
        :class:`plotly.graph_objects.Figure`.
    """
    go = _plotly()
    axis = dict(visible=False, showbackground=False, showspikes=False)
    fig = go.Figure()
    fig.update_layout(
        template="plotly_white", height=height, title=title, margin=dict(l=0, r=0, t=40 if title else 10, b=0),
        scene=dict(xaxis=axis, yaxis=axis, zaxis=axis, aspectmode="data", dragmode="orbit"),
        legend=dict(x=0.01, y=0.92, yanchor="top", bgcolor="rgba(255,255,255,0.75)", itemsizing="constant"),
        uirevision="keep",  # restyling (colour buttons, legend clicks) keeps the user's viewpoint
    )
    return fig


def set_view(fig, points, up=None, elevation_deg: float = 35.0, azimuth_deg: float = 35.0, zoom: float = 1.8,
             margin: float = 0.1):
    """Look at ``points`` :math:`(N, 3)` obliquely from above, with ``up`` (default
    :func:`lipmap.viewpoints.up_direction` of the points) as the screen's up, and clip the axes to their
    robust box (1st-99th percentile, widened by ``margin``) so a few stray lines cannot shrink the map."""
    from .viewpoints import scene_frame, up_direction

    p = np.asarray(points, dtype=float).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if len(p) < 2:
        return fig
    up = up_direction(None, p) if up is None else np.asarray(up, dtype=float)
    frame = scene_frame(p, up)
    e1, e2, up = frame["axes"]
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    eye = zoom * (np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up)
    lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
    pad = margin * max(float(np.max(hi - lo)), 1e-3)
    lo, hi = lo - pad, hi + pad
    xyz = ("x", "y", "z")
    # the eye is relative to the centre of the axis box, in units of the box (isotropic with aspectmode "data")
    fig.update_layout(scene=dict(
        xaxis=dict(range=[lo[0], hi[0]]), yaxis=dict(range=[lo[1], hi[1]]), zaxis=dict(range=[lo[2], hi[2]]),
        camera=dict(up=dict(zip(xyz, up.tolist())), eye=dict(zip(xyz, eye.tolist())))))
    return fig


# ----------------------------------------------------------------------------------------------
# lines
# ----------------------------------------------------------------------------------------------
def segments_xyz(lines) -> np.ndarray:
    """3D segments :math:`(N, 2, 3)` as one polyline :math:`(3N, 3)` float32: start, end, NaN gap.

    The gap row makes plotly lift the pen between segments, so N segments are one trace.
    """
    lines = geo.as_segments3d(np.asarray(lines, dtype=float)).reshape(-1, 2, 3)
    out = np.full((len(lines), 3, 3), np.nan, np.float32)
    out[:, :2] = lines
    return out.reshape(-1, 3)


def _per_vertex(values, n_vertices_each: int) -> np.ndarray:
    return np.repeat(np.asarray(values), n_vertices_each, axis=0)


def plot_lines(fig, lines, color: str = "#d62728", name: str = "lines", width: float = 2.0,
               support=None, kind: Optional[str] = None, visible: Union[bool, str] = True) -> int:
    """Add 3D segments :math:`(N, 2, 3)` as ONE trace; returns its index in ``fig.data``.

    Args:
        support: :math:`(N,)` supporting views per line, shown on hover and used by the colour switch
            (:func:`add_color_switch`).
        kind: stored in the trace's ``meta`` (``{"role": "lines", "kind": kind}``).
    """
    go = _plotly()
    xyz = segments_xyz(lines)
    n = len(xyz) // 3
    tr = dict(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="lines", name=name, visible=visible,
              line=dict(color=color, width=width), connectgaps=False,
              meta={"role": "lines", "kind": kind or name, "n": n})
    if support is not None:
        tr["customdata"] = _per_vertex(np.asarray(support, dtype=np.int32).reshape(n), 3)
        tr["hovertemplate"] = f"{html.escape(name)}<br>support: %{{customdata}} images<extra></extra>"
    else:
        tr["hoverinfo"] = "name"
    fig.add_trace(go.Scatter3d(**tr))
    return len(fig.data) - 1


def line_kinds(linemap) -> np.ndarray:
    """Per line of a :class:`~lipmap.linemap.LineMap`: ``"plane edge"``, ``"on-plane"`` (detections lifted
    onto the planes), ``"lift"`` (the depth-lifting baseline) or ``"line"`` (unknown origin, e.g. LIMAP)."""
    method = linemap.metadata.get("method")
    if method == "lift":
        return np.full(len(linemap), "lift", dtype=object)
    if method == "lipmap" and linemap.planes is not None and "edge_line" in linemap.planes:
        from .linemap import edge_line_mask

        return np.where(edge_line_mask(linemap), "plane edge", "on-plane").astype(object)
    return np.full(len(linemap), "line", dtype=object)


def plot_linemap(fig, linemap, width: float = 2.0, color_switch: bool = True) -> list[int]:
    """Add a :class:`~lipmap.linemap.LineMap`: one trace per line kind (:func:`line_kinds`), coloured by
    kind, hover showing each line's support; with ``color_switch`` buttons recolour them by support.

    Returns:
        the indices of the added traces (none for an empty map).
    """
    kinds = line_kinds(linemap)
    support = linemap.supports[:, 0] if len(linemap) else np.zeros(0, np.int32)
    traces = []
    for kind in KIND_COLORS:
        sel = kinds == kind
        if sel.any():
            traces.append(plot_lines(fig, linemap.lines[sel], KIND_COLORS[kind], f"{KIND_NAMES[kind]} ({sel.sum()})",
                                     width, support[sel], kind))
    if color_switch and traces:
        add_color_switch(fig, traces)
    return traces


def _support_colorbar(max_support: float) -> dict:
    ticks = [t for t in SUPPORT_TICKS if t <= max(max_support, 2)]
    return dict(title=dict(text="support<br>(images)", side="top"), tickvals=np.log10(ticks).tolist(),
                ticktext=[str(t) for t in ticks], x=1.0, xanchor="right", len=0.45, y=0.98, yanchor="top",
                thickness=14, bgcolor="rgba(255,255,255,0.7)")


def add_color_switch(fig, traces: Sequence[int]):
    """Buttons over the figure that colour the line ``traces`` by kind (their own colour) or by support
    (log scale, one shared colour bar); the traces need ``customdata`` = support (:func:`plot_lines`)."""
    traces = list(traces)
    kind_colors = [fig.data[i].line.color for i in traces]
    logs = []
    for i in traces:
        s = fig.data[i].customdata
        logs.append(np.round(np.log10(np.maximum(np.asarray(s, dtype=float), 1.0)), 3).tolist() if s is not None else [0.0])
    cmax = max(1e-3, max((max(v) for v in logs if v), default=1e-3))
    by_kind = {"line.color": kind_colors, "line.showscale": [False] * len(traces)}
    by_support = {"line.color": logs, "line.colorscale": [SUPPORT_COLORSCALE] * len(traces),
                  "line.cmin": [0.0] * len(traces), "line.cmax": [cmax] * len(traces),
                  "line.showscale": [k == 0 for k in range(len(traces))],
                  "line.colorbar": [_support_colorbar(10 ** cmax)] * len(traces)}
    menu = dict(type="buttons", direction="right", x=0.01, y=0.99, xanchor="left", yanchor="top", showactive=True,
                active=0, pad=dict(l=0, t=0), bgcolor="white",
                buttons=[dict(label="colour: kind", method="restyle", args=[by_kind, traces]),
                         dict(label="colour: support", method="restyle", args=[by_support, traces])])
    fig.update_layout(updatemenus=list(fig.layout.updatemenus or []) + [menu])
    return fig


# ----------------------------------------------------------------------------------------------
# planes
# ----------------------------------------------------------------------------------------------
def plot_planes(fig, corners, name: Optional[str] = None, opacity: float = 0.35, max_planes: int = 20000,
                visible: Union[bool, str] = True) -> Optional[int]:
    """Add rectangles (corners :math:`(K, 4, 3)`, v1..v4 in order around the border) as ONE Mesh3d,
    two triangles each, coloured by normal as ``planes.ply`` ((n + 1) / 2); returns its trace index
    (None without planes).

    More than ``max_planes`` rectangles: only the largest are drawn, and the legend says so.
    """
    from .viz import plane_normals

    go = _plotly()
    c = np.asarray(corners, dtype=float).reshape(-1, 4, 3) if corners is not None else np.zeros((0, 4, 3))
    if len(c) == 0:
        return None
    n_all = len(c)
    label = name or f"planes ({n_all})"
    if n_all > max_planes:
        area = np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]), axis=1)
        c = c[np.sort(np.argsort(-area, kind="stable")[:max_planes])]
        label = name or f"planes (largest {max_planes} of {n_all})"
    v = c.reshape(-1, 3).astype(np.float32)
    k = np.arange(len(c))[:, None] * 4
    f = np.concatenate([k + np.array([0, 1, 2]), k + np.array([0, 2, 3])], axis=1).reshape(-1, 3).astype(np.int32)
    rgb = np.clip((plane_normals(c) + 1) * 127.5, 0, 255).astype(int)
    face_rgb = np.repeat([f"rgb({r},{g},{b})" for r, g, b in rgb], 2)
    fig.add_trace(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], facecolor=face_rgb,
                            opacity=opacity, flatshading=True, name=label, showlegend=True, hoverinfo="name",
                            visible=visible, meta={"role": "planes", "n": len(c), "n_all": n_all}))
    return len(fig.data) - 1


# ----------------------------------------------------------------------------------------------
# cameras
# ----------------------------------------------------------------------------------------------
# Pyramid of a camera drawn as one pen stroke: the image rectangle, then the apex joined to each
# corner (an edge is retraced to get back to the apex): C = apex, 0..3 = image corners.
_FRUSTUM_PATH = (0, 1, 2, 3, 0, "C", 1, "C", 2, "C", 3)
_APEX = np.array([p == "C" for p in _FRUSTUM_PATH] + [False])  # + the gap row


def frustums(cam_from_world, cameras, size: float) -> np.ndarray:
    """Camera pyramids as one polyline :math:`(12 N, 3)` float32 (11 vertices + a NaN gap per camera).

    Args:
        cam_from_world: :math:`(N, 4, 4)` poses.
        cameras: one :class:`~lipmap.scene.Camera` for all, or one per pose.
        size: depth of the drawn image plane in front of the centre (metres).
    """
    T = np.asarray(cam_from_world, dtype=float).reshape(-1, 4, 4)
    cams = list(cameras) if isinstance(cameras, (list, tuple)) else [cameras] * len(T)
    if len(cams) != len(T):
        raise InputError(f"{len(T)} poses but {len(cams)} cameras")
    out = np.full((len(T), len(_FRUSTUM_PATH) + 1, 3), np.nan, np.float32)
    for i, (Ti, cam) in enumerate(zip(T, cams)):
        # image corners in COLMAP pixels: the image spans [0, W] x [0, H]
        uv = np.array([[0.0, 0.0], [cam.width, 0.0], [cam.width, cam.height], [0.0, cam.height]])
        pts = geo.transform_points(invert_T(Ti), np.vstack([geo.unproject_points(uv, size, cam), np.zeros(3)]))
        out[i, :-1] = [pts[4] if p == "C" else pts[p] for p in _FRUSTUM_PATH]
    return out.reshape(-1, 3)


def plot_cameras(fig, cam_from_world, cameras, name: str = "cameras", color: str = CAMERA_COLOR, size: float = 0.1,
                 width: float = 2.0, values=None, cmin: Optional[float] = None, cmax: Optional[float] = None,
                 colorscale="RdYlGn_r", colorbar: Optional[dict] = None, hovertext: Optional[Sequence[str]] = None,
                 customdata: Optional[Sequence[str]] = None, group: Optional[str] = None,
                 dash: str = "solid", visible: Union[bool, str] = True) -> Optional[int]:
    """Add a group of cameras as ONE trace of pyramids (:func:`frustums`); returns its index (None if empty).

    Args:
        values: :math:`(N,)` per camera (e.g. pose error): the pyramids are coloured by it on
            ``colorscale`` between ``cmin`` and ``cmax``; ``colorbar`` (plotly dict) shows the scale.
        hovertext: :math:`(N,)` shown when hovering a camera's apex.
        customdata: :math:`(N,)` strings carried by the apex vertices (e.g. a link opened on click).
        group: stored in the trace's ``meta`` (``{"role": "cameras", "group": group}``).
        dash: plotly line dash ("solid", "dot", "dash", ...), to tell groups apart in the legend.
    """
    go = _plotly()
    T = np.asarray(cam_from_world, dtype=float).reshape(-1, 4, 4)
    if len(T) == 0:
        return None
    xyz = frustums(T, cameras, size)
    k = len(_APEX)
    line = dict(color=color, width=width, dash=dash)
    if values is not None:
        vals = np.asarray(values, dtype=float).reshape(len(T))
        line = dict(color=_per_vertex(vals, k).astype(np.float32), colorscale=colorscale, width=width, dash=dash,
                    cmin=float(np.nanmin(vals)) if cmin is None else cmin,
                    cmax=float(np.nanmax(vals)) if cmax is None else cmax,
                    showscale=colorbar is not None, colorbar=colorbar)
    tr = dict(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="lines", name=name, line=line, connectgaps=False,
              visible=visible, meta={"role": "cameras", "group": group or name, "n": len(T)})
    # Hover text on the apex rows only: the label then reads one camera, and a page of thousands of
    # cameras does not repeat each text eleven times.
    apex = np.tile(_APEX, len(T))
    if hovertext is not None:
        text = np.full(len(xyz), "", dtype=object)
        text[apex] = np.repeat(np.asarray(list(hovertext), dtype=object), 3)
        tr.update(hovertext=text, hoverinfo="text")
    else:
        tr["hoverinfo"] = "name"
    if customdata is not None:
        cd = np.full(len(xyz), "", dtype=object)
        cd[apex] = np.repeat(np.asarray(list(customdata), dtype=object), 3)
        tr["customdata"] = cd
    fig.add_trace(go.Scatter3d(**tr))
    return len(fig.data) - 1


def camera_size(points, fraction: float = 0.04) -> float:
    """A pyramid depth that reads well beside ``points``: ``fraction`` of their robust box diagonal."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if len(p) < 2:
        return 0.1
    lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
    return max(fraction * float(np.linalg.norm(hi - lo)), 1e-3)


# ----------------------------------------------------------------------------------------------
# a line map with its planes and mapping cameras
# ----------------------------------------------------------------------------------------------
def linemap_figure(linemap, views=None, corners=None, title: Optional[str] = None, height: int = 720,
                   max_cameras: int = 2000):
    """The 3D view of one map: lines by kind (switchable to support), planes (toggle in the legend),
    mapping cameras. ``views``: the mapping :class:`~lipmap.scene.View` s (None: no cameras);
    ``corners``: plane corners :math:`(K, 4, 3)` (default: the map's own, :func:`lipmap.viz.linemap_corners`).

    Returns:
        the figure; ``fig.layout.meta["camera_size"]`` is the pyramid depth used, for adding more cameras.
    """
    from .viewpoints import up_direction
    from .viz import linemap_corners

    fig = init_figure(height, title)
    plot_linemap(fig, linemap)
    if corners is None:
        corners = linemap_corners(linemap)
    plot_planes(fig, corners)
    pts = linemap.lines.reshape(-1, 3)
    views = [v for v in (views or []) if v.cam_from_world is not None]
    size = camera_size(np.vstack([pts, [v.center for v in views]]) if views else pts)
    if views:
        step = max(1, -(-len(views) // max_cameras))
        shown = views[::step]
        label = f"mapping cameras ({len(views)})" if step == 1 else f"mapping cameras (every {step}th of {len(views)})"
        plot_cameras(fig, [v.cam_from_world for v in shown], [v.camera for v in shown], label, CAMERA_COLOR, size,
                     width=1.5, hovertext=[v.name for v in shown], group="mapping")
        pts = np.vstack([pts, [v.center for v in views]])
    if corners is not None and len(corners):  # planes reach beyond the lines (walls): keep them in the box
        pts = np.vstack([pts, np.asarray(corners, dtype=float).reshape(-1, 3)])
    set_view(fig, pts, up_direction(views or None, pts))
    fig.update_layout(meta={"camera_size": size})
    return fig


# ----------------------------------------------------------------------------------------------
# self-contained HTML
# ----------------------------------------------------------------------------------------------
PAGE_STYLE = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 0 auto; max-width: 1400px;
       padding: 0 24px 40px; color: #222; }
h1 { font-size: 1.6em; } h2 { margin-top: 2em; border-bottom: 1px solid #ddd; } h3 { margin-top: 1.5em; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0.6em 0; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; } th { background: #f3f3f3; }
code { font-size: 0.92em; } .note { color: #555; font-size: 0.92em; }
.plot3d { border: 1px solid #ddd; }
"""


def figure_div(fig, div_id: str, config: Optional[dict] = None) -> str:
    """The HTML of one figure (a div and the script that draws it), without plotly.js (see :func:`html_page`)."""
    import plotly.io as pio

    config = {"displaylogo": False, "responsive": True, **(config or {})}
    return pio.to_html(fig, full_html=False, include_plotlyjs=False, div_id=div_id, config=config)


def html_page(title: str, body: str, head: str = "") -> str:
    """A complete page that works offline: plotly.js is embedded once, in the head (as
    ``include_plotlyjs=True`` would), so figure divs from :func:`figure_div` need no network."""
    from plotly.offline import get_plotlyjs

    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title)}</title>\n<style>{PAGE_STYLE}</style>\n"
            "<script type=\"text/javascript\">window.PlotlyConfig = {MathJaxConfig: 'local'};</script>\n"
            f"<script type=\"text/javascript\">{get_plotlyjs()}</script>\n{head}</head>\n<body>\n{body}\n</body>\n</html>\n")


def save_html(fig, path, title: str = "lipmap", intro: str = "") -> Path:
    """Write ``fig`` as a self-contained page (plotly.js embedded, no network needed), atomically."""
    path = Path(path)
    body = f"<h1>{html.escape(title)}</h1>\n{intro}\n<div class=\"plot3d\">{figure_div(fig, 'linemap-3d')}</div>"
    write_text_atomic(path, html_page(title, body))
    return path


def save_linemap_html(linemap, path, views=None, corners=None, title: Optional[str] = None) -> Path:
    """``linemap.html``: :func:`linemap_figure` of ``linemap`` as a self-contained page."""
    n = len(linemap)
    meta = linemap.metadata
    title = title or f"Line map: {n} lines ({meta.get('method', '?')}), {meta.get('scene', '')}".rstrip(", ")
    fig = linemap_figure(linemap, views, corners)
    intro = ("<p class=\"note\">Drag to orbit, scroll to zoom. The buttons colour the lines by kind or by support "
             "(number of images that see a line); click a legend entry to hide or show it.</p>")
    return save_html(fig, path, title, intro)


__all__ = [
    "init_figure",
    "set_view",
    "segments_xyz",
    "plot_lines",
    "line_kinds",
    "plot_linemap",
    "add_color_switch",
    "plot_planes",
    "frustums",
    "plot_cameras",
    "camera_size",
    "linemap_figure",
    "figure_div",
    "html_page",
    "save_html",
    "save_linemap_html",
]
