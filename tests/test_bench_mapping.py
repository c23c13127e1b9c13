"""benchmarks/perf/bench_mapping.py: fresh-process mapping runs timed per thread environment."""
import json

import pytest

from conftest import benchmark_module

bm = benchmark_module("perf/bench_mapping.py")


def test_env_specs():
    assert bm.parse_env("default") == {}
    assert bm.parse_env("OMP_WAIT_POLICY=PASSIVE,OMP_NUM_THREADS=1") == {"OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    with pytest.raises(SystemExit, match="expected 'default' or KEY=VALUE"):
        bm.parse_env("PASSIVE")


def test_runs_each_environment_in_fresh_processes_and_writes_the_medians(synthetic_root, tmp_path, monkeypatch):
    monkeypatch.setattr(bm.results, "RESULTS", tmp_path / "results")
    (tmp_path / "results").mkdir()
    bm.main(["--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3", "--out", str(tmp_path / "w"),
             "--method", "lift", "--runs", "2", "--env", "default", "--env", "OMP_WAIT_POLICY=PASSIVE", "--tag", "t"])
    data = json.loads((tmp_path / "results" / "perf-mapping-synthetic-room-s3-t.json").read_text())
    assert list(data["runs"]) == ["default", "OMP_WAIT_POLICY=PASSIVE"]
    for runs in data["runs"].values():
        assert len(runs) == 2
        for r in runs:
            # the map's own timings, read back from the run's linemap.h5, within the process's wall time
            assert 0 < r["total_s"] <= r["wall_s"] and r["lines2d_s"] <= r["total_s"] and r["peak_rss_mb"] > 50
    rows = data["table"]["rows"]
    assert [r[2] for r in rows] == ["`default`", "`OMP_WAIT_POLICY=PASSIVE`"] and all(r[3] == 2 for r in rows)
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["run-0-0", "run-0-1", "run-1-0", "run-1-1"]


def test_a_failed_run_stops_with_the_command_and_its_error(tmp_path):
    with pytest.raises(SystemExit, match="mapping failed .*localization.cli map"):
        bm.main(["--dataset", "synthetic", "--root", str(tmp_path / "missing"), "--scene", "room-s3",
                 "--out", str(tmp_path / "w"), "--method", "lift", "--runs", "1"])
