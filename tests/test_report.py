"""localization.report: a report made from a tiny fake run (results, journal, line map, images)."""
from __future__ import annotations

import argparse

import cv2
import numpy as np
import pytest
from fake_run import Q0, Q1, make_fake_run

from localization import report as rp
from localization.config import LocalizationConfig


@pytest.fixture()
def fake_run(tmp_path):
    return make_fake_run(tmp_path)


def test_journal_named_in_results(fake_run):
    run = rp.load_scene_run(fake_run["out"] / "7scenes" / "chess")
    assert run.journal.name == f"queries-{LocalizationConfig().digest()}.jsonl"
    np.testing.assert_allclose(run.poses[Q0]["point+line"], fake_run["est"][Q0]["point+line"])
    assert rp.select_examples(run, 3) == [("improved", 1, Q0), ("worst", 1, Q1)]
    assert rp.query_lines_file(run) == run.folder / "lines2d_query.h5"  # an older run's name
    (run.folder / "lines2d_query.h5").rename(run.folder / "lines2d_query-0123abcd.h5")  # the pipeline's name
    assert rp.query_lines_file(run) == run.folder / "lines2d_query-0123abcd.h5"


def test_improved_examples_show_queries_lines_bring_within_5_cm_first(tmp_path):
    from localization.report_run import SceneRun, select_examples

    errs = {"a": (520.0, 140.0), "b": (30.0, 1.0), "c": (8.0, 2.0), "d": (3.0, 4.0), "e": (900.0, 900.0)}
    run = SceneRun("s", tmp_path, {"queries": {q: {"point": {"t_cm": p}, "point+line": {"t_cm": pl}}
                                               for q, (p, pl) in errs.items()}},
                   poses={q: {"point": np.eye(4), "point+line": np.eye(4)} for q in errs})
    # b and c end within 5 cm; a gains the most centimetres but still fails
    assert select_examples(run, 3) == [("improved", 1, "b"), ("improved", 2, "c"), ("improved", 3, "a"),
                                       ("worst", 1, "e"), ("worst", 2, "d")]
    assert select_examples(run, 1)[0] == ("improved", 1, "b")
    assert select_examples(run, 1, good_cm=0.5)[0] == ("improved", 1, "a")  # none within: the largest gain


def test_a_query_only_lines_localize_within_5_cm_is_the_first_improvement(tmp_path):
    """Without a point-only pose (scarce points, or none), a point+line pose within 5 cm is what lines are for: it
    leads the improvements; one farther off is a guess, among the largest errors only."""
    from localization.report_run import SceneRun, examples_note, select_examples

    errs = {"a": (30.0, 1.0), "b": (None, 2.0), "c": (None, 147.0), "d": (None, 0.5)}
    run = SceneRun("s", tmp_path, {"queries": {q: {"point": {"t_cm": p}, "point+line": {"t_cm": pl}}
                                               for q, (p, pl) in errs.items()}},
                   poses={q: {"point": None if p is None else np.eye(4), "point+line": np.eye(4)}
                          for q, (p, _) in errs.items()})
    assert select_examples(run, 3) == [("improved", 1, "d"), ("improved", 2, "b"), ("improved", 3, "a"),
                                       ("worst", 1, "c")]
    lines_only = SceneRun("s", tmp_path, {"queries": {q: run.queries[q] for q in "bcd"}},
                          poses={q: run.poses[q] for q in "bcd"})
    ex = select_examples(lines_only, 3)
    assert ex[:2] == [("improved", 1, "d"), ("improved", 2, "b")] and examples_note(lines_only, ex) is None
    far = SceneRun("s", tmp_path, {"queries": {"c": run.queries["c"]}}, poses={"c": run.poses["c"]})
    ex = select_examples(far, 3)
    assert ex == [("worst", 1, "c")] and "every point-only pose failed" in examples_note(far, ex)


