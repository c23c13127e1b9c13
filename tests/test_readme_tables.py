"""The README's tables are generated from benchmarks/results/ (one source per figure): they must agree, and
every results file must say how it was made."""
import json
import re
from pathlib import Path

from conftest import REPO, benchmark_module


def _readme_tables():
    return benchmark_module("readme_tables.py")


def test_readme_tables_are_generated_from_the_results():
    mod = _readme_tables()
    docs = mod.documents()
    assert docs[0] == REPO / "README.md" and {"design.md", "localization.md", "performance.md", "results.md", "usage.md"} <= {d.name for d in docs}
    assert mod.BLOCK.findall(docs[0].read_text()), "the README has no generated table"
    for path in docs:
        text = path.read_text()
        assert mod.render(text) == text, f"{path.name} is out of date: run python benchmarks/readme_tables.py"


def test_every_result_file_has_a_place_in_the_documents():
    """A results file no document shows or names is a figure without a reader (benchmarks/results is the figures'
    one home, shown in the README or docs/); the runs a shown CDF plot reads count through it."""
    mod = _readme_tables()
    texts = [d.read_text() for d in mod.documents()]
    shown = {n for text in texts for names in mod.BLOCK.findall(text) for n in names[1].split()}
    for name in [n for n in shown if n.startswith("localization-cdf-")]:
        for curve in json.loads((REPO / "benchmarks" / "results" / f"{name}.json").read_text())["curves"]:
            shown |= {Path(part.split(":")[0]).stem for part in curve.split("=", 1)[1].split("+")}
    orphans = sorted(f.stem for f in (REPO / "benchmarks" / "results").glob("*.json")
                     if f.stem not in shown and not any(f.stem in text for text in texts))
    assert not orphans, f"results no document shows: {orphans}"


def test_document_links_resolve():
    """The README sends readers to docs/ for the measurements behind each default: every relative link must exist,
    and a link to a section (``file.md#anchor``) must name one of that file's headings (GitHub's anchors)."""
    def anchors(path):
        heads = [line.lstrip("#").strip() for line in path.read_text().splitlines() if line.startswith("#")]
        return {re.sub(r"[^a-z0-9 \-]", "", h.lower()).replace(" ", "-") for h in heads}

    mod = _readme_tables()
    n_sections = 0
    for path in mod.documents():
        for target, anchor in re.findall(r"\]\(([^)#\s]*)(?:#([^)\s]+))?\)", path.read_text()):
            if "://" in target:
                continue
            dest = path.parent / target if target else path
            assert dest.exists(), f"{path.name} links to {target}, which does not exist"
            if anchor and dest.suffix == ".md":
                n_sections += 1
                assert anchor in anchors(dest), f"{path.name} links to {target}#{anchor}: no such heading"
    assert n_sections, "no section links checked"


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


def test_readme_tables_come_from_clean_commits():
    """A figure made on a tree with uncommitted changes reproduces from no commit: the README shows none."""
    mod = _readme_tables()
    names = [n for block in mod.BLOCK.findall(mod.README.read_text()) for n in block[1].split()]
    assert names
    dirty = [n for n in names if json.loads((REPO / "benchmarks" / "results" / f"{n}.json").read_text())["provenance"].get("dirty")]
    assert not dirty, f"README tables made on a dirty tree: {dirty}"


def test_results_refuse_a_dirty_tree_unless_told(tmp_path, monkeypatch):
    import pytest

    mod = _readme_tables()
    res = mod.results
    monkeypatch.setattr(res, "dirty", lambda: True)
    monkeypatch.delenv(res.ALLOW_DIRTY_ENV, raising=False)
    monkeypatch.setattr(res, "RESULTS", res._DEFAULT_RESULTS)
    with pytest.raises(SystemExit, match="uncommitted changes"):
        res.write("never-written", {"table": {"header": [], "rows": []}})
    assert not (res._DEFAULT_RESULTS / "never-written.json").exists()
    monkeypatch.setattr(res, "RESULTS", tmp_path)  # a results folder of one's own (the tests') takes anything
    monkeypatch.setenv(res.ALLOW_DIRTY_ENV, "1")
    path = res.write("dirty-ok", {"table": {"header": [], "rows": []}})
    assert json.loads(path.read_text())["provenance"]["dirty"] is True


def test_results_refuse_code_imported_from_another_checkout(tmp_path, monkeypatch):
    import sys
    import types

    import pytest

    res = _readme_tables().results
    monkeypatch.setattr(res, "dirty", lambda: False)
    monkeypatch.setattr(res, "RESULTS", res._DEFAULT_RESULTS)
    assert res.foreign_packages() == []  # the tests import this checkout's packages
    other = types.ModuleType("lipmap")
    other.__file__ = str(tmp_path / "other-checkout" / "lipmap" / "__init__.py")
    monkeypatch.setitem(sys.modules, "lipmap", other)
    with pytest.raises(SystemExit, match="not this checkout"):
        res.write("never-written", {"table": {"header": [], "rows": []}})
    assert not (res._DEFAULT_RESULTS / "never-written.json").exists()
