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
