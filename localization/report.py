"""Visual report of a localization run, made from its artifacts only (no pose is recomputed).

    write_report(OUT, dataset) reads
        OUT/<dataset>/results.json, summary.md
        OUT/<dataset>/<scene>/results.json, the journal and the map it names (map-*/linemap.h5, planes.ply)
    and writes
        OUT/<dataset>/report/report.md
        OUT/<dataset>/report/accuracy_5cm5deg.png           ours (point, point+line) beside the paper's rows
        OUT/<dataset>/report/cdf_<scene>.png                 cumulative translation / rotation errors
        OUT/<dataset>/report/query_<scene>_<kind><k>.png     query overlays, point-only vs point+line pose
        OUT/<dataset>/report/linemap_<scene>.png, planes_<scene>.png
        OUT/<dataset>/report.html                            the same, interactive, in ONE self-contained file
                                                             (localization.report_html): plotly error CDFs and
                                                             3D views of each map, its planes and the poses
    and adds (or refreshes) a "Plots" block at the end of summary.md.

The query images and cameras come from the dataset (``root``): pass it, or the run's results.json
may name it ("root"); a synthetic run made by ``lipmap-loc eval`` without --root is found under
OUT/synthetic-data. Without a dataset root the image-based figures are skipped (and the report says so).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from lipmap import InputError, logger
from lipmap.imageio import write_text_atomic

from . import evaluate as ev
# the run's reading lives in report_run (shared with report.html); its public names stay importable from here
from .report_run import (COLORS, KEYS, LABELS, OVERVIEW_CELLS, PROVENANCE, R_THRESH_DEG, T_THRESH_CM, SceneAssets,
                         SceneRun, _num, _plural, cdf_label, cdf_range, cdf_steps, fmt_err, load_scene_run, overview_rows,
                         query_lines_file, select_examples, examples_note, slug)

BEGIN, END = "<!-- lipmap-report:begin -->", "<!-- lipmap-report:end -->"
HTML_NAME = "report.html"  # OUT/<dataset>/report.html, beside summary.md


# ----------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------
def _cdf_panel(ax, errs: dict, unit: str, thresh: float, what: str):
    rng = cdf_range(errs, thresh)
    if rng is None:
        ax.text(0.5, 0.5, "no successful query", ha="center", va="center", transform=ax.transAxes)
        return
    lo, hi = rng
    for key, e in errs.items():
        xs, ys = cdf_steps(e, lo, hi)
        ax.step(xs, ys, where="post", color=COLORS[key], lw=2.2, label=cdf_label(key, e, unit, thresh))
    ax.axvline(thresh, color="0.35", ls="--", lw=1.2)
    ax.text(thresh, 50, f"{thresh:g} {unit} ", color="0.25", fontsize=10, rotation=90, ha="right", va="center")
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(0, 101)
    import matplotlib.ticker as mt

    ax.xaxis.set_major_locator(mt.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(mt.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(mt.NullFormatter())
    ax.set_xlabel(f"{what} error ({unit}, log scale)")
    ax.set_ylabel("queries with smaller error (%)")
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    ax.legend(loc="lower right", framealpha=0.9)


def plot_error_cdfs(run: SceneRun, out_png) -> Path:
    """Cumulative distributions of translation (cm) and rotation (deg) errors, point vs point+line."""
    from lipmap import viz

    t, r = {}, {}
    for key in KEYS:
        t[key], r[key] = run.errors(key)
    n = len(run.queries)
    with viz.style():
        fig = viz.new_figure(14, 5.2)
        a0, a1 = fig.subplots(1, 2)
        _cdf_panel(a0, t, "cm", T_THRESH_CM, "translation")
        _cdf_panel(a1, r, "deg", R_THRESH_DEG, "rotation")
        a0.set_title("translation error")
        a1.set_title("rotation error")
        fig.suptitle(f"{run.name}: cumulative pose errors over {_plural(n, 'query', 'queries')} "
                     "(failed queries never reach the curve)")
    return viz.save_figure(fig, out_png)


def plot_accuracy_bars(scenes: dict, out_png, paper: Optional[dict] = None, n_queries: Optional[dict] = None) -> Path:
    """Per-scene % of queries within 5 cm and 5 deg: ours (point, point+line) beside the paper's rows.

    Args:
        scenes: {scene: {"point": S, "point+line": S}} (the results.json summaries).
        paper: the paper table (default: benchmarks/7scenes/paper_table.json).
    """
    from matplotlib.patches import Patch

    from lipmap import viz

    paper = paper or ev.load_paper_table()
    cols = list(paper["columns"])
    greys = {c: str(g) for c, g in zip([c for c in cols if paper["columns"][c]["group"] == "matching-based"],
                                         np.linspace(0.3, 0.78, 4))}
    greens = ["#1b7837", "#5aae61", "#a6dba0"]
    for c, g in zip([c for c in cols if paper["columns"][c]["group"] != "matching-based"], greens):
        greys[c] = g
    names = list(scenes)
    nb = 2 + len(cols)
    width = 0.86 / nb
    with viz.style():
        fig = viz.new_figure(max(9.0, 1.9 * len(names) + 4.5), 6.2)
        ax = fig.add_subplot(1, 1, 1)
        for i, name in enumerate(names):
            x0 = i - 0.43 + width / 2
            for j, key in enumerate(KEYS):
                v = (scenes[name].get(key) or {}).get("acc_5cm_5deg")
                if v is None:
                    continue
                ax.bar(x0 + j * width, v, width, color=COLORS[key], edgecolor="black", lw=0.6, zorder=3)
                ax.text(x0 + j * width, v + 1, f"{v:.0f}", ha="center", va="bottom", fontsize=9, zorder=4)
            prow = paper["scenes"].get(name.lower())
            if prow is None:
                ax.text(x0 + (2 + (len(cols) - 1) / 2) * width, 50, "not in the\npaper's table", ha="center",
                        va="center", fontsize=10, color="0.3", style="italic")
                continue
            for j, c in enumerate(cols):
                v = prow[c][2]
                ax.bar(x0 + (2 + j) * width, v, width, color=greys[c], edgecolor="black", lw=0.4, zorder=3,
                       hatch="//" if paper["columns"][c]["group"] != "matching-based" else None)
        labels = [f"{n}\n({_plural((n_queries or {}).get(n, '?'), 'query', 'queries')})" if n_queries else n for n in names]
        ax.set_xticks(range(len(names)), labels)
        ax.set_xlim(-0.55, len(names) - 0.45)
        ax.set_ylim(0, 108)
        ax.set_ylabel("queries within 5 cm and 5° (%)")
        ax.grid(True, axis="y", alpha=0.35, zorder=0)
        handles = [Patch(facecolor=COLORS[k], edgecolor="black", label=f"ours, {LABELS[k]}") for k in KEYS]
        in_paper = any(n.lower() in paper["scenes"] for n in names)
        if in_paper:
            handles += [Patch(facecolor=greys[c], edgecolor="black", label=f"paper: {c}",
                              hatch="//" if paper["columns"][c]["group"] != "matching-based" else None) for c in cols]
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=10, framealpha=0.95,
                  title="ours: this run; paper: full test\nsets, hloc SuperPoint+SuperGlue" if in_paper else None,
                  title_fontsize=10)
        fig.suptitle("Accuracy at 5 cm / 5°: ours beside the paper's 7-Scenes table")
    return viz.save_figure(fig, out_png)


def plot_query_overlay(run: SceneRun, query: str, view, linemap, out_png, line_query=None, kind: str = "",
                       rank: int = 0, min_px: float = 20.0, max_lines: int = 300) -> Path:
    """The query image with its detected 2D lines (blue) and the map's visible lines projected (red)
    with the point-only pose (left) and the point+line pose (right).

    Visible: in front, inside the image, not occluded by the map's planes (``line_query``) or, for
    maps without planes, by the query's depth map; drawn: those at least ``min_px`` long in the
    image, at most ``max_lines`` of them (best supported first).
    """
    from lipmap import viz
    from lipmap.lines2d import load_lines

    cam = view.camera
    try:
        img = view.load_color()
    except InputError as e:
        logger.warning("%s", e)
        img = None
    det = None
    qlines = query_lines_file(run)
    try:
        det = load_lines(qlines, query)
    except InputError as e:
        logger.warning("No query lines for the overlay of %s: %s", query, e)
    depth, occl = None, "planes"
    if line_query is None:
        occl = "none"
        if view.depth_path is not None:
            try:
                depth, occl = view.load_depth(), "query depth map"
            except InputError as e:
                logger.warning("%s", e)
    rec = run.queries.get(query, {})
    panels = []
    support = linemap.supports[:, 0] if len(linemap) else np.zeros(0, int)
    for key in KEYS:
        T = run.poses.get(query, {}).get(key)
        r = rec.get(key, {})
        if T is None:  # this method found no pose: nothing to project
            why = r.get("reason") or "failed"
            panels.append((f"{LABELS[key]}: no pose ({why})", np.zeros((0, 2, 2)), "map lines: no pose to project with"))
            continue
        idx = viz.visible_line_indices(linemap.lines, T, cam, depth=depth, line_query=line_query)
        segs, ok = viz.project_to_image(linemap.lines[idx], T, cam)
        idx, segs = idx[ok], segs[ok]
        # Short and weakly supported map lines bury the alignment under clutter: keep the lines the
        # line query could use (>= min_px) and, of those, the best supported.
        n_vis = len(idx)
        length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1) if len(segs) else np.zeros(0)
        keep = np.flatnonzero(length >= min_px)
        capped = len(keep) > max_lines
        if capped:
            keep = keep[np.lexsort((-length[keep], -support[idx[keep]]))[:max_lines]]
        segs = segs[keep]
        title = f"{LABELS[key]} pose: {_num(r.get('t_cm')):.1f} cm, {_num(r.get('R_deg')):.2f}°"
        if key == "point+line" and "n_line_inliers" in r:
            title += f"  ({r['n_line_inliers']}/{r.get('n_line_matches', '?')} line inliers)"
        else:
            title += f"  ({r.get('n_inliers', '?')}/{r.get('n_matches', '?')} point inliers)"
        label = f"map lines, projected ({len(segs)} of {n_vis} visible"
        if len(segs) < n_vis:
            label += f": ≥ {min_px:g} px" + (f", {max_lines} best supported" if capped else "")
        panels.append((title, segs, label + ")"))
    what = {"improved": "largest improvement", "worst": "largest point+line error"}.get(kind, kind)
    sup = f"{run.name} / {query}" + (f"  ({what} #{rank})" if kind else "") + f"  - occlusion test: {occl}"
    fig = viz.overlay_figure(img, cam, det, panels, sup)
    return viz.save_figure(fig, out_png)


# ----------------------------------------------------------------------------------------------
# the report
# ----------------------------------------------------------------------------------------------
def _dataset_root(out: Path, dataset: str, all_res: dict, run: SceneRun, root) -> Optional[Path]:
    cands = [root, run.results.get("root"), run.results.get("dataset_root"), all_res.get("root"),
             all_res.get("dataset_root"), (all_res.get("scene_details", {}).get(run.name) or {}).get("root")]
    if dataset == "synthetic":
        cands.append(out.parent / "synthetic-data")
    for c in cands:
        if c and Path(c).is_dir():
            return Path(c)
    return None


def _load_scene(dataset, root, run: SceneRun):
    from lipmap.datasets import load_scene

    # the published pseudo-GT folder the run read (pgt/<source>/7scenes), when it read that layout
    published = [Path(f).parent for f in run.results.get("pgt_files", []) if Path(f).parent.name == "7scenes"]
    return load_scene(dataset, root, run.name, pose_source=run.results.get("pose_source", "posetxt"),
                      pgt_dir=published[0] if published else None)


def detect_dataset(out_root) -> tuple[Path, str]:
    """(out_root, dataset) from ``OUT`` (one dataset folder with results.json) or ``OUT/<dataset>``."""
    out_root = Path(out_root)
    if (out_root / "results.json").exists():
        try:
            ds = json.loads((out_root / "results.json").read_text()).get("dataset")
        except json.JSONDecodeError:
            ds = None
        if ds and out_root.name == ds:
            return out_root.parent, ds
    found = sorted(p.name for p in out_root.iterdir() if (p / "results.json").exists()) if out_root.is_dir() else []
    if len(found) == 1:
        return out_root, found[0]
    if not found:
        raise InputError("no <dataset>/results.json here (run `lipmap-loc eval` first)", out_root)
    raise InputError(f"several datasets here ({', '.join(found)})", out_root, hint="pass --dataset")


# the figures write_report makes (report/ holds nothing else of ours)
GENERATED_PNG = ("accuracy_", "cdf_", "query_", "linemap_", "planes_")


def write_report(out_root, dataset: Optional[str] = None, root=None, n_examples: int = 3) -> Path:
    """Write OUT/<dataset>/report/ (PNGs + report.md) and OUT/<dataset>/report.html (one self-contained
    page with interactive plots and 3D views) from a finished run; returns report.md.

    Args:
        out_root: the ``--out`` folder of ``lipmap-loc eval`` (holds ``<dataset>/``).
        dataset: "7scenes" or "synthetic"; None: the only dataset under ``out_root``.
        root: dataset root for the query / mapping images (see the module docstring).
        n_examples: query overlays per kind (largest improvements, largest point+line errors).
    """
    if dataset is None:
        out_root, dataset = detect_dataset(out_root)
    out = Path(out_root) / dataset
    if not out.is_dir():
        raise InputError("no results for this dataset here (run `lipmap-loc eval` first)", out)
    rep = out / "report"
    rep.mkdir(parents=True, exist_ok=True)
    for old in rep.glob("*.png"):  # the figures are this run's: an earlier run's overlays must not stay beside them
        if old.name.startswith(GENERATED_PNG):
            old.unlink()
    all_res, runs = _load_runs(out)
    summaries = {n: all_res.get("scenes", {}).get(n) or r.results.get("summary", {}) for n, r in runs.items()}
    n_q = {n: len(r.queries) for n, r in runs.items()}
    paper = ev.load_paper_table()
    notes = []

    md = _overview_md(dataset, out, runs, summaries, n_q, paper)
    bars, md_acc = _accuracy_section(summaries, rep, paper, n_q, list(runs))
    cdfs, md_cdf = _cdf_section(runs, rep, notes)
    assets = {}
    md_q, md_m = _image_sections(out, dataset, all_res, runs, root, rep, n_examples, notes, assets)
    md += md_acc + md_cdf + md_q + md_m
    if notes:
        md += ["## Notes", ""] + [f"- {x}" for x in notes] + [""]
    report = rep / "report.md"
    write_text_atomic(report, "\n".join(md))
    _refresh_summary_links(out / "summary.md", rep, bars, cdfs)
    from .report_html import write_report_html

    html = write_report_html(out / HTML_NAME, dataset, out, runs, summaries, n_q, paper, assets, list(notes))
    logger.info("Report: %s (interactive: %s)", report, html)
    return report


def _load_runs(out: Path) -> tuple[dict, dict]:
    """The dataset's results.json ({} if absent) and every scene's run, in the results' scene order."""
    all_path = out / "results.json"
    all_res = json.loads(all_path.read_text()) if all_path.exists() else {}
    names = list(all_res.get("scenes", {})) or sorted(p.name for p in out.iterdir() if (p / "results.json").exists())
    if not names:
        raise InputError("no scene results (<scene>/results.json) here", out)
    return all_res, {n: load_scene_run(out / n) for n in names}


