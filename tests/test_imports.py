"""The package's import graph: a DAG (no module imports, directly or through others, one that imports it),
production code never imports the test helpers, and hloc_io depends on nothing of localization.

Every import counts, also those inside functions: a lazy import hides a cycle from Python's loader but not
from a reader. Imports under ``if TYPE_CHECKING:`` are annotations only and do not count.
"""
import ast
import functools
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("lipmap", "localization")


def _modules() -> dict:
    """{dotted name: (file, is_package)} of every module of the packages."""
    mods = {}
    for pkg in PACKAGES:
        for f in (REPO / pkg).rglob("*.py"):
            parts = list(f.relative_to(REPO).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            mods[".".join(parts[:-1] if is_pkg else parts)] = (f, is_pkg)
    return mods


def _type_checking_lines(tree) -> set:
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                lines.update(range(sub.lineno, sub.end_lineno + 1))
    return lines


@functools.lru_cache(maxsize=1)
def import_graph() -> dict:
    """{module: set of package modules it imports}."""
    mods = _modules()

    def owner(name):  # the module a dotted name lives in (``lipmap.geometry.project_points`` -> ``lipmap.geometry``)
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for m, (f, is_pkg) in mods.items():
        tree = ast.parse(f.read_text())
        skip = _type_checking_lines(tree)
        pkg = m if is_pkg else m.rpartition(".")[0]
        deps = set()
        for node in ast.walk(tree):
            if getattr(node, "lineno", None) in skip:
                continue
            if isinstance(node, ast.Import):
                deps.update(owner(a.name) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(parts + ([node.module] if node.module else []))
                deps.update(owner(f"{base}.{a.name}") for a in node.names)
        graph[m] = {d for d in deps if d and d != m}
    return graph


def cycles(graph: dict) -> list:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_checker_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_graph_sees_lazy_and_relative_imports():
    g = import_graph()
    assert "lipmap.geometry" in g["lipmap.datasets.registration"]  # relative, module level
    assert "lipmap.lift" in g["lipmap.mapping.pipeline"]  # inside a function


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_production_code_does_not_import_the_test_helpers():
    assert [m for m, deps in import_graph().items() if "lipmap.testing" in deps and m != "lipmap.testing"] == []


def test_hloc_io_depends_on_nothing_of_localization():
    assert not {d for d in import_graph()["localization.hloc_io"] if d.startswith("localization")}


def test_the_per_query_api_uses_public_names_only():
    """localization.api is what users copy from: it imports no ``_private`` name of the package."""
    tree = ast.parse((REPO / "localization" / "api.py").read_text())
    private = [f"{n.module}.{a.name}" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
               for a in n.names if a.name.startswith("_")]
    assert not private, private


def test_every_localization_module_is_one_readable_file():
    """No module of localization/ over 700 lines: the per-query core, the scene loop and the point sources apart."""
    long = {f.relative_to(REPO).as_posix(): n for f in (REPO / "localization").rglob("*.py")
            if (n := len(f.read_text().splitlines())) > 700}
    assert not long, long
