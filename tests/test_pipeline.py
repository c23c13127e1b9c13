"""End-to-end localization pipeline on a mini synthetic scene: schema, bad input, resume, determinism."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from lipmap import InputError
from lipmap.datasets.synthetic import SynthConfig, generate_scene
from dataclasses import replace

from localization.config import LocalizationConfig
from localization.pipeline import run_eval

MINI = SynthConfig("mini", 240, 180, 196.875, 196.875, 120.0, 90.0, n_mapping=16, n_query=6, texels_per_m=200.0)
CONF = LocalizationConfig(points="sift-n2048", map_method="lift", num_retrieved=5)


@pytest.fixture(scope="module")
def mini_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("mini")
    generate_scene(root, seed=1, preset=MINI)
    return root


def _copy(mini_root, tmp_path) -> Path:
    shutil.copytree(mini_root, tmp_path / "data")
    return tmp_path / "data"


def _numbers(results: dict) -> dict:
    """results.json without the timing fields (which differ run to run)."""
    out = {}
    for scene, s in results["scenes"].items():
        for k, v in s.items():
            out[(scene, k)] = {kk: vv for kk, vv in v.items() if "ms" not in kk}
    return out


def test_eval_end_to_end(mini_root, tmp_path):
    path = run_eval("synthetic", mini_root, ["room-s1"], tmp_path / "out", CONF)
    res = json.loads(path.read_text())
    s = res["scenes"]["room-s1"]
    for key in ("point", "point+line"):
        for field in ("median_t_cm", "median_R_deg", "acc_5cm_5deg", "n_queries", "n_failed", "median_ms_per_query"):
            assert field in s[key]
        assert s[key]["n_queries"] == 6
    assert s["point"]["n_failed"] == 0 and s["point"]["median_t_cm"] < 3.0
    scene_dir = tmp_path / "out" / "synthetic" / "room-s1"
    lines = (scene_dir / "results_point_line.txt").read_text().split("\n")
    assert len([l for l in lines if l.strip()]) == 6 and len(lines[0].split()) == 8
    summary = (tmp_path / "out" / "synthetic" / "summary.md").read_text()
    assert "room-s1" in summary
    assert "Line query: projection, map lines seen in at least 1 mapping image(s) by the track test" in summary


def test_bad_query_is_reported_and_others_kept(mini_root, tmp_path):
    root = _copy(mini_root, tmp_path)
    seq = root / "room-s1" / "seq-02"
    (seq / "frame-000001.color.png").write_bytes(b"\x89PNG truncated")
    (seq / "frame-000002.pose.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    res = json.loads((run_eval("synthetic", root, ["room-s1"], tmp_path / "out", CONF).parent / "room-s1" / "results.json").read_text())
    assert "frame-000001.color.png" in res["errors"]["seq-02/frame-000001.color.png"]
    assert "cannot be decoded" in res["errors"]["seq-02/frame-000001.color.png"]
    assert "seq-02/frame-000002.color.png" in res["skipped_invalid_gt"]
    s = res["summary"]["point"]
    assert s["n_queries"] == 5 and s["n_failed"] == 1  # the corrupt one fails, the invalid-GT one is not counted
    good = [q for n, q in res["queries"].items() if n != "seq-02/frame-000001.color.png"]
    assert all(q["point"]["t_cm"] is not None and q["point"]["t_cm"] < 5 for q in good)


def test_bad_mapping_frame_stops_or_is_skipped(mini_root, tmp_path):
    root = _copy(mini_root, tmp_path)
    bad = root / "room-s1" / "seq-01" / "frame-000003.color.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(InputError, match="frame-000003.color.png.*skip-bad-frames"):
        run_eval("synthetic", root, ["room-s1"], tmp_path / "out", CONF)
    path = run_eval("synthetic", root, ["room-s1"], tmp_path / "out2", CONF, skip_bad_frames=True)
    res = json.loads((path.parent / "room-s1" / "results.json").read_text())
    assert any("frame-000003.color.png" in m for m in res["skipped_mapping_frames"])
    assert res["summary"]["point"]["n_failed"] == 0


def _cli(args, env=None):
    return subprocess.run([sys.executable, "-m", "localization.cli", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=600)


def test_sigkill_during_localization_then_resume_gives_same_results(mini_root, tmp_path):
    args = ["eval", "--dataset", "synthetic", "--root", str(mini_root), "--scenes", "room-s1", "--method", "lift",
            "--points", "sift-n2048"]
    ref = _cli(args + ["--out", str(tmp_path / "ref")])
    assert ref.returncode == 0, ref.stderr[-2000:]
    # the run the CLI would make, killed by its checkpoint callback right after the third query was journaled
    script = ("import sys; from lipmap.testing import kill_at; from localization.pipeline import LocalizationConfig, run_eval; "
              "run_eval('synthetic', sys.argv[1], ['room-s1'], sys.argv[2], "
              "LocalizationConfig(map_method='lift', points='sift-n2048'), checkpoint=kill_at('query', 3))")
    killed = subprocess.run([sys.executable, "-c", script, str(mini_root), str(tmp_path / "run")], capture_output=True,
                            text=True, timeout=600)
    assert killed.returncode == -9, killed.stderr[-2000:]
    journal = next((tmp_path / "run" / "synthetic" / "room-s1").glob("queries-*.jsonl"))
    assert len(journal.read_text().splitlines()) == 3
    assert not (tmp_path / "run" / "synthetic" / "results.json").exists()
    again = _cli(args + ["--out", str(tmp_path / "run")])
    assert again.returncode == 0, again.stderr[-2000:]
    assert "Resuming room-s1: 3 of 6" in again.stderr
    a = json.loads((tmp_path / "ref" / "synthetic" / "results.json").read_text())
    b = json.loads((tmp_path / "run" / "synthetic" / "results.json").read_text())
    assert _numbers(a) == _numbers(b)


def test_truncated_journal_line_is_redone(mini_root, tmp_path):
    out = tmp_path / "out"
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)
    journal = next((out / "synthetic" / "room-s1").glob("queries-*.jsonl"))
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])  # a write cut by a kill
    a = json.loads((out / "synthetic" / "results.json").read_text())
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)
    b = json.loads((out / "synthetic" / "results.json").read_text())
    assert _numbers(a) == _numbers(b)


def test_same_seed_same_numbers(mini_root, tmp_path):
    a = json.loads(run_eval("synthetic", mini_root, ["room-s1"], tmp_path / "a", CONF).read_text())
    b = json.loads(run_eval("synthetic", mini_root, ["room-s1"], tmp_path / "b", CONF).read_text())
    assert _numbers(a) == _numbers(b)


def _map_used(out: Path, scene: str = "room-s1"):
    """The line map a run localized with, as its results.json names it, and those results."""
    from lipmap.linemap import LineMap

    res = json.loads((out / "synthetic" / scene / "results.json").read_text())
    return LineMap.load(out / "synthetic" / scene / res.get("map", {}).get("path", "linemap.h5")), res


def test_eval_with_another_map_method_into_the_same_out_uses_that_map(mini_root, tmp_path):
    """eval with lift, then with lipmap into one OUT: the second run must localize with (and report) a lipmap
    map built for it, not reuse the lift map; both variants stay on disk."""
    out = tmp_path / "out"
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)
    lift_map, lift_res = _map_used(out)
    run_eval("synthetic", mini_root, ["room-s1"], out, replace(CONF, map_method="lipmap", mapping="quick"))
    lm, res = _map_used(out)
    assert lm.metadata["method"] == "lipmap" and lm.planes is not None
    assert res["config"]["map_method"] == "lipmap" and res["map"]["method"] == "lipmap"
    assert res["n_map_lines"] == len(lm) and res["map"]["path"] != lift_res["map"]["path"]
    assert len(list((out / "synthetic" / "room-s1").glob("map-*/linemap.h5"))) == 2
    assert len(list((out / "synthetic" / "room-s1").glob("queries-*.jsonl"))) == 2
    # the lift run again: its map and journal are reused, its numbers unchanged
    again = json.loads(run_eval("synthetic", mini_root, ["room-s1"], out, CONF).read_text())
    assert _map_used(out)[1]["map"] == lift_res["map"] and len(_map_used(out)[0]) == len(lift_map)
    assert _numbers(again) == _numbers(json.loads(json.dumps({"scenes": {"room-s1": lift_res["summary"]}})))


def test_map_into_a_folder_made_with_other_settings_stops_naming_both(mini_root, tmp_path):
    from lipmap.artifacts import StaleArtifactError
    from lipmap.datasets import load_scene
    from lipmap.mapping.pipeline import map_scene

    scene = load_scene("synthetic", mini_root, "room-s1")
    path = map_scene(scene, tmp_path / "m", "quick", "lift")
    mtime = path.stat().st_mtime_ns
    assert map_scene(scene, tmp_path / "m", "quick", "lift") == path and path.stat().st_mtime_ns == mtime  # reused
    with pytest.raises(StaleArtifactError, match=r"linemap\.h5: was made by linemap with other settings .*"
                                                 r"method: 'lift' -> 'lipmap'.*--overwrite"):
        map_scene(scene, tmp_path / "m", "quick", "lipmap")
    with pytest.raises(StaleArtifactError, match=r"lift\.merge_max_angle: 0\.03 -> 0\.01"):
        map_scene(scene, tmp_path / "m", {"preset": "quick", "lift": "lift-merge"}, "lift")
    assert path.stat().st_mtime_ns == mtime  # nothing was touched


def test_a_map_made_by_other_mapping_code_is_not_reused(mini_root, tmp_path, monkeypatch):
    """The map's stamp holds the digest of the code that makes maps: after a change there the map is made again,
    and a folder holding the old one stops with the difference named; a change elsewhere keeps it."""
    import lipmap.artifacts as art
    from lipmap.artifacts import StaleArtifactError
    from lipmap.datasets import load_scene
    from lipmap.mapping.pipeline import map_scene, mapping_stamp

    scene = load_scene("synthetic", mini_root, "room-s1")
    path = map_scene(scene, tmp_path / "m", "quick", "lift")
    before = mapping_stamp(scene, "quick", "lift")
    monkeypatch.setattr(art, "MAPPING_CODE", art.MAPPING_CODE[:-1])  # as if presets.py were not mapping code
    assert mapping_stamp(scene, "quick", "lift").digest != before.digest
    with pytest.raises(StaleArtifactError, match=r"code: '[0-9a-f]+' -> '[0-9a-f]+'"):
        map_scene(scene, tmp_path / "m", "quick", "lift")
    monkeypatch.undo()
    assert map_scene(scene, tmp_path / "m", "quick", "lift") == path  # the same code: reused


def test_a_journal_is_not_resumed_by_other_code(mini_root, tmp_path, monkeypatch):
    """The journal resumes the same code's run; after a code change the queries are localized again (their
    poses and timings would otherwise be the old code's)."""
    import localization.pipeline as lp

    out = tmp_path / "out"
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)
    first = set((out / "synthetic" / "room-s1").glob("queries-*.jsonl"))
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)  # same code: the same journal, nothing redone
    assert set((out / "synthetic" / "room-s1").glob("queries-*.jsonl")) == first
    monkeypatch.setattr(lp, "code_digest", lambda: "other-code")
    run_eval("synthetic", mini_root, ["room-s1"], out, CONF)
    journals = set((out / "synthetic" / "room-s1").glob("queries-*.jsonl"))
    assert len(journals) == 2 and len((journals - first).pop().read_text().splitlines()) == 6


