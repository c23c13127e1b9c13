import json
import subprocess
import sys

import pytest

from localization.cli import main


def test_info_json_redkitchen(redkitchen_root, capsys):
    assert main(["info", "--dataset", "7scenes", "--root", str(redkitchen_root), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rk = out["scenes"]["redkitchen"]
    assert (rk["n_mapping"], rk["n_query"]) == (50, 50)
    assert rk["intrinsics"] == [525.0, 525.0, 320.0, 240.0] and rk["pose_source"] == "posetxt"
    assert out["scenes"]["redkitchen-sparse"]["n_query"] == 25


def test_info_bad_root_is_one_line_error(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "localization.cli", "info", "--dataset", "7scenes", "--root", str(tmp_path), "--scenes", "chess"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "scene 'chess' not found" in r.stderr


def test_map_lift_then_map_eval(synthetic_root, tmp_path, capsys):
    """`lipmap-loc map` writes the artifacts and prints the time; map-eval scores them against the mesh."""
    scene = ["--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3"]
    assert main(["map", *scene, "--out", str(tmp_path / "m"), "--method", "lift"]) == 0
    out = capsys.readouterr().out
    assert "lines ->" in out and "mapping time:" in out and "supports (detections passing the track test): median" in out
    assert "lines no image verifies" in out
    assert "keyframes: 30 of 30 mapping views" in out  # the small room's views are 13-30 cm apart
    assert {"linemap.h5", "linemap.ply", "lines2d.h5", "linemap.html"} <= {p.name for p in (tmp_path / "m").iterdir()}
    assert out.splitlines()[-1] == f"3D view: {tmp_path / 'm' / 'linemap.html'}"
    assert "lifted lines (" in (tmp_path / "m" / "linemap.html").read_text()  # the lift map's one kind
    # the same folder asked for another method: stopped with both settings named, exit 2, nothing touched
    assert main(["map", *scene, "--out", str(tmp_path / "m"), "--method", "lipmap", "--preset", "quick"]) == 2
    err = capsys.readouterr().err
    assert "linemap.h5: was made by linemap with other settings" in err and "method: 'lift' -> 'lipmap'" in err
    assert main(["map-eval", "--linemap", str(tmp_path / "m" / "linemap.h5"), *scene,
                 "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["n_lines"] > 100 and m["M1"]["line"]["prec@0.05"] > 0.9  # exact synthetic depth
    # each line is a lifted detection of one of these views (0.40 of the visible length shown on this room)
    assert "shown by the mapping images:" in capsys.readouterr().out and 0.2 < m["image_support"] <= 1.0


def test_map_prints_the_plane_statistics(tmp_path, capsys):
    from lipmap.datasets.synthetic import SynthConfig, generate_scene

    tiny = SynthConfig("tiny", 160, 120, 131.25, 131.25, 80.0, 60.0, n_mapping=8, n_query=2, texels_per_m=150.0)
    generate_scene(tmp_path / "d", seed=2, preset=tiny)
    scene = ["--dataset", "synthetic", "--root", str(tmp_path / "d"), "--scene", "room-s2"]
    assert main(["map", *scene, "--out", str(tmp_path / "m"), "--preset", "quick"]) == 0
    out = capsys.readouterr().out
    assert "plane edges +" in out and "area-weighted median" in out and "depth vs sensor: median" in out


def test_map_bad_plane_depth_tol(synthetic_root, tmp_path, capsys):
    assert main(["map", "--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3",
                 "--out", str(tmp_path), "--plane-depth-tol", "-0.1"]) == 2
    assert "argument --plane-depth-tol: must be a number >= 0" in capsys.readouterr().err


def test_keyframes_option_sets_the_mapping_keyframes(synthetic_root, tmp_path, capsys):
    from argparse import Namespace

    from localization.cli import _mapping_conf
    from lipmap.mapping.pipeline import get_conf

    conf = get_conf(_mapping_conf(Namespace(preset="fast", keyframes=(10.0, 2.5))))
    assert (conf.keyframes.min_translation, conf.keyframes.min_rotation_deg) == (0.1, 2.5)
    assert not get_conf(_mapping_conf(Namespace(preset="quick", keyframes=(0.0, 0.0)))).keyframes.enabled
    assert _mapping_conf(Namespace(preset="fast", keyframes=None)) == "fast"
    assert get_conf("fast").refine.enabled and get_conf("fast").refine.lines == "all"
    assert not get_conf("quick").refine.enabled and not get_conf("paper").refine.enabled
    refine = get_conf(_mapping_conf(Namespace(preset="fast", keyframes=None, refine_lines="on-plane"))).refine
    assert refine.enabled and refine.lines == "on-plane"
    assert get_conf(_mapping_conf(Namespace(preset="fast", keyframes=None, refine_lines="edges"))).refine.lines == "edges"
    from localization.cli import build_parser

    args = build_parser().parse_args(["map", "--dataset", "synthetic", "--root", "r", "--scene", "s", "--out", "o",
                                      "--refine-lines"])
    assert args.refine_lines == "all"  # the flag alone: the on-plane lines as before, and fast's edges still
    scene = ["--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3", "--out", str(tmp_path)]
    for bad in ("5", "a,b", "-1,5"):
        assert main(["map", *scene, f"--keyframes={bad}"]) == 2
        assert "--keyframes" in capsys.readouterr().err
    # 50 cm / 30 deg: a sparser map of the same room, said in the output
    assert main(["map", *scene, "--method", "lift", "--keyframes", "50,30"]) == 0
    out = capsys.readouterr().out
    n = int(out.split("keyframes: ")[1].split(" of")[0])
    assert 3 <= n < 30


def test_full_resolution_option_sets_the_plane_resolution(synthetic_root, tmp_path, capsys):
    from argparse import Namespace

    from localization.cli import _mapping_conf, build_parser
    from lipmap.mapping.pipeline import get_conf
    from lipmap.planes.config import PlaneOptConfig

    def planes(**kw):
        return PlaneOptConfig.preset(get_conf(_mapping_conf(Namespace(preset="fast", keyframes=None, **kw))).planes)

    default = planes()  # half resolution, the last 900 iterations at full
    assert default.downscale == 0 and default.target_width == 320 and default.fine_iterations == 900
    full = planes(full_resolution=-1)  # the flag alone
    assert full.downscale == 1 and full.iterations == default.iterations and full.split == default.split
    assert default.fine_downscale == 0  # half the working downscale: the camera's own on 7-Scenes
    fine = planes(full_resolution=300)  # the camera's own, whatever its size
    assert fine.fine_iterations == 300 and fine.fine_downscale == 1 and fine.downscale == 0
    assert fine.iterations == default.iterations
    coarse = planes(full_resolution=0)  # none at full resolution
    assert coarse.fine_iterations == 0 and coarse.downscale == 0
    parse = build_parser().parse_args
    base = ["map", "--dataset", "synthetic", "--root", "r", "--scene", "s", "--out", "o"]
    assert parse(base + ["--full-resolution"]).full_resolution == -1
    assert parse(base + ["--full-resolution", "900"]).full_resolution == 900
    assert parse(base).full_resolution is None
    scene = ["--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3", "--out", str(tmp_path)]
    assert main(["map", *scene, "--full-resolution", "-2"]) == 2
    assert "argument --full-resolution: must be an integer >= 0" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any work


def test_extract_gate_option_sets_the_extraction_thresholds(synthetic_root, tmp_path, capsys):
    from argparse import Namespace

    from localization.cli import _mapping_conf
    from lipmap.mapping.pipeline import get_conf

    def extract(**kw):
        return get_conf(_mapping_conf(Namespace(preset=kw.pop("preset", "fast"), keyframes=None, **kw))).extract

    default = extract()
    assert (default.max_dist, default.max_angle) == (3.0, 0.03)
    wide = extract(extract_gate=(10.0, 0.1))
    assert (wide.max_dist, wide.max_angle) == (10.0, 0.1)
    # only the gate changes: the rest of the preset's extraction (merging, tracks) stays
    assert wide.merge == default.merge and wide.track_max_dist == default.track_max_dist
    paper = extract(preset="paper", extract_gate=(2.0, 0.02))
    assert (paper.max_dist, paper.max_angle, paper.dist_reduce) == (2.0, 0.02, "mean")
    scene = ["--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3", "--out", str(tmp_path)]
    for bad, why in (("3", "takes PX,RAD"), ("x,0.1", "takes PX,RAD"), ("0,0.1", "PX > 0"), ("3,2", "RAD < pi/2")):
        assert main(["map", *scene, "--extract-gate", bad]) == 2
        assert why in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any work


def test_aggregate_option_turns_the_aggregation_on():
    from argparse import Namespace

    from localization.cli import _mapping_conf
    from lipmap.mapping.pipeline import get_conf

    def conf(**kw):
        return get_conf(_mapping_conf(Namespace(preset=kw.pop("preset", "fast"), keyframes=None, **kw)))

    assert not conf().aggregate.enabled and not conf(aggregate=False).aggregate.enabled
    on = conf(aggregate=True, extract_gate=(6.0, 0.06))
    assert on.aggregate.enabled and on.aggregate.merge and on.extract.max_dist == 6.0
    assert conf(preset="paper", aggregate=True).aggregate.enabled


def test_track_and_explain_gates_set_the_map_that_meets_every_mapping_target(capsys):
    """The map of docs/design.md that meets every mapping target of the RedKitchen mini, from the command line; gates checked as --extract-gate's."""
    from localization.cli import _mapping_conf, build_parser
    from lipmap.mapping.pipeline import get_conf

    def conf(*argv):
        args = build_parser().parse_args(["map", "--dataset", "synthetic", "--root", "R", "--scene", "S", "--out", "O",
                                          *argv])
        return get_conf(_mapping_conf(args))

    c = conf("--extract-gate", "4,0.04", "--track-gate", "4,0.05", "--explain-gate", "2,0.01", "--aggregate")
    e = c.extract
    assert (e.max_dist, e.max_angle, e.track_max_dist, e.track_max_angle) == (4.0, 0.04, 4.0, 0.05)
    assert tuple(c.explain_gate) == (2.0, 0.01) and c.aggregate.enabled
    default = conf()
    assert default.explain_gate == () and (default.extract.track_max_dist, default.extract.track_max_angle) == (2.0, 0.01)
    only_tracks = conf("--track-gate", "3,0.03").extract
    assert (only_tracks.max_dist, only_tracks.max_angle) == (default.extract.max_dist, default.extract.max_angle)
    base = ["map", "--dataset", "synthetic", "--root", "R", "--scene", "S", "--out", "O"]
    for bad in ("4", "0,0.05", "4,2"):
        for option in ("--track-gate", "--explain-gate"):
            assert main([*base, option, bad]) == 2
            assert f"argument {option}: takes PX,RAD" in capsys.readouterr().err


def test_eval_bad_line_rescue(tmp_path, capsys):
    assert main(["eval", "--dataset", "synthetic", "--out", str(tmp_path), "--line-rescue", "-1"]) == 2
    assert "argument --line-rescue: must be an integer >= 0" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any work


def test_eval_options_set_the_rescue():
    from localization.cli import build_parser, eval_config

    def conf(*opts):
        return eval_config(build_parser().parse_args(["eval", "--dataset", "synthetic", "--out", "x", *opts]))

    assert conf().line_rescue.solver == "near" and conf().line_rescue.weak_inliers == 20
    assert conf("--rescue-solver", "ransac").line_rescue.solver == "ransac"
    assert conf("--rescue-solver", "refine").line_rescue.solver == "refine"
    assert conf().line_rescue.threads == 2 and conf("--rescue-threads", "1").line_rescue.threads == 1
    assert conf("--line-rescue", "0", "--line-query", "raycast").line_rescue.weak_inliers == 0
    assert conf("--line-query", "raycast").line_query.method == "raycast"
    assert conf().line_rescue.hypotheses.upright and not conf("--no-vanishing-points").line_rescue.hypotheses.upright
    assert conf().max_line_step == (0.3, 5.0) and conf("--max-line-step", "0.15,3").max_line_step == (0.15, 3.0)
    assert conf("--max-line-step", "off").max_line_step == ()
    # the lines no mapping image verifies are left out of the query and the rescue's scoring unless --min-support 0
    assert conf().line_query.min_support == 1 and conf().line_rescue.hypotheses.min_support == 1
    every = conf("--min-support", "0", "--line-query", "raycast")
    assert every.line_query.min_support == 0 and every.line_rescue.hypotheses.min_support == 0
    assert every.line_query.method == "raycast"


def test_eval_bad_rescue_threads(tmp_path, capsys):
    assert main(["eval", "--dataset", "synthetic", "--out", str(tmp_path), "--rescue-threads", "0"]) == 2
    assert "argument --rescue-threads: must be an integer >= 1" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_eval_bad_min_support(tmp_path, capsys):
    assert main(["eval", "--dataset", "synthetic", "--out", str(tmp_path), "--min-support", "-1"]) == 2
    assert "argument --min-support: must be an integer >= 0" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_eval_bad_max_line_step(tmp_path, capsys):
    for bad in ("0.3", "0.3,x", "-1,5", "0.3,5,1"):
        assert main(["eval", "--dataset", "synthetic", "--out", str(tmp_path), f"--max-line-step={bad}"]) == 2
        assert "argument --max-line-step: takes METRES,DEGREES" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before any work


def test_every_option_has_help():
    """A user reads `lipmap-loc <command> --help`: every option says what it does."""
    import argparse

    from localization.cli import build_parser

    ap = build_parser()
    (sub,) = [a for a in ap._actions if isinstance(a, argparse._SubParsersAction)]
    missing = [f"{name} {'/'.join(a.option_strings)}" for name, p in sub.choices.items() for a in p._actions
               if a.option_strings and not isinstance(a, argparse._HelpAction) and not a.help]
    assert not missing, missing


@pytest.mark.parametrize("command, option, bad", [
    ("eval", "--seed", "-1"),
    ("eval", "--max-point-matches", "-3"),
    ("eval", "--max-point-matches", "many"),
    ("eval", "--min-support", "-1"),
    ("eval", "--line-rescue", "-2"),
    ("eval", "--max-line-step", "0,5"),
    ("eval", "--ray-cpus", "0"),
    ("eval", "--ray-chunk", "0"),
    ("eval", "--mapping-step", "0"),
    ("eval", "--full-resolution", "-5"),
    ("eval", "--keyframes", "5,-1"),
    ("eval", "--extract-gate", "3,nan"),
    ("map", "--plane-depth-tol", "inf"),
    ("map", "--mapping-step", "-1"),
    ("map-eval", "--min-support", "-1"),
    ("map-eval", "--thresholds", "0.05,-0.1"),
    ("report", "--examples", "-1"),
    ("download", "--retries", "-1"),
    ("synth", "--seed", "-4"),
    ("synth", "--workers", "0"),
])
def test_a_number_out_of_range_is_an_argparse_error_before_any_work(tmp_path, capsys, command, option, bad):
    """Exit 2 with one line naming the option, no traceback, and nothing made (a negative seed used to map the whole
    scene and then fail every query)."""
    out = tmp_path / "out"
    base = {"eval": ["--dataset", "synthetic", "--out", str(out)],
            "map": ["--dataset", "synthetic", "--root", str(tmp_path), "--scene", "s", "--out", str(out)],
            "map-eval": ["--linemap", str(out / "linemap.h5")],
            "report": [str(out)],
            "download": ["7scenes", "--root", str(out)],
            "synth": ["--out", str(out)]}[command]
    assert main([command, *base, f"{option}={bad}"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f"lipmap-loc {command}: error: argument {option}" in err and repr(bad) in err
    assert not out.exists()


def test_the_point_budget_is_all_or_a_number():
    from localization.cli import build_parser, eval_config

    def budget(*opts):
        return eval_config(build_parser().parse_args(["eval", "--dataset", "synthetic", "--out", "x", *opts])).max_point_matches

    assert budget() is None and budget("--max-point-matches", "all") is None
    assert budget("--max-point-matches", "5") == 5 and budget("--max-point-matches", "0") == 0
