"""Every notebook in notebooks/ runs headless, top to bottom, in a fresh working directory.

The kernel must be the interpreter running the tests (the project's venv): a kernelspec named
``python3`` pointing at ``sys.executable`` is put first on JUPYTER_PATH, so a ``python3`` kernelspec
in the user's or the system's Jupyter folders cannot send the notebooks to another Python. The
notebooks hold their own checks (``assert``), so a regression shows up as a failed cell.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat", reason="notebook tests need the [test] extra (nbformat, nbclient, ipykernel)")
nbclient = pytest.importorskip("nbclient", reason="notebook tests need the [test] extra (nbformat, nbclient, ipykernel)")
pytest.importorskip("ipykernel", reason="notebook tests need the [test] extra (nbformat, nbclient, ipykernel)")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
# Over 60 s on two CPU cores: both fit LiP-Map planes (~1-3 min depending on the machine's load).
SLOW = {"quickstart.ipynb", "mapping_metrics.ipynb"}
PROBE = "import sys; print(sys.prefix)"  # the venv's prefix, unlike its python symlink, is its own


@pytest.fixture(scope="module")
def jupyter_path(tmp_path_factory) -> Path:
    """A Jupyter data dir whose ``python3`` kernelspec runs this interpreter."""
    root = tmp_path_factory.mktemp("jupyter")
    spec = root / "kernels" / "python3"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (lipmap tests)",
        "language": "python",
    }))
    return root


def test_notebooks_exist_and_are_stored_without_outputs():
    assert {"quickstart.ipynb", "hloc_integration.ipynb", "mapping_metrics.ipynb"} <= {p.name for p in NOTEBOOKS}
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        assert nb.metadata.get("kernelspec", {}).get("name") == "python3", path.name
        for i, cell in enumerate(nb.cells):
            if cell.cell_type == "code":
                assert cell.outputs == [] and cell.execution_count is None, \
                    f"{path.name} cell {i} has outputs: clear them before committing"


@pytest.mark.parametrize("path", [pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.name in SLOW else [])
                                  for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, jupyter_path, monkeypatch):
    monkeypatch.setenv("JUPYTER_PATH", str(jupyter_path))
    monkeypatch.delenv("MPLBACKEND", raising=False)  # the kernel's inline backend shows the figures
    nb = nbformat.read(path, as_version=4)
    nb.cells.insert(0, nbformat.v4.new_code_cell(PROBE))
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    t0 = time.time()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as e:
        nbformat.write(nb, tmp_path / path.name)  # executed copy, outputs included, for a post-mortem
        pytest.fail(f"{path.name}: a cell failed (executed copy: {tmp_path / path.name})\n{e}")
    seconds = time.time() - t0
    nbformat.write(nb, tmp_path / path.name)

    probe = "".join(o.get("text", "") for o in nb.cells[0].outputs).strip()
    assert Path(probe).resolve() == Path(sys.prefix).resolve(), f"the kernel ran the Python of {probe}, not {sys.prefix}"
    n_images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert n_images >= 3, f"{path.name} showed {n_images} figures"
    assert (tmp_path / "outputs").is_dir(), "notebooks write under ./outputs of their working directory"
    print(f"{path.name}: {seconds:.0f} s, {n_images} figures")
