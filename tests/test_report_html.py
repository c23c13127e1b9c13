"""report.html and linemap.html in a real browser: Debian's Chromium, driven by playwright, offline.

The pages are opened from disk with every request that is not a ``file:`` URL blocked (and recorded), and
checked for: no JavaScript error; every 3D view drawn by WebGL (hiding its traces must change a good share
of its pixels); the traces the page holds (kinds, planes, camera groups) matching the map and the run; the
colour buttons and the click-to-overlay handler working in the page.

Without Chromium or playwright the tests skip, unless ``LIPMAP_REQUIRE_BROWSER=1`` (set by .ci/run), which
makes a missing browser a failure.
"""
from __future__ import annotations

import os
import shutil

import cv2
import numpy as np
import pytest
from fake_run import Q0, make_fake_run

pytestmark = pytest.mark.browser

REQUIRED = os.environ.get("LIPMAP_REQUIRE_BROWSER") == "1"
TRACES_JS = """Array.from(document.querySelectorAll('.js-plotly-plot')).map(el => ({
    id: el.id, n: el.data.length, names: el.data.map(t => t.name), meta: el.data.map(t => t.meta || null)}))"""


def _missing() -> str:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[test]')"
    if shutil.which("chromium") is None:
        return "Debian's chromium is not installed (apt-get install -y chromium)"
    return ""


@pytest.fixture(scope="module")
def browser():
    why = _missing()
    if why:
        if REQUIRED:
            pytest.fail(f"LIPMAP_REQUIRE_BROWSER=1 but {why}")
        pytest.skip(why)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        # the system's Chromium: playwright's own browser download is never used
        b = p.chromium.launch(executable_path=shutil.which("chromium"))
        yield b
        b.close()


class Page:
    """One page opened from disk, offline, with its console errors and blocked requests recorded."""

    def __init__(self, browser, path):
        self.errors, self.blocked = [], []
        self.page = browser.new_page(viewport={"width": 1200, "height": 900})
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.route("**/*", self._route)
        self.page.goto(path.resolve().as_uri())
        self.page.wait_for_function("Array.from(document.querySelectorAll('.js-plotly-plot'))"
                                    ".every(el => el._fullLayout && el._fullData)", timeout=30000)

    def _route(self, route):
        if route.request.url.startswith("file:"):
            route.continue_()
        else:
            self.blocked.append(route.request.url)
            route.abort()

    def traces(self) -> dict:
        return {p["id"]: p for p in self.page.evaluate(TRACES_JS)}

    def shot(self, div_id: str) -> np.ndarray:
        el = self.page.locator(f"#{div_id}")
        el.scroll_into_view_if_needed()
        # two animation frames: WebGL draws on the frame after a change
        self.page.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        img = cv2.imdecode(np.frombuffer(el.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None
        return img.astype(int)

    def drawn_share(self, div_id: str) -> float:
        """Share of the view's pixels that change when all its traces are hidden: what WebGL drew."""
        with_data = self.shot(div_id)
        self.page.evaluate("id => Plotly.restyle(id, {visible: false})", div_id)
        without = self.shot(div_id)
        self.page.evaluate("id => Plotly.restyle(id, {visible: true})", div_id)
        return float((np.abs(with_data - without).sum(-1) > 30).mean())

    def close(self):
        self.page.close()


def _roles(trace: dict) -> list:
    return [(m or {}).get("role") for m in trace["meta"]]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from localization.report import html_report_of, write_report

    run = make_fake_run(tmp_path_factory.mktemp("report"))
    md = write_report(run["out"], "7scenes", root=run["root"])
    return html_report_of(md)


def test_report_html_in_chromium(browser, report):
    page = Page(browser, report)
    try:
        traces = page.traces()
        assert set(traces) == {"accuracy", "cdf-chess", "cdf-room-x", "scene3d-chess"}  # room-x: no map, no 3D view
        chess = traces["scene3d-chess"]
        metas = chess["meta"]
        assert _roles(chess) == ["lines", "lines", "planes", "cameras", "cameras", "cameras", "cameras"]
        assert [(m["kind"], m["n"]) for m in metas[:2]] == [("plane edge", 2), ("on-plane", 2)]
        assert metas[2]["n"] == 2  # both planes
        assert [m["group"] for m in metas[3:]] == ["mapping", "query-gt", "query-point", "query-point+line"]
        assert [m["n"] for m in metas[3:]] == [1, 2, 2, 2]
        assert len(traces["cdf-chess"]["names"]) == 4  # point, point+line x translation, rotation

        share = page.drawn_share("scene3d-chess")
        assert share > 0.02, f"the 3D view drew {100 * share:.2f} % of its pixels"
        for div in ("accuracy", "cdf-chess"):
            img = page.shot(div)
            assert (np.abs(img - 255).sum(-1) > 30).mean() > 0.02, div

        # the hover text of the point-only cameras: each query's errors
        hover = page.page.evaluate("() => document.getElementById('scene3d-chess').data[5].hovertext.filter(t => t)")
        assert any(Q0 in t and "point only: 5.0 cm / 0.10°" in t for t in hover)

        # colour by support: a real click on the button restyles every line trace
        page.page.locator("#scene3d-chess .updatemenu-button", has_text="colour: support").click()
        colors = page.page.evaluate("() => document.getElementById('scene3d-chess').data.slice(0, 2).map(t => t.line.color)")
        assert all(isinstance(c, list) and len(c) == 6 for c in colors), colors
        assert page.drawn_share("scene3d-chess") > 0.02

        # a click on a query camera shows its overlay PNG, found on disk through the relative link
        link = page.page.evaluate("() => document.getElementById('scene3d-chess').data[6].customdata.find(c => c)")
        assert link.startswith("report/query_chess_") and (report.parent / link).exists()
        page.page.evaluate("l => document.getElementById('scene3d-chess')"
                           ".emit('plotly_click', {points: [{customdata: l}]})", link)
        page.page.wait_for_function("() => { const i = document.querySelector('#scene3d-chess-overlay img');"
                                    " return i.complete && i.naturalWidth > 0; }", timeout=5000)
        assert page.page.is_visible("#scene3d-chess-overlay")

        assert page.errors == [], page.errors
        assert page.blocked == [], f"the page asked the network for {page.blocked}"
    finally:
        page.close()


def test_linemap_html_in_chromium(browser, tmp_path):
    from lipmap.datasets import load_scene
    from lipmap.linemap import LineMap
    from lipmap.viz3d import save_linemap_html

    run = make_fake_run(tmp_path)
    lm = LineMap.load(run["out"] / "7scenes" / "chess" / "linemap.h5")
    scene = load_scene("7scenes", run["root"], "chess")
    path = save_linemap_html(lm, tmp_path / "linemap.html", views=scene.mapping)
    page = Page(browser, path)
    try:
        (view,) = page.traces().values()
        assert _roles(view) == ["lines", "lines", "planes", "cameras"]
        assert [m.get("kind") for m in view["meta"][:2]] == ["plane edge", "on-plane"]
        share = page.drawn_share(view["id"])
        assert share > 0.02, f"the 3D view drew {100 * share:.2f} % of its pixels"
        assert page.errors == [] and page.blocked == [], (page.errors, page.blocked)
    finally:
        page.close()
