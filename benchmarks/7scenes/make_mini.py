"""Cut the RedKitchen minis (the shared ``7scenes-redkitchen-mini``) from a full 7-Scenes download, frame for frame.

    lipmap-loc download 7scenes --root DATA --scenes redkitchen
    python benchmarks/7scenes/make_mini.py --root DATA --out OUT [--pgt DATA/pgt]

Both minis come from RedKitchen ``seq-01``, frames 0-499, keeping their frame numbers:
    OUT/redkitchen/          seq-01: frames 0, 10, ... 490 (mapping)   seq-02: frames 5, 15, ... 495 (queries)
    OUT/redkitchen-sparse/   seq-01: frames 0, 20, ... 480 (mapping)   seq-02: frames 10, 30, ... 490 (queries)
each with TrainSplit.txt ("sequence1"), TestSplit.txt ("sequence2") and ``pgt/{dslam,sfm}_<mini>.txt``: the
published pseudo-GT lines of those frames, verbatim, the queries renamed to ``seq-02/...``. A frame is
``frame-NNNNNN.color.jpg`` (the colour PNG re-encoded as JPEG, quality 80, 4:2:0: the minis' quantization tables),
``.depth.png`` and ``.pose.txt`` (both copied byte for byte). OUT also gets the licences:
``LICENSE-7scenes-data.rtf`` (from ``--licence-7scenes``, default DATA/LICENSE-7scenes-data.rtf: save Microsoft's
licence there from the 7-Scenes page) and ``LICENSE.visloc_pseudo_gt_limitations.BSD3`` (PGT/LICENSE, which
``lipmap-loc download`` fetches); a licence not found is named in a warning. The shared copy's ``LICENSE.tsdf-fusion-python.BSD2`` covers the repository
its frames were taken from and does not apply to a cut from Microsoft's archives.

What may differ from the shared copy: the JPEG bytes (same quality and tables; the encoder's version decides the
rest) and the pose files' text, which keeps the official layout (tab-separated, 8 significant digits) where the
shared copy holds the same values reprinted.
"""
from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from lipmap import InputError, logger

SOURCE_SCENE, SOURCE_SEQ = "redkitchen", "seq-01"
MINIS = {  # mini -> (mapping frames, query frames) of SOURCE_SCENE/SOURCE_SEQ
    "redkitchen": (range(0, 500, 10), range(5, 500, 10)),
    "redkitchen-sparse": (range(0, 500, 20), range(10, 500, 20)),
}
PGT_SOURCES = ("dslam", "sfm")
JPEG_QUALITY = 80
LICENCE_7SCENES = "LICENSE-7scenes-data.rtf"
LICENCE_PGT = "LICENSE.visloc_pseudo_gt_limitations.BSD3"
SEVENSCENES_PAGE = "https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/"


