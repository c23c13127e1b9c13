import json
import subprocess
import sys

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
    assert "lines ->" in out and "mapping time:" in out
    assert {"linemap.h5", "linemap.ply", "lines2d.h5"} <= {p.name for p in (tmp_path / "m").iterdir()}
    assert main(["map-eval", "--linemap", str(tmp_path / "m" / "linemap.h5"), *scene,
                 "--json", str(tmp_path / "m.json")]) == 0
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["n_lines"] > 100 and m["M1"]["line"]["prec@0.05"] > 0.9  # exact synthetic depth


def test_map_bad_plane_depth_tol(synthetic_root, tmp_path, capsys):
    assert main(["map", "--dataset", "synthetic", "--root", str(synthetic_root), "--scene", "room-s3",
                 "--out", str(tmp_path), "--plane-depth-tol", "-0.1"]) == 2
    assert "--plane-depth-tol must be >= 0" in capsys.readouterr().err
