"""``report.html``: the localization report as ONE self-contained page (plotly.js embedded, no network).

    write_report_html(OUT/<dataset>/report.html, ...)      called by localization.report.write_report

The page holds what ``report/report.md`` holds, made interactive: the per-scene table beside the paper's
row, ours beside every paper row at 5 cm / 5 deg (bars), each scene's error CDFs, and per scene a 3D
view (:mod:`lipmap.viz3d`) of its line map (colour by kind or support), planes, mapping cameras and the
query cameras at the ground-truth, point-only and point+line poses, coloured by translation error.
Hovering a query camera shows its errors; clicking one that has an overlay PNG (``report/query_*.png``,
linked by a relative path) shows it under the view.
"""
from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Optional

import numpy as np

from lipmap import logger
from lipmap.imageio import write_text_atomic

from .report_run import (COLORS, KEYS, LABELS, OVERVIEW_CELLS, PROVENANCE, R_THRESH_DEG, T_THRESH_CM, SceneAssets,
                         SceneRun, _num, cdf_label, cdf_range, cdf_steps, fmt_err, overview_rows, slug)

GT_COLOR = "#6a3d9a"
ERROR_COLORSCALE = [[0.0, "#1a9850"], [0.25, "#a6d96a"], [0.5, "#fee08b"], [0.75, "#f46d43"], [1.0, "#a50026"]]
# Nominal query camera (60 deg horizontal field of view, 4:3) for runs reported without their dataset:
# only the pyramid's shape depends on it, never a pose.
NOMINAL_CAMERA = (640, 480, (554.3, 554.3, 320.0, 240.0))

CLICK_JS = """
<script>
window.addEventListener('load', function () {
  document.querySelectorAll('.js-plotly-plot').forEach(function (el) {
    var box = document.getElementById(el.id + '-overlay');
    if (!box || !el.on) return;
    el.on('plotly_click', function (ev) {
      var p = ev && ev.points && ev.points[0];
      var link = p && p.customdata;
      if (!link) return;
      box.querySelector('img').src = link;
      var a = box.querySelector('a');
      a.href = link;
      a.textContent = link;
      box.style.display = 'block';
    });
  });
});
</script>
"""


def _table(header: list, rows: list) -> str:
    th = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    trs = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>\n" for r in rows)
    return f"<table>\n<tr>{th}</tr>\n{trs}</table>\n"


# ----------------------------------------------------------------------------------------------
# 2D plots
# ----------------------------------------------------------------------------------------------
def accuracy_figure(summaries: dict, paper: dict):
    """Per-scene % within 5 cm / 5 deg: ours (point, point+line) beside every column of the paper's table."""
    import plotly.graph_objects as go

    names = list(summaries)
    fig = go.Figure()
    for key in KEYS:
        fig.add_trace(go.Bar(x=names, y=[(summaries[n].get(key) or {}).get("acc_5cm_5deg") for n in names],
                             name=f"ours, {LABELS[key]}", marker_color=COLORS[key], texttemplate="%{y:.0f}",
                             textposition="outside"))
    greys = np.linspace(0.3, 0.8, max(len(paper["columns"]), 1))
    for c, g in zip(paper["columns"], greys):
        learned = paper["columns"][c]["group"] != "matching-based"
        vals = [(paper["scenes"].get(n.lower()) or {}).get(c, [None] * 3)[2] for n in names]
        grey = int(255 * g)
        fig.add_trace(go.Bar(x=names, y=vals, name=f"paper: {c}", marker_color=f"rgb({grey},{grey},{grey})",
                             marker_pattern_shape="/" if learned else ""))
    fig.update_layout(template="plotly_white", barmode="group", height=420, margin=dict(t=30, b=40),
                      yaxis=dict(title="queries within 5 cm and 5° (%)", range=[0, 105]), legend=dict(font=dict(size=11)))
    return fig