def _overview_md(dataset: str, out: Path, runs: dict, summaries: dict, n_q: dict, paper: dict) -> list:
    """Title, provenance and the per-scene table of ours beside the paper's LiP-Map row."""
    md = [f"# Localization report ({dataset})", "",
          f"Made from the artifacts in `{out}` (results.json, per-query journals, line maps); {PROVENANCE} "
          f"Full table: [summary.md](../summary.md). Interactive 3D views: [{HTML_NAME}](../{HTML_NAME}).", ""]
    header, rows = overview_rows(runs, summaries, n_q, paper)
    md += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    md += ["| " + " | ".join(r) + " |" for r in rows]
    md += ["", OVERVIEW_CELLS, ""]
    return md


def _accuracy_section(summaries: dict, rep: Path, paper: dict, n_q: dict, names: list) -> tuple[Path, list]:
    """Plot the 5 cm / 5° bars; returns the PNG and its report section."""
    bars = plot_accuracy_bars(summaries, rep / "accuracy_5cm5deg.png", paper, n_q)
    missing = [n for n in names if n.lower() not in paper["scenes"]]
    md = ["## Accuracy at 5 cm / 5°", "",
          "Ours (blue: point only, orange: point+line) beside every row of the paper's 7-Scenes table (grey: "
          "matching-based, hatched green: learning-based). The paper used the full test sequences and hloc "
          "SuperPoint+SuperGlue points, so compare trends, not absolute numbers."
          + (f" Not in the paper's table (no paper bars): {', '.join(missing)}." if missing else ""), "",
          f"![accuracy at 5 cm / 5 deg]({bars.name})", ""]
    return bars, md


