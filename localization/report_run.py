"""A finished localization run as both reports read it (``report.md`` and ``report.html``): the scene runs,
their journals' poses, the example queries, the error-CDF curves and the per-scene table. No pose is
recomputed; nothing here draws.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from lipmap import InputError, logger

from . import evaluate as ev

KEYS = ("point", "point+line")
LABELS = {"point": "point only", "point+line": "point+line"}
COLORS = {"point": "#1f77b4", "point+line": "#ff7f0e"}
T_THRESH_CM, R_THRESH_DEG = 5.0, 5.0

# ----------------------------------------------------------------------------------------------
# reading a run
# ----------------------------------------------------------------------------------------------
@dataclass
class SceneRun:
    """One scene's artifacts: results.json, the journal's poses, and file locations."""

    name: str
    folder: Path
    results: dict
    poses: dict = field(default_factory=dict)  # {query: {"point": (4, 4) or None, "point+line": ...}}
    journal: Optional[Path] = None

    @property
    def queries(self) -> dict:
        return self.results.get("queries", {})

    @property
    def map_path(self) -> Path:
        """The ``linemap.h5`` this run localized with (named in results.json)."""
        return self.folder / self.results.get("map", {}).get("path", "linemap.h5")

    def errors(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """Translation (cm) and rotation (deg) errors of every evaluated query; inf = failed."""
        t = [_num(q.get(key, {}).get("t_cm")) for q in self.queries.values()]
        r = [_num(q.get(key, {}).get("R_deg")) for q in self.queries.values()]
        return np.array(t, dtype=float), np.array(r, dtype=float)


@dataclass
class SceneAssets:
    """What one scene's image figures were made from, kept for the HTML report."""

    linemap: Optional[object] = None  # lipmap.linemap.LineMap
    scene: Optional[object] = None  # lipmap.scene.Scene, None without the dataset
    overlays: dict = field(default_factory=dict)  # {query: (kind, rank, overlay PNG)}


def _plural(n, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def _num(x) -> float:
    return math.inf if x is None else float(x)


def find_journal(folder: Path, results: dict) -> Optional[Path]:
    """The journal that produced ``results`` (named in it), else the newest."""
    if results.get("journal") and (folder / results["journal"]).exists():
        return folder / results["journal"]
    found = sorted(folder.glob("queries-*.jsonl"), key=lambda p: p.stat().st_mtime)
    if found:
        logger.warning("No journal matches the config in %s; using the newest, %s.", folder / "results.json", found[-1].name)
        return found[-1]
    return None


def read_journal_poses(path: Optional[Path]) -> dict:
    """{query: {"point": cam_from_world (4, 4) or None, "point+line": ...}}; later lines win."""
    out = {}
    if path is None or not path.exists():
        return out
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
            name = rec["name"]
        except (json.JSONDecodeError, KeyError, TypeError):
            continue  # a line cut by an interrupted write
        poses = {}
        for key in KEYS:
            T = (rec.get(key) or {}).get("cam_from_world")
            poses[key] = np.asarray(T, dtype=float) if T is not None and (rec.get(key) or {}).get("success") else None
        out[name] = poses
    return out


def load_scene_run(folder) -> SceneRun:
    folder = Path(folder)
    path = folder / "results.json"
    if not path.exists():
        raise InputError("scene results are missing (run `lipmap-loc eval` first)", path)
    try:
        results = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"not valid JSON: {e}", path) from None
    journal = find_journal(folder, results)
    return SceneRun(folder.name, folder, results, read_journal_poses(journal), journal)