def cut_frame(src_seq: Path, frame: int, dst_seq: Path) -> None:
    """``frame`` of ``src_seq`` into ``dst_seq``: colour PNG -> JPEG, depth and pose copied as they are."""
    import cv2

    stem = f"frame-{frame:06d}"
    color = src_seq / f"{stem}.color.png"
    img = cv2.imread(str(color), cv2.IMREAD_COLOR) if color.exists() else None
    if img is None:
        raise InputError("colour image is missing or unreadable", color,
                         "download RedKitchen with: lipmap-loc download 7scenes --root DATA --scenes redkitchen")
    if not cv2.imwrite(str(dst_seq / f"{stem}.color.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
        raise InputError("cannot write the JPEG", dst_seq / f"{stem}.color.jpg")
    for kind in ("depth.png", "pose.txt"):
        src = src_seq / f"{stem}.{kind}"
        if not src.exists():
            raise InputError(f"{kind.split('.')[0]} file is missing", src)
        shutil.copyfile(src, dst_seq / src.name)


def read_published_pgt(pgt_dir: Path, source: str, scene: str = SOURCE_SCENE) -> dict[str, str]:
    """``{name: the rest of its line}`` of the published ``<source>/7scenes/<scene>_{train,test}.txt``."""
    out = {}
    for split in ("train", "test"):
        path = Path(pgt_dir) / source / "7scenes" / f"{scene}_{split}.txt"
        if not path.exists():
            raise InputError("published pseudo-GT file is missing", path,
                             "fetch it with: lipmap-loc download 7scenes --root DATA --scenes redkitchen")
        for line in path.read_text().splitlines():
            parts = line.split(maxsplit=1)
            if len(parts) == 2:
                out[parts[0]] = parts[1]
    return out


def make_mini(root, out, mini: str = "redkitchen", pgt_dir=None) -> Path:
    """OUT/<mini> cut from ROOT/redkitchen/seq-01 and the published pseudo GT in ``pgt_dir`` (default ROOT/pgt)."""
    from tqdm import tqdm

    if mini not in MINIS:
        raise InputError(f"unknown mini {mini!r}; choose one of {', '.join(MINIS)}")
    src_seq = Path(root) / SOURCE_SCENE / SOURCE_SEQ
    if not src_seq.is_dir():
        raise InputError("RedKitchen seq-01 not found", src_seq,
                         "download it with: lipmap-loc download 7scenes --root DATA --scenes redkitchen")
    pgt_dir = Path(pgt_dir) if pgt_dir is not None else Path(root) / "pgt"
    published = {src: read_published_pgt(pgt_dir, src) for src in PGT_SOURCES}
    dst = Path(out) / mini
    renamed = {}  # name in the published lists -> name in the mini
    for seq, frames in zip(("seq-01", "seq-02"), MINIS[mini]):
        (dst / seq).mkdir(parents=True, exist_ok=True)
        for i in tqdm(frames, desc=f"{mini}/{seq}", leave=False):
            cut_frame(src_seq, i, dst / seq)
            renamed[f"{SOURCE_SEQ}/frame-{i:06d}.color.png"] = f"{seq}/frame-{i:06d}.color.png"
    (dst / "TrainSplit.txt").write_text("sequence1\n")
    (dst / "TestSplit.txt").write_text("sequence2\n")
    (dst / "pgt").mkdir(exist_ok=True)
    for src, lines in published.items():
        missing = [name for name in renamed if name not in lines]
        if missing:
            raise InputError(f"no {src} pose for {missing[0]} ({len(missing)} frames missing)",
                             pgt_dir / src / "7scenes" / f"{SOURCE_SCENE}_train.txt")
        rows = [f"{new} {lines[old]}" for old, new in renamed.items()]
        (dst / "pgt" / f"{src}_{mini}.txt").write_text("\n".join(rows) + "\n")
    return dst


def copy_licences(out: Path, pgt_dir: Path, licence_7scenes: Path) -> list[Path]:
    """The licences that travel with the minis; a missing one is named in a warning, not invented."""
    written = []
    for src, name, where in ((licence_7scenes, LICENCE_7SCENES, f"save it from {SEVENSCENES_PAGE}"),
                             (pgt_dir / "LICENSE", LICENCE_PGT, "lipmap-loc download 7scenes fetches it")):
        if Path(src).is_file():
            shutil.copyfile(src, out / name)
            written.append(out / name)
        else:
            logger.warning("%s not found: OUT/%s is not written (%s)", src, name, where)
    return written


def make_minis(root, out, pgt_dir=None, licence_7scenes=None) -> Path:
    """Both minis and their licences under ``out``; returns ``out``."""
    root, out = Path(root), Path(out)
    pgt_dir = Path(pgt_dir) if pgt_dir is not None else root / "pgt"
    for mini in MINIS:
        logger.info("%s", make_mini(root, out, mini, pgt_dir))
    copy_licences(out, pgt_dir, Path(licence_7scenes) if licence_7scenes else root / LICENCE_7SCENES)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True, help="a 7-Scenes root holding redkitchen/seq-01")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--pgt", type=Path, default=None, help="the published pseudo-GT folder (default: ROOT/pgt)")
    ap.add_argument("--licence-7scenes", type=Path, default=None,
                    help=f"the 7-Scenes licence file (default: ROOT/{LICENCE_7SCENES})")
    args = ap.parse_args(argv)
    try:
        print(make_minis(args.root, args.out, args.pgt, args.licence_7scenes))
    except InputError as e:
        raise SystemExit(f"make_mini.py: error: {e}") from None


if __name__ == "__main__":
    main()