def _cdf_section(runs: dict, rep: Path, notes: list) -> tuple[dict, list]:
    """Plot each scene's error CDFs; returns {scene: PNG} and the report section."""
    md = ["## Error distributions", "",
          "Share of queries localized better than a given error (log x axis); the dashed line marks 5 cm / 5°. "
          "A curve that ends below 100 % has failed queries.", ""]
    cdfs = {}
    for n, r in runs.items():
        if not r.queries:
            notes.append(f"{n}: no per-query results, no error distribution.")
            continue
        cdfs[n] = plot_error_cdfs(r, rep / f"cdf_{slug(n)}.png")
        md += [f"### {n}", "", f"![error distributions of {n}]({cdfs[n].name})", ""]
    return cdfs, md


def _image_sections(out: Path, dataset: str, all_res: dict, runs: dict, root, rep: Path, n_examples: int,
                    notes: list, assets: dict) -> tuple[list, list]:
    """The query-example and line-map sections, made together because both need each scene's line map;
    ``assets`` gets each scene's :class:`SceneAssets`."""
    md_q = ["## Query examples", "",
            f"For the {n_examples} queries whose translation error improved most with lines (first those that "
            "lines bring within 5 cm, a query without a point-only pose first of all), then the "
            f"{n_examples} largest point+line translation errors: the query image with its detected 2D lines "
            "(blue) and the map's visible 3D lines projected (red) with the point-only pose (left) and the "
            "point+line pose (right). Well-aligned red and blue lines mean a good pose.", ""]
    md_m = ["## Line maps", "",
            "Left: the map's lines drawn into the mapping view that sees most of them, over its dimmed image; "
            "right: all lines from an oblique virtual camera outside the scene's bounding box (grey), nearer "
            "lines thicker, with the mapping camera centres (green). Colour: support (number of images). "
            "Planar mesh (lipmap maps): ray-cast from the same mapping view and from the overview camera, "
            "coloured by normal.", ""]
    for n, r in runs.items():
        lm = _load_linemap_or_note(n, r, notes)
        scene = _load_dataset_scene_or_note(out, dataset, all_res, n, r, root, notes)
        assets[n] = SceneAssets(lm, scene)
        # the overview render works without the scene
        if lm is not None:
            md_m += _linemap_md(n, r, lm, scene, rep, notes)
        if lm is None or scene is None:
            continue
        md_q += _query_examples_md(n, r, lm, scene, rep, n_examples, notes, assets[n].overlays)
    return md_q, md_m