def query_lines_file(run: SceneRun) -> Path:
    """The queries' 2D lines: ``lines2d_query-<digest>.h5`` as the pipeline names it (the newest when several
    settings left one each), else the undigested ``lines2d_query.h5`` of older runs."""
    found = sorted(run.folder.glob("lines2d_query-*.h5"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else run.folder / "lines2d_query.h5"


def select_examples(run: SceneRun, n: int = 3, good_cm: float = 5.0) -> list[tuple[str, int, str]]:
    """The ``n`` largest translation improvements of point+line over point-only, first among the queries that
    point+line puts within ``good_cm`` (else the largest are rescues of queries that fail either way, 5 m -> 1.4 m),
    from the queries with both poses or, within ``good_cm``, without a point-only pose (lines found what points could
    not: the first shown); then the ``n`` largest point+line translation errors among the rest of the queries with a
    point+line pose (a point-only pose may be missing: lines may be all there is).

    Returns:
        ``[(kind, rank, query)]`` with kind "improved" or "worst", rank from 1.
    """
    cand = []
    for q, rec in run.queries.items():
        p = run.poses.get(q, {})
        tp, tl = _num(rec.get("point", {}).get("t_cm")), _num(rec.get("point+line", {}).get("t_cm"))
        if p.get("point+line") is not None and math.isfinite(tl):
            cand.append((q, tp if p.get("point") is not None else math.inf, tl))
    better = [c for c in cand if c[1] > c[2] and (math.isfinite(c[1]) or c[2] <= good_cm)]
    improved = sorted(better, key=lambda c: (c[2] > good_cm, c[2] - c[1], c[2]))[:n]
    taken = {c[0] for c in improved}
    worst = sorted((c for c in cand if c[0] not in taken), key=lambda c: -c[2])[:n]
    return [("improved", i + 1, c[0]) for i, c in enumerate(improved)] + [("worst", i + 1, c[0]) for i, c in enumerate(worst)]


def examples_note(run: SceneRun, examples: list) -> Optional[str]:
    """Why a scene's examples lack the improvements (or all examples), or None when nothing is missing."""
    n_pl = sum(1 for q in run.queries if run.poses.get(q, {}).get("point+line") is not None)
    n_pt = sum(1 for q in run.queries if run.poses.get(q, {}).get("point") is not None)
    if not examples:
        return "no query has a point+line pose, so there is no example to show" if not n_pl else \
            "no query has a finite point+line error, so there is no example to show"
    if any(kind == "improved" for kind, _, _ in examples):
        return None
    if not n_pt:
        return (f"every point-only pose failed ({len(run.queries)} of {len(run.queries)} queries) and lines brought "
                "none within 5 cm: only the largest point+line errors are shown")
    return "no query's translation error improved with lines: only the largest point+line errors are shown"


# ----------------------------------------------------------------------------------------------
# error distributions and the per-scene table
# ----------------------------------------------------------------------------------------------
def cdf_range(errs: dict, thresh: float) -> Optional[tuple[float, float]]:
    """The log x range of an error CDF: from below the smallest positive error (and a tenth of the
    threshold) to beyond the largest and twice the threshold; None when no query succeeded."""
    finite = np.concatenate([e[np.isfinite(e)] for e in errs.values()])
    if len(finite) == 0:
        return None
    pos = finite[finite > 0]
    # an exact 0 (identical rotation) has no place on a log axis: it is drawn at the left edge
    lo = max(min(pos.min() if len(pos) else thresh, thresh / 10) / 1.6, 1e-3)
    hi = max(finite.max(), thresh * 2) * 1.6
    return lo, hi


def cdf_steps(e: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Step curve (x, % of ALL queries with a smaller error) from ``lo`` to ``hi``, drawn 'post':
    failed queries (inf) never reach it, so it ends below 100 %."""
    n = len(e)
    x = np.maximum(np.sort(e[np.isfinite(e)]), lo)
    y = 100.0 * np.arange(1, len(x) + 1) / max(n, 1)
    return np.concatenate([[lo], x, [hi]]), np.concatenate([[0.0], y, [y[-1] if len(y) else 0.0]])


def cdf_label(key: str, e: np.ndarray, unit: str, thresh: float) -> str:
    """Legend entry of one CDF: median, share within the threshold, failed queries."""
    n = len(e)
    med = np.median(e) if n else math.inf
    within = 100.0 * np.mean(e <= thresh) if n else 0.0
    fails = int(np.sum(~np.isfinite(e)))
    label = f"{LABELS[key]}: median {med:.2f} {unit}, {within:.0f}% ≤ {thresh:g} {unit}" if math.isfinite(med) \
        else f"{LABELS[key]}: median failed, {within:.0f}% ≤ {thresh:g} {unit}"
    return label + (f", {fails} failed" if fails else "")


def overview_rows(runs: dict, summaries: dict, n_q: dict, paper: dict) -> tuple[list, list]:
    """The per-scene table of ours beside the paper's LiP-Map row: (header, rows of cell strings)."""
    header = ["scene", "queries", "line map", "ours point", "ours point+line", "paper LiP-Map (point+line)"]
    rows = []
    for n, r in runs.items():
        s = summaries[n]
        prow = paper["scenes"].get(n.lower())
        pcell = "n/a (not in the paper)" if prow is None else "{:.1f} / {:.2f} / {:.1f}".format(*prow["LiP-Map (point+line)"])
        method = (r.results.get("config") or {}).get("map_method", "?")
        rows.append([n, str(n_q[n]), f"{r.results.get('n_map_lines', '?')} lines ({method})",
                     ev.format_summary(s.get("point")), ev.format_summary(s.get("point+line")), pcell])
    return header, rows


OVERVIEW_CELLS = "Cells: median translation (cm) / median rotation (deg) / % within 5 cm and 5°."
PROVENANCE = ("no pose was recomputed. Errors: translation = distance between camera centres, rotation = angle of "
              "R_gt^T R_est; failed queries count as infinitely wrong.")


def slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s)


def fmt_err(r: dict) -> str:
    t, R = _num(r.get("t_cm")), _num(r.get("R_deg"))
    return "failed" if not math.isfinite(t) else f"{t:.1f} cm / {R:.2f}°"
