"""A held-out-viewpoint split of the RedKitchen mini: map every 5th frame of 0-245, query every 5th of 250-495.

    python benchmarks/7scenes/make_heldout_split.py --src ../shared/data/7scenes-redkitchen-mini --out DATA/heldout

The mini's own scenes interleave mapping and query frames (a query is ~3.5 cm from a mapping frame), so
point-only localization is already at the ground truth's floor there. Here the 50 queries follow the
50 mapping frames along the trajectory, tens of cm and tens of degrees from the nearest mapping view,
as 7-Scenes' test sequences are. Writes ``OUT/redkitchen-heldout`` in the 7-Scenes layout (frames are
symbolic links to the source; frame numbers kept) with its ``pgt/`` lists re-keyed to the new sequence
folders, so ``--pose-source sfm`` works. Evaluate under ``sfm``: pose.txt drifts by centimetres between
the two stretches (see ../shared/data/README.md).
"""
from __future__ import annotations

import argparse
from pathlib import Path

MAPPING = range(0, 250, 5)
QUERY = range(250, 500, 5)


def find_frame(src_scene: Path, frame: int) -> Path:
    """The sequence folder of the mini that holds ``frame`` (mapping frames in seq-01, queries in seq-02)."""
    for seq in ("seq-01", "seq-02"):
        if (src_scene / seq / f"frame-{frame:06d}.pose.txt").exists():
            return src_scene / seq
    raise FileNotFoundError(f"frame {frame} not found in {src_scene}")


def make_split(src_root: Path, out_root: Path, scene: str = "redkitchen") -> Path:
    src = Path(src_root) / scene
    dst = Path(out_root) / f"{scene}-heldout"
    renamed = {}
    for seq, frames in (("seq-01", MAPPING), ("seq-02", QUERY)):
        (dst / seq).mkdir(parents=True, exist_ok=True)
        for i in frames:
            old_seq = find_frame(src, i)
            for f in old_seq.glob(f"frame-{i:06d}.*"):
                link = dst / seq / f.name
                if not link.exists():
                    link.symlink_to(f.resolve())
            renamed[f"{old_seq.name}/frame-{i:06d}.color.png"] = f"{seq}/frame-{i:06d}.color.png"
    (dst / "TrainSplit.txt").write_text("sequence1\n")
    (dst / "TestSplit.txt").write_text("sequence2\n")
    (dst / "pgt").mkdir(exist_ok=True)
    for lst in sorted((src / "pgt").glob(f"*_{scene}.txt")):
        rows = []
        for line in lst.read_text().splitlines():
            name, *rest = line.split()
            if name in renamed:
                rows.append(" ".join([renamed[name], *rest]))
        (dst / "pgt" / lst.name.replace(f"_{scene}.txt", f"_{scene}-heldout.txt")).write_text("\n".join(rows) + "\n")
    return dst


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, default=Path("../shared/data/7scenes-redkitchen-mini"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    print(make_split(args.src, args.out))


if __name__ == "__main__":
    main()