def _load_linemap_or_note(n: str, r: SceneRun, notes: list):
    """The scene's line map, or None with a note (no overlays or map renders without it)."""
    from lipmap.linemap import LineMap

    try:
        return LineMap.load(r.map_path)
    except InputError as e:
        notes.append(f"{n}: no line map ({e}); no overlays or map renders.")
    return None


def _load_dataset_scene_or_note(out: Path, dataset: str, all_res: dict, n: str, r: SceneRun, root, notes: list):
    """The scene from the dataset root, or None with a note saying why the image figures are missing."""
    droot = _dataset_root(out, dataset, all_res, r, root)
    if droot is None:
        notes.append(f"{n}: dataset root unknown (pass `--root`), so no query overlays and no mapping-view renders.")
        return None
    try:
        return _load_scene(dataset, droot, r)
    except InputError as e:
        notes.append(f"{n}: cannot load the scene from {droot} ({e}); no query overlays.")
    return None


def _linemap_md(n: str, r: SceneRun, lm, scene, rep: Path, notes: list) -> list:
    """Render the scene's line map (and planes) and return its report subsection."""
    from lipmap import viz

    try:
        written = viz.render_linemap_views(lm, scene, rep, f"linemap_{slug(n)}.png", f"planes_{slug(n)}.png",
                                           map_dir=r.map_path.parent)
    except Exception as e:  # noqa: BLE001 - one bad render must not lose the report
        logger.warning("Line map render of %s failed: %s", n, e)
        notes.append(f"{n}: line map render failed ({e}).")
        written = []
    md = [f"### {n}", "", f"{len(lm)} lines, method `{lm.metadata.get('method', '?')}`."
          + ("" if any("planes_" in p.name for p in written) else " This map has no planes (no planes.ply), so no planar mesh render."), ""]
    return md + [f"![{p.stem}]({p.name})" for p in written] + [""]


