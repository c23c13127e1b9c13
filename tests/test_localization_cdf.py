"""benchmarks/localization_cdf.py: shares within each error from localization_variants' per-query errors."""
import json

import numpy as np
import pytest

from conftest import benchmark_module

cdf = benchmark_module("localization_cdf.py")


def _variants_file(path, point, point_line, variant="default"):
    path.write_text(json.dumps({"variants": {variant: {"t_cm": {"point": point, "point+line": point_line}}}}))
    return path


def test_table_and_picture_from_two_maps(tmp_path, monkeypatch):
    monkeypatch.setattr(cdf.results, "RESULTS", tmp_path)
    inf = float("inf")
    a = _variants_file(tmp_path / "a.json", [inf, inf, 3.0, 0.5], [0.5, 1.5, 4.0, 30.0])
    b = _variants_file(tmp_path / "b.json", [inf, inf, 3.0, 0.5], [0.9, 9.0, 12.0, inf], variant="x")
    cdf.main(["--name", "cdf-t", f"A={a}", f"B={b}:x"])
    data = json.loads((tmp_path / "cdf-t.json").read_text())
    rows = data["table"]["rows"]
    assert [r[0] for r in rows] == ["point-only", "A", "B"]
    assert rows[0][2] == "failed" and rows[0][3:6] == ["25.0", "25.0", "50.0"]  # medians over inf: no pose
    assert rows[1][2] == f"{np.median([0.5, 1.5, 4.0, 30.0]):.2f}" and rows[1][3:] == ["25.0", "50.0", "75.0", "75.0", "75.0"]
    assert rows[2][2] == "10.50" and rows[2][3:] == ["25.0", "25.0", "25.0", "50.0", "75.0"]
    assert (tmp_path / "cdf-t.png").stat().st_size > 10_000 and data["picture"] == "cdf-t.png"


def test_a_file_without_per_query_errors_is_named(tmp_path):
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"variants": {"default": {"median_t_cm": {"point": 1.0}}}}))
    with pytest.raises(SystemExit, match="old.json: no per-query errors for variant 'default'"):
        cdf.main(["--name", "x", f"A={old}"])
    with pytest.raises(SystemExit, match="expected LABEL=FILE"):
        cdf.main(["--name", "x", str(old)])


def test_reads_what_localization_variants_writes(tmp_path, monkeypatch):
    """The contract between the two scripts: every localization's error, per variant, in draw-major order."""
    lv = benchmark_module("localization_variants.py")
    monkeypatch.setattr(lv.results, "RESULTS", tmp_path)
    monkeypatch.setattr(cdf.results, "RESULTS", tmp_path)
    monkeypatch.setattr(lv, "load_scene", lambda *a, **k: object())
    monkeypatch.setattr(lv, "eval_inputs", lambda *a, **k: (None, None, None, None))
    errors = {"point": np.array([np.inf, 2.0, 0.5]), "point+line": np.array([40.0, 1.5, 0.4])}
    monkeypatch.setattr(lv, "run_variant", lambda *a, **k: {"t_cm": errors, "R_deg": errors, "rescued": [True] * 3,
                                                            "line_ms": 9.0, "line_matches": 30,
                                                            "line_matches_correct": 24})
    lv.main(["--dataset", "synthetic", "--root", str(tmp_path), "--scene", "s", "--out", str(tmp_path), "--matches", "5",
             "--tag", "t", "default={}"])
    written = tmp_path / "localization-variants-synthetic-s-lipmap-posetxt-5-t.json"
    assert json.loads(written.read_text())["variants"]["default"]["t_cm"]["point+line"] == [40.0, 1.5, 0.4]
    cdf.main(["--name", "c", f"LiP-Map={written.name}"])  # a bare name is looked up in the results folder
    rows = json.loads((tmp_path / "c.json").read_text())["table"]["rows"]
    assert rows[1][:3] == ["LiP-Map", 3, "1.50"] and rows[0][2] == "2.00"


def test_a_curve_pools_several_files(tmp_path, monkeypatch):
    monkeypatch.setattr(cdf.results, "RESULTS", tmp_path)
    a = _variants_file(tmp_path / "a.json", [1.0, 3.0], [0.5, 2.5])
    b = _variants_file(tmp_path / "b.json", [9.0, 9.0], [30.0, 40.0], variant="s")
    cdf.main(["--name", "p", f"both={a}+{b}:s"])
    rows = json.loads((tmp_path / "p.json").read_text())["table"]["rows"]
    assert rows[0][1] == 4 and rows[0][2] == "6.00"  # point-only pooled: 1, 3, 9, 9
    assert rows[1][:3] == ["both", 4, "16.25"] and rows[1][3:6] == ["25.0", "25.0", "50.0"]