def test_maps_that_differ_after_the_planes_share_them(mini_root, tmp_path, monkeypatch):
    """With ``planes_root``, planes.h5 lives in a folder keyed by its own stamp: a map with other extraction settings,
    or made after a change to code the planes do not depend on, is remade from the same planes (not re-optimized);
    other plane settings, or a change to plane code, give planes of their own."""
    import lipmap.artifacts as art
    from lipmap.datasets import load_scene
    from lipmap.mapping.pipeline import map_scene

    scene = load_scene("synthetic", mini_root, "room-s1")
    a = map_scene(scene, tmp_path / "a", "quick", "lipmap", planes_root=tmp_path)
    planes = sorted(tmp_path.glob("planes-quick-*/planes.h5"))
    assert len(planes) == 1 and not (tmp_path / "a" / "planes.h5").exists()
    made = planes[0].stat().st_mtime_ns

    def lines(path):
        from lipmap.linemap import LineMap

        lm = LineMap.load(path)
        assert (path.parent / lm.metadata["planes_file"]).resolve() == planes[0].resolve()
        return len(lm)

    wide = map_scene(scene, tmp_path / "b", {"preset": "quick", "extract": {"max_dist": 6.0, "max_angle": 0.06}}, "lipmap",
                     planes_root=tmp_path)
    monkeypatch.setattr(art, "MAPPING_CODE", art.MAPPING_CODE + ("viz.py",))  # as if viz.py now made maps
    again = map_scene(scene, tmp_path / "c", "quick", "lipmap", planes_root=tmp_path)
    assert sorted(tmp_path.glob("planes-quick-*/planes.h5")) == planes and planes[0].stat().st_mtime_ns == made
    assert lines(again) == lines(a) and lines(wide) >= lines(a)  # a wider gate keeps at least the same edges
    # the wide gate's extraction votes lie up to 6 px / 0.06 rad off; the finished tracks keep only what passes the
    # paper's track test against the finished lines, so testing them again removes nothing
    from lipmap.linemap import LineMap
    from lipmap.mapping.extract import ExtractConfig, verify_tracks

    lm = LineMap.load(wide)
    assert lm.metadata["n_unverified_observations"] > 0
    assert verify_tracks(lm, scene.mapping, ExtractConfig()).supports.tolist() == lm.supports.tolist()

    monkeypatch.setattr(art, "PLANES_CODE", art.PLANES_CODE + ("viz.py",))  # as if the planes now depended on it
    map_scene(scene, tmp_path / "d", "quick", "lipmap", planes_root=tmp_path)
    map_scene(scene, tmp_path / "e", {"preset": "quick", "line_weight": 1.0}, "lipmap", planes_root=tmp_path)
    assert len(list(tmp_path.glob("planes-quick-*/planes.h5"))) == 3