def _query_examples_md(n: str, r: SceneRun, lm, scene, rep: Path, n_examples: int, notes: list,
                       overlays: dict) -> list:
    """Overlay the scene's example queries (``overlays`` gets {query: (kind, rank, PNG)}); returns its
    report subsection ([] without examples)."""
    from lipmap import viz

    ex = select_examples(r, n_examples)
    why = examples_note(r, ex)
    if why:
        notes.append(f"{n}: {why}.")
    if not ex:
        return []
    lq = None
    if viz.linemap_corners(lm, r.map_path.parent) is not None:
        from lipmap.mapping.assign import LineVisibility

        lq = LineVisibility(lm.lines, viz.linemap_corners(lm, r.map_path.parent))
    md = [f"### {n}", "", "| example | query | point only | point+line | line inliers |", "|---|---|---|---|---|"]
    imgs = []
    for kind, rank, q in ex:
        p = _overlay_or_note(n, r, q, kind, rank, scene, lm, lq, rep, notes)
        if p is None:
            continue
        overlays[q] = (kind, rank, p)
        rec = r.queries[q]
        what = "largest improvement" if kind == "improved" else "largest point+line error"
        md.append(f"| {what} #{rank} | `{q}` | {fmt_err(rec['point'])} | {fmt_err(rec['point+line'])} "
                  f"| {rec['point+line'].get('n_line_inliers', '-')} |")
        imgs.append(f"![{kind} {rank}: {q}]({p.name})")
    return md + [""] + [x for i in imgs for x in (i, "")]