def test_write_report(fake_run):
    out, root = fake_run["out"], fake_run["root"]
    path = rp.write_report(out, "7scenes", root=root)
    rep = out / "7scenes" / "report"
    assert path == rep / "report.md"
    expected = ["accuracy_5cm5deg.png", "cdf_chess.png", "cdf_room-x.png", "query_chess_improved1.png",
                "query_chess_worst1.png", "linemap_chess.png", "planes_chess.png"]
    for name in expected:
        img = cv2.imread(str(rep / name))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 400, name
    text = path.read_text()
    for section in ("# Localization report (7scenes)", "## Accuracy at 5 cm / 5°", "## Error distributions",
                    "### chess", "### room-x", "## Query examples", "## Line maps", "## Notes"):
        assert section in text, section
    for name in expected:
        assert f"]({name})" in text, name
    assert f"| largest improvement #1 | `{Q0}` | 5.0 cm / 0.10° | 0.5 cm / 0.10° | 7 |" in text
    assert "Not in the paper's table (no paper bars): room-x." in text
    assert "room-x: cannot load the scene" in text  # no images for it: said, not silently dropped
    # summary.md gets one plots block, refreshed (not duplicated) by a second run
    rp._refresh_summary_links(out / "7scenes" / "summary.md", rep, rep / "accuracy_5cm5deg.png",
                              {"chess": rep / "cdf_chess.png"})
    summary = (out / "7scenes" / "summary.md").read_text()
    assert summary.startswith("# Localization summary (7scenes)\n\n| table |")
    assert summary.count(rp.BEGIN) == 1 and summary.count(rp.END) == 1
    assert "](report/accuracy_5cm5deg.png)" in summary and "](report/cdf_chess.png)" in summary
    assert "[report.html](report.html)" in summary
    # the interactive page (checked in a browser by test_report_html.py): one file, no script from the network
    page = rp.html_report_of(path).read_text()
    assert rp.html_report_of(path) == out / "7scenes" / "report.html"
    assert "<script src=" not in page and "Plotly.newPlot" in page
    assert 'id="scene3d-chess"' in page and 'id="scene3d-room-x"' not in page  # room-x has no line map
    assert "report/query_chess_improved1.png" in page  # the overlay, linked relative to the page


def test_report_without_dataset_root_and_cli(fake_run, capsys):
    out = fake_run["out"]
    ap = argparse.ArgumentParser()
    rp.add_report_parser(ap.add_subparsers(dest="command"))
    args = ap.parse_args(["report", str(out)])  # dataset detected, no root
    path = args.func(args)
    assert capsys.readouterr().out.splitlines()[-1] == f"report.html: {out / '7scenes' / 'report.html'}"
    text = path.read_text()
    assert "chess: dataset root unknown (pass `--root`)" in text
    rep = path.parent
    assert (rep / "linemap_chess.png").exists()  # the overview needs no images
    assert not list(rep.glob("query_*.png"))
    page = rp.html_report_of(path).read_text()
    assert 'id="scene3d-chess"' in page and "queries: ground truth" not in page  # estimates only, no GT
    with pytest.raises(rp.InputError):
        rp.write_report(out / "nothing-here", None)


def test_a_report_holds_only_its_own_runs_pictures(fake_run):
    """Two runs into one OUT: the second, whose point-only poses all failed and whose point+line poses lie beyond
    5 cm, leaves none of the first run's overlays, says why it shows no improvement, and still shows its largest
    point+line errors."""
    import json

    out, root = fake_run["out"], fake_run["root"]
    rep = out / "7scenes" / "report"
    rp.write_report(out, "7scenes", root=root)
    assert (rep / "query_chess_improved1.png").exists()
    chess = out / "7scenes" / "chess"
    res = json.loads((chess / "results.json").read_text())
    journal = chess / res["journal"]
    lines = [json.loads(x) for x in journal.read_text().splitlines()]
    for rec in lines:
        rec["point"] = {"success": False, "reason": "2 matches < 4"}
    journal.write_text("".join(json.dumps(r) + "\n" for r in lines))
    for q in res["queries"].values():
        q["point"] = {"t_cm": None, "R_deg": None, "success": False}
        q["point+line"]["t_cm"] += 10.0
    (chess / "results.json").write_text(json.dumps(res))
    text = rp.write_report(out, "7scenes", root=root).read_text()
    assert not (rep / "query_chess_improved1.png").exists() and "improved1" not in text
    assert "chess: every point-only pose failed (2 of 2 queries) and lines brought none within 5 cm" in text
    assert {p.name for p in rep.glob("query_chess_*.png")} == {"query_chess_worst1.png", "query_chess_worst2.png"}
    assert f"| largest point+line error #1 | `{Q1}` | failed | 14.0 cm / 0.10° |" in text
