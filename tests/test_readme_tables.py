"""The README's tables are generated from benchmarks/results/ (one source per figure): they must agree, and
every results file must say how it was made."""
import json

from conftest import REPO, benchmark_module


def _readme_tables():
    return benchmark_module("readme_tables.py")


def test_readme_tables_are_generated_from_the_results():
    mod = _readme_tables()
    text = (REPO / "README.md").read_text()
    blocks = mod.BLOCK.findall(text)
    assert blocks, "the README has no generated table"
    assert mod.render(text) == text, "README.md is out of date: run python benchmarks/readme_tables.py"


def test_every_result_records_command_commit_machine_and_date():
    files = sorted((REPO / "benchmarks" / "results").glob("*.json"))
    assert files
    for f in files:
        p = json.loads(f.read_text())["provenance"]
        assert p["command"].startswith("python benchmarks/") and p["commit"] and p["date"], f.name
        assert p["machine"]["cores"] >= 1 and p["machine"]["cpu"], f.name


def test_a_block_renders_its_rows_and_provenance(tmp_path, monkeypatch):
    mod = _readme_tables()
    res = {"provenance": {"command": "python benchmarks/x.py", "commit": "abc1234", "dirty": False, "date": "2026-12-01 10:00 UTC",
                          "machine": {"cpu": "CPU", "cores": 2}},
           "table": {"header": ["a", "b"], "rows": [[1, 2], ["", 3]]}}
    (tmp_path / "t.json").write_text(json.dumps(res))
    monkeypatch.setattr(mod.results, "RESULTS", tmp_path)
    out = mod.render("x\n<!-- results: t -->\nold\n<!-- /results -->\ny\n")
    assert out.startswith("x\n<!-- results: t -->\n| a | b |\n| --- | --- |\n| 1 | 2 |\n|  | 3 |\n")
    assert "commit abc1234" in out and "`python benchmarks/x.py`" in out and out.endswith("<!-- /results -->\ny\n")


def test_the_thread_environment_is_recorded_and_shown(monkeypatch):
    """OMP_WAIT_POLICY=PASSIVE halves the plane optimization's speed alone: a timing says which it ran under."""
    mod = _readme_tables()
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    m = mod.results.machine()
    assert m["env"] == {"OMP_WAIT_POLICY": "PASSIVE"} and m["torch_threads"] >= 1
    assert mod._machine(m).endswith("cores, OMP_WAIT_POLICY=PASSIVE")
    monkeypatch.delenv("OMP_WAIT_POLICY")
    assert "env" not in mod.results.machine() and mod._machine(mod.results.machine()).endswith(" cores")


def test_localization_variants_rows_name_their_run(tmp_path, monkeypatch):
    """A block may pool several variant runs (scenes, budgets): each run's first row names it."""
    mod = _readme_tables()
    prov = {"commit": "abc1234", "dirty": False, "date": "2026-12-01 10:00 UTC", "machine": {"cpu": "CPU", "cores": 2}}
    table = {"header": ["variant", "x"], "rows": [["default", 1], ["other", 2]]}
    runs = {
        "localization-variants-a": {"scene": "redkitchen-heldout", "method": "lipmap", "matches": "5", "match_seeds": [0, 1, 2],
                                    "command": "python benchmarks/localization_variants.py --scene redkitchen-heldout --pose-source sfm --matches 5"},
        "localization-variants-b": {"scene": "redkitchen", "method": "lift", "matches": "0", "match_seeds": [0],
                                    "command": "python benchmarks/localization_variants.py --scene redkitchen --matches 0"},
    }
    for name, r in runs.items():
        data = {"provenance": {**prov, "command": r.pop("command")}, **r, "table": table}
        (tmp_path / f"{name}.json").write_text(json.dumps(data))
    monkeypatch.setattr(mod.results, "RESULTS", tmp_path)
    out = mod.render("<!-- results: localization-variants-a localization-variants-b -->\n<!-- /results -->\n")
    assert ("| run | variant | x |\n| --- | --- | --- |\n"
            "| redkitchen-heldout (sfm), lipmap, 5 matches, 3 draws | default | 1 |\n|  | other | 2 |\n"
            "| redkitchen (posetxt), lift, all matches | default | 1 |\n|  | other | 2 |\n") in out