def _overlay_or_note(n: str, r: SceneRun, q: str, kind: str, rank: int, scene, lm, lq, rep: Path,
                     notes: list) -> Optional[Path]:
    """Plot one query overlay; None with a note when the query or the plot fails."""
    try:
        view = scene.view(q)
    except KeyError:
        notes.append(f"{n}: query {q} is not in the loaded scene; overlay skipped.")
        return None
    try:
        return plot_query_overlay(r, q, view, lm, rep / f"query_{slug(n)}_{kind}{rank}.png", lq, kind, rank)
    except Exception as e:  # noqa: BLE001 - one bad overlay must not lose the report
        logger.warning("Overlay of %s failed: %s", q, e)
        notes.append(f"{n}: overlay of {q} failed ({e}).")
    return None


def _refresh_summary_links(summary: Path, rep: Path, bars: Path, cdfs: dict):
    """Add or replace the plots block at the end of summary.md (nothing else is touched)."""
    block = [BEGIN, "## Plots", "", "Full visual report: [report/report.md](report/report.md); interactive, with 3D "
             f"views of the line maps and poses: [{HTML_NAME}]({HTML_NAME})", "",
             f"![accuracy at 5 cm / 5 deg](report/{bars.name})", ""]
    block += [f"![error distributions of {n}](report/{p.name})" for n, p in cdfs.items()]
    block += ["", END]
    text = summary.read_text() if summary.exists() else ""
    if BEGIN in text and END in text:
        pre, rest = text.split(BEGIN, 1)
        post = rest.split(END, 1)[1]
        text = pre.rstrip("\n") + "\n\n" + "\n".join(block) + post
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + "\n".join(block) + "\n"
    write_text_atomic(summary, text)


# ----------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------
def add_report_parser(subparsers):
    """`lipmap-loc report OUT [--dataset D] [--root ROOT] [--examples N]`."""
    from lipmap.cliargs import int_at_least

    p = subparsers.add_parser("report", help="plots, report.md and an interactive report.html (3D line maps, planes, "
                                             "poses) from a finished eval run (no pose is recomputed)")
    p.add_argument("out", type=Path, help="the --out folder of `lipmap-loc eval` (holds <dataset>/results.json)")
    p.add_argument("--dataset", default=None, choices=["7scenes", "synthetic"], help="default: the only dataset under OUT")
    p.add_argument("--root", type=Path, default=None,
                   help="dataset root for the query and mapping images (default: from results.json, or OUT/synthetic-data)")
    p.add_argument("--examples", type=int_at_least(0), default=3, help="query overlays per kind (improved, worst)")
    p.set_defaults(func=cli_report)
    return p


def html_report_of(report_md: Path) -> Path:
    """The ``report.html`` that :func:`write_report` wrote beside the ``report/`` folder of ``report_md``."""
    return Path(report_md).parent.parent / HTML_NAME


def cli_report(args) -> Path:
    path = write_report(args.out, args.dataset, root=args.root, n_examples=args.examples)
    print(f"report: {path}\nreport.html: {html_report_of(path)}")
    return path
