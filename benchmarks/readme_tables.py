"""Regenerate the tables of the README and of ``docs/*.md`` from ``benchmarks/results/*.json`` (the figures' one source).

    python benchmarks/readme_tables.py           # rewrite README.md and docs/*.md in place
    python benchmarks/readme_tables.py --check   # exit 1 if one of them is out of date (the tests run this)

A generated block in one of those files is

    <!-- results: NAME1 NAME2 ... -->
    ...table rows of NAME1, then NAME2 (same header), then one provenance line per file...

(a ``localization_variants.py`` result's rows get a first column naming its run: scene, ground truth, map, matches)
    <!-- /results -->

where each NAME is a file ``benchmarks/results/NAME.json`` written by a benchmark script, holding
``table: {header, rows}`` and ``provenance: {command, commit, date, machine}``.
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import results  # noqa: E402

README = results.REPO / "README.md"
DOCS = results.REPO / "docs"
BLOCK = re.compile(r"(<!-- results: ([^>]*?) -->\n)(.*?)(<!-- /results -->)", re.S)


def documents() -> list[Path]:
    """The files whose tables are generated: the README (headline tables) and docs/*.md (the measurements behind
    the defaults)."""
    return [README, *sorted(DOCS.glob("*.md"))]


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _machine(m: dict) -> str:
    gpu = f", {m['gpu']}" if m.get("gpu") else ""
    env = "".join(f", {k}={v}" for k, v in m.get("env", {}).items())
    return f"{m.get('cpu', '?')}, {m.get('cores', '?')} cores{gpu}{env}"


def _parse_markdown(table: str) -> tuple[list, list]:
    """(header, rows) of a markdown table as a benchmark printed it."""
    lines = [ln.strip() for ln in table.strip().splitlines() if ln.strip().startswith("|")]
    cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
    return cells[0], [c for c in cells[1:] if not all(set(x) <= set("-: ") for x in c)]


def render_block(names: list[str]) -> str:
    """The markdown of one generated block: the tables of ``names`` under one header, then provenance."""
    header, rows, notes = None, [], []
    for name in names:
        r = results.read(name)
        t, p = r["table"], r["provenance"]
        head, body = _parse_markdown(t) if isinstance(t, str) else (t["header"], t["rows"])
        if name.startswith("localization-variants-"):  # a block may pool several runs: name each on its first row
            run = results.variants_run(r)
            head, body = ["run", *head], [[run if i == 0 else "", *row] for i, row in enumerate(body)]
        if header is None:
            header = head
        elif head != header:
            raise ValueError(f"{name}: its table header {head} differs from {header}")
        rows += body
        dirty = " (uncommitted changes)" if p.get("dirty") else ""
        notes.append(f"`{name}`: {p['date']}, commit {p['commit']}{dirty}, {_machine(p['machine'])}: `{p['command']}`")
    lines = [_row(header), _row(["---"] * len(header)), *(_row(r) for r in rows), ""]
    lines += ["<sub>" + "<br>".join(notes) + "</sub>", ""]
    return "\n".join(lines)


def render(text: str) -> str:
    return BLOCK.sub(lambda m: m.group(1) + render_block(m.group(2).split()) + m.group(4), text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="only check that the files are up to date")
    args = ap.parse_args(argv)
    stale = []
    for path in documents():
        text = path.read_text()
        new = render(text)
        if new == text:
            continue
        stale.append(path)
        if not args.check:
            path.write_text(new)
            print(f"{path}: {len(BLOCK.findall(text))} generated blocks")
    if args.check and stale:
        names = ", ".join(str(p.relative_to(results.REPO)) for p in stale)
        print(f"tables differ from benchmarks/results/ in {names}: run python benchmarks/readme_tables.py")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
