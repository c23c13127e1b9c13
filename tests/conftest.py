"""Shared fixtures: real 7-Scenes data from ../shared/data (skipped when absent) and a small synthetic scene."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

torch.set_num_threads(min(2, os.cpu_count() or 1))

REPO = Path(__file__).resolve().parents[1]


def benchmark_module(relpath: str):
    """A benchmark script (``relpath`` under ``benchmarks/``) imported as a module; ``benchmarks/`` goes on the path
    first, so that the scripts' own ``import results`` works."""
    import importlib.util
    import sys

    if str(REPO / "benchmarks") not in sys.path:
        sys.path.insert(0, str(REPO / "benchmarks"))
    path = REPO / "benchmarks" / relpath
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real 7-Scenes test data not found at {SHARED_DATA} (../shared/data beside the repository)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def redkitchen_root(shared_data) -> Path:
    root = shared_data / "7scenes-redkitchen-mini"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    return root


@pytest.fixture(scope="session")
def stairs_root(shared_data) -> Path:
    root = shared_data / "7scenes-stairs-fixture"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    return root


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    """Dataset root holding the small synthetic scene room-s3 (generated once per test session)."""
    from lipmap.datasets.synthetic import generate_scene

    root = tmp_path_factory.mktemp("synthetic")
    generate_scene(root, seed=3, preset="small")
    return root
