"""Size of ``report.html`` and its load time in headless Chromium, for an existing eval output.

    lipmap-loc eval --dataset 7scenes --root ../shared/data/7scenes-redkitchen-mini --scenes redkitchen \
        --max-point-matches 10 --out OUT
    python benchmarks/perf/bench_report_html.py OUT --dataset 7scenes --name report-html-7scenes-redkitchen

Rewrites the report (``localization.report.write_report``: timed), then opens ``OUT/<dataset>/report.html``
from disk in Debian's Chromium (playwright, network blocked) ``--loads`` times, each in a fresh page. Load
time: from the request of the page until every plot is drawn (each plotly div laid out, then two animation
frames so WebGL has drawn the 3D views). Writes ``benchmarks/results/<name>.json``.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import results  # noqa: E402

DRAWN_JS = """() => {
    const plots = Array.from(document.querySelectorAll('.js-plotly-plot'));
    return plots.length > 0 && plots.every(el => el._fullLayout && el._fullData);
}"""


def load_seconds(browser, html: Path) -> tuple[float, int, list]:
    """One load of ``html`` in a fresh page: (seconds, number of plots, console errors)."""
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.route("**/*", lambda r: r.continue_() if r.request.url.startswith("file:") else r.abort())
    t0 = time.perf_counter()
    page.goto(html.resolve().as_uri())
    page.wait_for_function(DRAWN_JS, timeout=120000, polling=20)
    page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    seconds = time.perf_counter() - t0
    n = page.evaluate("document.querySelectorAll('.js-plotly-plot').length")
    page.close()
    return seconds, n, errors


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the --out folder of `lipmap-loc eval`")
    ap.add_argument("--dataset", default="7scenes")
    ap.add_argument("--root", type=Path, default=None, help="dataset root (default: from results.json)")
    ap.add_argument("--loads", type=int, default=3)
    ap.add_argument("--name", default=None, help="results file name (default: report-html-<dataset>)")
    args = ap.parse_args(argv)
    from playwright.sync_api import sync_playwright

    from localization.report import html_report_of, write_report

    t0 = time.perf_counter()
    html = html_report_of(write_report(args.out, args.dataset, root=args.root))
    write_s = time.perf_counter() - t0
    size_mb = html.stat().st_size / 2**20
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=shutil.which("chromium"))
        loads = [load_seconds(browser, html) for _ in range(args.loads)]
        version = browser.version
        browser.close()
    secs = [s for s, _, _ in loads]
    errors = sorted({e for _, _, errs in loads for e in errs})
    n_plots = loads[0][1]
    scenes = sorted(p.parent.name for p in (args.out / args.dataset).glob("*/results.json"))
    print(f"{html}: {size_mb:.1f} MiB, {n_plots} plots, load {', '.join(f'{s:.2f}' for s in secs)} s "
          f"(Chromium {version}); report written in {write_s:.1f} s; console errors: {errors or 'none'}")
    name = args.name or f"report-html-{args.dataset}"
    row = [", ".join(scenes), f"{size_mb:.1f}", str(n_plots), f"{np.median(secs):.1f}", f"{write_s:.1f}"]
    results.write(name, {"html": str(html), "size_mib": size_mb, "n_plots": n_plots, "load_s": secs,
                         "write_report_s": write_s, "chromium": version, "console_errors": errors,
                         "table": {"header": ["scenes", "report.html (MiB)", "plots", "load in headless Chromium (s, median)",
                                              "write_report (s)"], "rows": [row]}})


if __name__ == "__main__":
    main()
