"""`lipmap-loc eval --ray`: the same results as a local run, resume from the journal, and a clear error without Ray.

Without Ray the Ray test skips, unless ``LIPMAP_REQUIRE_RAY=1`` (set by .ci/run, whose install has the ray extra),
which makes a missing Ray a failure.
"""
import json
import os
import sys
from pathlib import Path

import pytest

from localization import cli
from localization.pipeline import run_eval

from test_pipeline import CONF, MINI  # the mini synthetic scene and the fast settings of the pipeline tests

SCENE = "room-s1"


def _without_wall_clock(obj):
    """A results.json without its wall-clock fields - ``timings`` and every ``ms`` field (``ms``,
    ``line_stage_ms``, ``median_ms_per_query``, ...) - which differ between any two runs, local ones too."""
    if isinstance(obj, dict):
        return {k: _without_wall_clock(v) for k, v in obj.items() if k != "timings" and "ms" not in k.split("_")}
    if isinstance(obj, list):
        return [_without_wall_clock(v) for v in obj]
    return obj


def _results(out: Path):
    """(dataset results.json, scene results.json), each as text without the wall-clock fields; kept as the
    dumped text so that the key order counts too."""
    return tuple(json.dumps(_without_wall_clock(json.loads(p.read_text())), indent=1)
                 for p in (out / "synthetic" / "results.json", out / "synthetic" / SCENE / "results.json"))


@pytest.fixture
def ray_local():
    """A local Ray instance with 2 CPUs (its workers inherit this process's environment, PYTHONPATH included)."""
    try:
        import ray
    except ImportError:
        why = 'Ray is not installed (pip install "lipmap[ray]")'
        if os.environ.get("LIPMAP_REQUIRE_RAY") == "1":
            pytest.fail(f"LIPMAP_REQUIRE_RAY=1 but {why}")
        pytest.skip(why)
    ray.init(num_cpus=2, include_dashboard=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow
def test_ray_eval_equals_local_eval_and_resumes_from_the_journal(tmp_path, ray_local):
    from lipmap.datasets.synthetic import generate_scene
    from localization.scaleout import RayRunner

    root = tmp_path / "data"
    generate_scene(root, seed=1, preset=MINI)
    run_eval("synthetic", root, [SCENE], tmp_path / "local", CONF)
    # chunks of 4 queries: the 6 queries come back from 2 tasks and are journaled in query order
    run_eval("synthetic", root, [SCENE], tmp_path / "ray", CONF, runner=RayRunner(chunk=4))
    local = _results(tmp_path / "local")
    assert _results(tmp_path / "ray") == local
    journal = next((tmp_path / "ray" / "synthetic" / SCENE).glob("queries-*.jsonl"))
    names = [json.loads(line)["name"] for line in journal.read_text().splitlines()]
    local_journal = tmp_path / "local" / "synthetic" / SCENE / journal.name  # the same settings: the same digest
    assert names == [json.loads(line)["name"] for line in local_journal.read_text().splitlines()] and len(names) == 6

    # a run killed after 4 queries: the Ray run asks only for the 2 left and appends them after the others
    scene_dir = tmp_path / "ray" / "synthetic" / SCENE
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:4]) + "\n")
    for p in (scene_dir / "results.json", tmp_path / "ray" / "synthetic" / "results.json"):
        p.unlink()
    asked = []
    run_eval("synthetic", root, [SCENE], tmp_path / "ray", CONF, runner=RayRunner(chunk=4),
             checkpoint=lambda event: asked.append(event) if event == "query" else None)
    assert len(asked) == 2
    assert journal.read_text().splitlines()[:4] == lines[:4]
    assert [json.loads(line)["name"] for line in journal.read_text().splitlines()] == names
    assert _results(tmp_path / "ray") == local


def test_ray_without_ray_installed_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code = cli.main(["eval", "--dataset", "synthetic", "--out", str(tmp_path / "out"), "--ray"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "--ray needs Ray" in err and 'pip install "lipmap[ray]"' in err
    assert not (tmp_path / "out").exists()  # stopped before any work


def test_ray_options_without_ray_are_refused(tmp_path, capsys):
    assert cli.main(["eval", "--dataset", "synthetic", "--out", str(tmp_path / "out"), "--ray-chunk", "10"]) == 2
    assert "go with --ray" in capsys.readouterr().err