def cdf_figure(run: SceneRun):
    """Cumulative translation and rotation errors, point-only vs point+line (log x, the 5 cm / 5 deg lines dashed)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    fig = make_subplots(rows=1, cols=2, subplot_titles=("translation error (cm)", "rotation error (deg)"),
                        horizontal_spacing=0.08)
    errs = {key: run.errors(key) for key in KEYS}
    for col, (what, unit, thresh, which) in enumerate((("translation", "cm", T_THRESH_CM, 0),
                                                        ("rotation", "deg", R_THRESH_DEG, 1)), start=1):
        e = {key: errs[key][which] for key in KEYS}
        rng = cdf_range(e, thresh)
        if rng is None:
            continue
        for key in KEYS:
            xs, ys = cdf_steps(e[key], *rng)
            fig.add_trace(go.Scatter(x=xs, y=ys, mode="lines", line=dict(color=COLORS[key], width=2.5, shape="hv"),
                                     name=f"{what}, {cdf_label(key, e[key], unit, thresh)}", legendgroup=what,
                                     hovertemplate=f"%{{x:.2f}} {unit}: %{{y:.0f}} %<extra>{LABELS[key]}</extra>"),
                          row=1, col=col)
        fig.add_vline(x=thresh, line=dict(color="#555", dash="dash", width=1.2), row=1, col=col)
        fig.update_xaxes(type="log", range=[math.log10(rng[0]), math.log10(rng[1])], row=1, col=col)
        fig.update_yaxes(range=[0, 101], row=1, col=col)
    fig.update_yaxes(title_text="queries with smaller error (%)", row=1, col=1)
    fig.update_layout(template="plotly_white", height=430, margin=dict(t=40, b=40),
                      legend=dict(orientation="h", y=-0.18, font=dict(size=11)))
    return fig


# ----------------------------------------------------------------------------------------------
# the 3D view of one scene
# ----------------------------------------------------------------------------------------------
def _query_camera(assets: SceneAssets, q: str):
    from lipmap.scene import Camera

    if assets.scene is not None:
        try:
            return assets.scene.view(q)
        except KeyError:
            pass
    return Camera(*NOMINAL_CAMERA)


def scene_figure(name: str, run: SceneRun, assets: SceneAssets, overlay_links: dict):
    """The scene's line map, planes and mapping cameras (:func:`lipmap.viz3d.linemap_figure`) plus one trace
    per query pose group (ground truth, point only, point+line), the estimates coloured by translation error.

    Args:
        overlay_links: {query: relative link to its overlay PNG}, carried by its cameras for the click handler.
    """
    from lipmap import viz3d
    from lipmap.scene import View

    lm, scene = assets.linemap, assets.scene
    views = list(scene.mapping) if scene is not None else None
    fig = viz3d.linemap_figure(lm, views, title=f"{name}: {len(lm)} lines ({lm.metadata.get('method', '?')})",
                               corners=_corners(run, lm))
    size = fig.layout.meta["camera_size"]
    queries = list(run.queries)
    found = {q: _query_camera(assets, q) for q in queries}
    gt = [q for q in queries if isinstance(found[q], View) and found[q].cam_from_world is not None]
    if gt:
        viz3d.plot_cameras(fig, [found[q].cam_from_world for q in gt], [found[q].camera for q in gt],
                           f"queries: ground truth ({len(gt)})", GT_COLOR, size, width=2.0, dash="dot",
                           hovertext=[f"{q}<br>ground truth" for q in gt],
                           customdata=[overlay_links.get(q, "") for q in gt], group="query-gt")
    for key in KEYS:
        qs = [q for q in queries if run.poses.get(q, {}).get(key) is not None]
        if not qs:
            continue
        t = np.array([_num(run.queries[q].get(key, {}).get("t_cm")) for q in qs])
        cams = [found[q].camera if isinstance(found[q], View) else found[q] for q in qs]
        show_bar = key == "point+line"
        viz3d.plot_cameras(
            fig, [run.poses[q][key] for q in qs], cams,
            f"queries: {LABELS[key]} ({len(qs)} of {len(queries)}), coloured by error",
            size=size, width=3.0 if key == "point+line" else 2.0, dash="solid" if key == "point+line" else "dash",
            values=np.minimum(t, 1e6), cmin=0.0,
            cmax=2 * T_THRESH_CM, colorscale=ERROR_COLORSCALE,
            colorbar=dict(title=dict(text="query<br>error (cm)", side="top"), x=1.0, xanchor="right", len=0.4,
                          y=0.02, yanchor="bottom", thickness=14) if show_bar else None,
            hovertext=[_hover(q, run.queries[q], key, q in overlay_links) for q in qs],
            customdata=[overlay_links.get(q, "") for q in qs], group=f"query-{key}")
    return fig


def _corners(run: SceneRun, lm):
    from lipmap import viz

    return viz.linemap_corners(lm, run.map_path.parent)


def _hover(q: str, rec: dict, key: str, has_overlay: bool) -> str:
    r = rec.get(key, {})
    text = f"<b>{html.escape(q)}</b><br>{LABELS[key]}: {fmt_err(r)}"
    other = KEYS[1 - KEYS.index(key)]
    text += f"<br>({LABELS[other]}: {fmt_err(rec.get(other, {}))})"
    if key == "point+line" and "n_line_inliers" in r:
        text += f"<br>line inliers {r['n_line_inliers']} / {r.get('n_line_matches', '?')} matches"
    if has_overlay:
        text += "<br><i>click: overlay image</i>"
    return text


def _scene_section(name: str, run: SceneRun, assets: Optional[SceneAssets], out: Path, notes: list) -> str:
    """The 3D view of one scene, its overlay viewer and the table of example queries."""
    sid = slug(name)
    if assets is None or assets.linemap is None:
        return f"<h3>{html.escape(name)}</h3>\n<p class=\"note\">No line map, so no 3D view (see the notes).</p>\n"
    links = {q: p.relative_to(out).as_posix() if p.is_relative_to(out) else p.as_posix()
             for q, (_, _, p) in assets.overlays.items()}
    try:
        fig = scene_figure(name, run, assets, links)
    except Exception as e:  # noqa: BLE001 - one bad view must not lose the page
        logger.warning("3D view of %s failed: %s", name, e)
        notes.append(f"{name}: 3D view failed ({e}).")
        return f"<h3>{html.escape(name)}</h3>\n<p class=\"note\">3D view failed: {html.escape(str(e))}</p>\n"
    from lipmap import viz3d

    parts = [f"<h3>{html.escape(name)}</h3>",
             f"<div class=\"plot3d\">{viz3d.figure_div(fig, f'scene3d-{sid}')}</div>",
             f"<div id=\"scene3d-{sid}-overlay\" style=\"display:none\"><p>Overlay: <a href=\"#\"></a></p>"
             "<img style=\"max-width:100%\" alt=\"query overlay\"></div>"]
    if assets.overlays:
        rows = []
        for q, (kind, rank, _) in assets.overlays.items():
            rec = run.queries.get(q, {})
            what = "largest improvement" if kind == "improved" else "largest point+line error"
            rows.append(f"<tr><td>{what} #{rank}</td><td><code>{html.escape(q)}</code></td>"
                        f"<td>{html.escape(fmt_err(rec.get('point', {})))}</td>"
                        f"<td>{html.escape(fmt_err(rec.get('point+line', {})))}</td>"
                        f"<td><a href=\"{html.escape(links[q])}\">{html.escape(Path(links[q]).name)}</a></td></tr>")
        parts.append("<table><tr><th>example</th><th>query</th><th>point only</th><th>point+line</th><th>overlay</th></tr>"
                     + "\n".join(rows) + "</table>")
    return "\n".join(parts) + "\n"


# ----------------------------------------------------------------------------------------------
# the page
# ----------------------------------------------------------------------------------------------
def write_report_html(path, dataset: str, out: Path, runs: dict, summaries: dict, n_q: dict, paper: dict,
                      assets: dict, notes: list) -> Path:
    """Write the self-contained ``report.html`` (see the module docstring); returns its path.

    Args:
        out: OUT/<dataset>, the folder links are relative to (``path`` should be in it).
        runs, summaries, n_q: per scene, as :func:`localization.report.write_report` reads them.
        assets: {scene: :class:`~localization.report.SceneAssets`} (line map, dataset scene, overlays).
        notes: the report's notes (what is missing and why); 3D-view failures are added.
    """
    from lipmap import viz3d

    path, out = Path(path), Path(out)
    header, rows = overview_rows(runs, summaries, n_q, paper)
    body = [f"<h1>Localization report ({html.escape(dataset)})</h1>",
            f"<p>Made from the artifacts in <code>{html.escape(str(out))}</code>; {html.escape(PROVENANCE)} "
            "Static version: <a href=\"report/report.md\">report/report.md</a>; full table: "
            "<a href=\"summary.md\">summary.md</a>.</p>",
            _table(header, rows), f"<p class=\"note\">{html.escape(OVERVIEW_CELLS)}</p>",
            "<h2>Accuracy at 5 cm / 5°</h2>",
            "<p class=\"note\">Ours beside every row of the paper's 7-Scenes table (grey: matching-based; hatched: "
            "learning-based). The paper used the full test sequences and hloc SuperPoint+SuperGlue points, so compare "
            "trends, not absolute numbers.</p>",
            viz3d.figure_div(accuracy_figure(summaries, paper), "accuracy"),
            "<h2>Error distributions</h2>",
            "<p class=\"note\">Share of queries localized better than a given error (log x axis); the dashed line marks "
            "5 cm / 5°. A curve that ends below 100 % has failed queries.</p>"]
    for n, r in runs.items():
        if r.queries:
            body += [f"<h3>{html.escape(n)}</h3>", viz3d.figure_div(cdf_figure(r), f"cdf-{slug(n)}")]
    body += ["<h2>Line maps and poses</h2>",
             "<p class=\"note\">Drag to orbit, scroll to zoom. Buttons: colour the lines by kind (plane edges, lines on "
             "the planes, lines lifted with depth) or by support (number of images that see a line). Legend: click "
             "to hide or show the planes, the mapping cameras (grey) and the query cameras: ground truth (purple, dotted), "
             "point only (dashed) and point+line (solid), both coloured by translation error (green 0 to red 10 cm "
             "and more). Hover a query "
             "camera for its errors; click one marked <i>overlay</i> to show its overlay image below the view.</p>"]
    for n, r in runs.items():
        body.append(_scene_section(n, r, assets.get(n), out, notes))
    if notes:
        body += ["<h2>Notes</h2>", "<ul>" + "".join(f"<li>{html.escape(x)}</li>" for x in notes) + "</ul>"]
    write_text_atomic(path, viz3d.html_page(f"Localization report ({dataset})", "\n".join(body) + CLICK_JS))
    return path
