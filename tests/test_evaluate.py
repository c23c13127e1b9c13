import math
import re

import numpy as np
import pytest

from lipmap.poses import make_T
from localization.evaluate import load_paper_table, query_errors, summarize, summary_markdown


def test_query_errors_and_failures():
    I = np.eye(4)
    gt = {"a": I, "b": I, "c": I, "bad_gt": None}
    est = {"a": make_T(np.eye(3), [0.03, 0, 0]), "b": None}  # c missing -> failed
    errs = query_errors(est, gt)
    assert set(errs) == {"a", "b", "c"}  # invalid GT is skipped, not counted
    assert errs["a"] == pytest.approx((0.03, 0.0))
    assert math.isinf(errs["b"][0]) and math.isinf(errs["c"][1])
    s = summarize(errs, [5.0, 7.0])
    assert s["n_queries"] == 3 and s["n_failed"] == 2
    assert s["acc_5cm_5deg"] == pytest.approx(100 / 3)
    assert s["median_t_cm"] is None  # the median is a failure when most queries failed
    assert s["median_ms_per_query"] == 6.0


def test_summarize_medians():
    errs = {str(i): (0.01 * i, 0.5 * i) for i in range(1, 6)}
    s = summarize(errs)
    assert s["median_t_cm"] == pytest.approx(3.0) and s["median_R_deg"] == pytest.approx(1.5)
    assert s["acc_5cm_5deg"] == 100.0 and s["acc_2cm_2deg"] == 40.0


def test_paper_table_matches_tex(shared_data):
    tex = (shared_data.parent / "paper" / "lipmap-paper.tex").read_text()
    table = load_paper_table()
    for scene, cols in table["scenes"].items():
        row = next(l for l in tex.splitlines() if l.strip().lower().startswith(scene + " &"))
        cells = [re.sub(r"\\textbf\{([^}]*)\}", r"\1", c).strip().rstrip("\\").strip() for c in row.split("&")[1:]]
        vals = [[float(x) for x in c.split("/")] for c in cells]
        assert vals == [cols[c] for c in table["columns"]], scene


def test_summary_markdown_has_paper_rows():
    res = {"scenes": {"redkitchen": {"point": summarize({"q": (0.02, 1.0)}), "point+line": summarize({"q": (0.01, 0.5)})}}}
    md = summary_markdown(res, "7scenes", "posetxt")
    assert "| redkitchen | 1 (0 / 0) | 2.0 / 1.00 / 100.0 | 1.0 / 0.50 / 100.0 | 4.2 / 1.39 / 58.9" in md
    assert "posetxt" in md


def test_summary_markdown_reports_fine_thresholds_and_names_its_ground_truth():
    # 1.5 cm / 0.5 deg: outside 1 cm 1 deg, inside 2 cm 2 deg; the point+line query is inside both.
    res = {"scenes": {"s": {"point": summarize({"q": (0.015, 0.5)}), "point+line": summarize({"q": (0.005, 0.5)})}}}
    md = summary_markdown(res, "7scenes", "sfm")
    assert "| s | 0.0 | 100.0 | 100.0 | 100.0 | 100.0 | 100.0 |" in md
    assert "pseudo ground truth" in md and "KinectFusion" not in md
    assert "KinectFusion" in summary_markdown(res, "7scenes", "posetxt")
    assert "exact poses" in summary_markdown(res, "synthetic", "posetxt")
