"""The dataset side of the hloc-written fixture (tests/data/hloc_7scenes), with its images regenerated.

    python benchmarks/7scenes/make_hloc_fixture_root.py --out DATA/hloc-fixture

The fixture stores hloc's outputs and the scene's poses, not its images (they are the embedded synthetic scene's,
``generate_scene(seed=0, preset="small")``, bit for bit: tests/data/hloc_7scenes/README.md). This writes
``OUT/room-s0`` (its 10 mapping and 4 query frames with their images) and ``OUT/7scenes_densevlad_retrieval_top_10``,
so that ``lipmap-loc eval --dataset synthetic --root OUT --hloc tests/data/hloc_7scenes/hloc_outputs/7scenes`` and
``benchmarks/localization_table.py --hloc ...`` localize from the files hloc's own code wrote.
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

FIXTURE = Path(__file__).resolve().parents[2] / "tests" / "data" / "hloc_7scenes"


def make_root(out: Path) -> Path:
    from lipmap.datasets.synthetic import generate_scene

    out = Path(out)
    with tempfile.TemporaryDirectory() as tmp:
        scene_dir = generate_scene(Path(tmp), seed=0, preset="small")
        shutil.copytree(FIXTURE / "datasets" / "7scenes", out, dirs_exist_ok=True)
        for pose in out.glob("room-s0/seq-*/frame-*.pose.txt"):
            stem = pose.name[: -len(".pose.txt")]
            for kind in ("color.png", "depth.png"):
                shutil.copy(scene_dir / pose.parent.name / f"{stem}.{kind}", pose.parent / f"{stem}.{kind}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    print(make_root(ap.parse_args(argv).out))


if __name__ == "__main__":
    main()
