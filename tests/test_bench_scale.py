"""benchmarks/perf/bench_scale.py: its tables and where a tagged (partial) rerun writes."""
import json

from conftest import benchmark_module

bs = benchmark_module("perf/bench_scale.py")


def _map_rows(views, seconds, kf, planes=None):
    rows = [{"views": views, "queries": 0, "stage": "plane_optimization", "seconds": seconds * 0.8, "peak_rss_mb": 900.0},
            {"views": views, "queries": 0, "stage": "mapping_total", "seconds": seconds, "peak_rss_mb": 1000.0,
             "n_keyframes": kf, "n_lines": 100, "f@5cm": 0.5}]
    if planes:
        rows[-1].update(planes)
    return rows


def test_tables_show_the_plane_rounds_only_when_the_rows_have_them():
    old = _map_rows(100, 500.0, 100)
    table, _ = bs._tables(old, {})
    assert table["header"][-1] == "F@5cm" and all(len(r) == 8 for r in table["rows"])
    new = _map_rows(1500, 900.0, 492, {"n_planes": 2100, "max_planes": 2900, "prune_split_rounds": 72, "splits": 8400})
    table, _ = bs._tables(old + new, {})
    assert table["header"][-3:] == ["planes (most during the run)", "prune/split rounds", "splits"]
    assert table["rows"][-1][-3:] == ["2100 (2900)", 72, 8400]
    assert table["rows"][1][-3:] == ["", "", ""]  # a row measured before the columns existed


def test_a_tagged_rerun_writes_its_own_file_and_no_estimate(tmp_path, monkeypatch):
    monkeypatch.setattr(bs.results, "RESULTS", tmp_path)
    made = {100: _map_rows(100, 500.0, 100), 1500: _map_rows(1500, 900.0, 492)}
    monkeypatch.setattr(bs, "_run_worker", lambda args, kind, n: made[n] if kind == "map" else [])
    bs.main(["--root", str(tmp_path), "--work", str(tmp_path / "w"), "--views", "100", "1500", "--queries",
             "--tag", "rounds"])
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == ["perf-scale-rounds.json", "perf-scale-rounds.jsonl"]
    data = json.loads((tmp_path / "perf-scale-rounds.json").read_text())
    assert data["summary"]["mapping"]["time_ratio"] == 1.8
    assert len((tmp_path / "perf-scale-rounds.jsonl").read_text().splitlines()) == 4


def test_the_estimate_takes_a_tagged_reruns_rows_over_the_full_runs(tmp_path):
    full = _map_rows(100, 500.0, 100) + _map_rows(400, 480.0, 354) + [
        {"views": 100, "queries": 100, "stage": "point_map", "seconds": 50.0, "peak_rss_mb": 900.0},
        {"views": 100, "queries": 100, "stage": "per_query", "seconds": 1.2, "peak_rss_mb": 900.0}]
    rerun = _map_rows(100, 660.0, 100) + _map_rows(400, 900.0, 354)
    for name, rows in (("a.jsonl", full), ("b.jsonl", rerun)):
        (tmp_path / name).write_text("".join(json.dumps(r) + "\n" for r in rows))
    rows = bs.measured_rows([tmp_path / "a.jsonl", tmp_path / "b.jsonl"])
    assert len(rows) == len(full)
    total = {r["views"]: r["seconds"] for r in rows if r["stage"] == "mapping_total"}
    assert total == {100: 660.0, 400: 900.0}
    est = bs.estimate(rows, 0.2)
    # line map = fixed + per keyframe, fitted through the rerun's two points; the query side from the full run
    assert abs(est["line_map_per_keyframe_s"] - (900.0 - 660.0) / 254) < 1e-3 and est["per_query_s"] == 1.2
