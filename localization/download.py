"""`lipmap-loc download 7scenes`: 7-Scenes, its published pseudo ground truth and hloc's 7-Scenes files.

    download_7scenes(ROOT, ["chess", "fire"]) writes
        ROOT/<scene>/TrainSplit.txt, TestSplit.txt, seq-NN/frame-NNNNNN.{color.png,depth.png,pose.txt}
        ROOT/pgt/{sfm,dslam}/7scenes/<scene>_{train,test}.txt    pseudo GT of Brachmann et al. (ICCV 2021)
        ROOT/pgt/LICENSE                                           the licence of the repository they come from
        ROOT/7scenes_sfm_triangulated/<scene>/triangulated/        hloc_models=True: hloc's SIFT SfM models
        ROOT/7scenes_densevlad_retrieval_top_10/<scene>_top10.txt  retrieval=True: hloc's query pairs
    and keeps its transfers in ROOT/downloads/ (an archive is deleted once unpacked, unless keep_archives).

Every transfer resumes: bytes go to ``<file>.part`` and the next try asks the server for the rest (HTTP Range),
within one run (``DownloadConfig.retries``) and across runs. A file gets its final name only when it has the
length the server announced and, where one is published (``PUBLISHED_SHA256``), the right SHA-256. Every zip
passes ``ZipFile.testzip()`` (all CRCs) before it is unpacked. A finished scene carries
``ROOT/<scene>/.lipmap-download.json`` and is skipped afterwards, as is a scene unpacked by other means (its
split files and all its sequence folders present, no ``seq-NN.zip`` left). One item's failure does not stop
the others; the error raised at the end names each URL, file and what to do. An archive fetched by hand can
be put at ``ROOT/downloads/<name>`` (names as in :class:`Remote`): it is checked and unpacked like a download.

Sources, all in ``SOURCES``: Microsoft's 7-Scenes archives (the URLs of hloc's 7Scenes README), the pseudo-GT
files of github.com/tsattler/visloc_pseudo_gt_limitations at the pinned commit ``PGT_COMMIT``, and the two
Google Drive files hloc's 7Scenes README names. A mirror holding the same files as ``<mirror>/<name>``
replaces all of them: ``mirror=`` (``--mirror``) or the environment variable ``LIPMAP_DOWNLOAD_MIRROR``.
"""
from __future__ import annotations

import argparse
import hashlib
import http.client
import json
import os
import re
import time
import urllib.error
import urllib.request
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from lipmap import InputError, __version__, logger
from lipmap.datasets.sevenscenes import SEVENSCENES_SCENES, read_split

PGT_COMMIT = "22b7c48a0e55b49d0214a8dbb022426f518e2795"
SOURCES = {
    "7scenes": "http://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/{file}",
    "pgt": "https://raw.githubusercontent.com/tsattler/visloc_pseudo_gt_limitations/" + PGT_COMMIT + "/{file}",
    "hloc": "https://drive.usercontent.google.com/download?id={file}&export=download&confirm=t",
}
HLOC_DRIVE_IDS = {  # hloc/pipelines/7Scenes/README.md
    "7scenes_sfm_triangulated": "1cu6KUR7WHO7G4EO49Qi3HEKU6n_yYDjb",
    "7scenes_densevlad_retrieval_top_10": "1IbS2vLmxr1N0f3CEnd_wsYlgclwTyvB1",
}
PUBLISHED_SHA256 = {  # the files at PGT_COMMIT
    "pgt/LICENSE": "c40e1e793a1362597dd0f9f74ad92ebb32b14ff85cc296af48e3164af9497cbe",
    "pgt/dslam/7scenes/chess_test.txt": "f2ea1fa6142c2129272fe3593c86e8cf11bd953a8f3edb69e98d12fa472e3e28",
    "pgt/dslam/7scenes/chess_train.txt": "6ca1cffc2595899433fdd7f5df3e39b17d7bf1f1cb3d8ac8c76484fa21700be7",
    "pgt/dslam/7scenes/fire_test.txt": "b945e75f699a1de427141039d10031d456365293075f39a6ab08d95bbb0b59e8",
    "pgt/dslam/7scenes/fire_train.txt": "8bcf0e5bb6aead0e059263fa8b16697c6e5bee70636e46d72935f9cd9f763827",
    "pgt/dslam/7scenes/heads_test.txt": "841eac8ef82919920606d0ae0aba812d41f4d002e261d8d2123f948725e0d9e1",
    "pgt/dslam/7scenes/heads_train.txt": "8841bd09cbfe0876c6f7e4e5b6621265ae6a8a80333502297e42ed2889781559",
    "pgt/dslam/7scenes/office_test.txt": "7d68ed94496c07cc8ae01f8340772dd0c6c11f7f83c8248eed5dfde7c0374d87",
    "pgt/dslam/7scenes/office_train.txt": "e60593ee9ebc28ab321259fc91f799c2539c150be86bb32a7037bfd61b6e8c4b",
    "pgt/dslam/7scenes/pumpkin_test.txt": "47562422d7ae13916d35d22b29cb2282ad0903233dd033791e0f4b91fe7708dd",
    "pgt/dslam/7scenes/pumpkin_train.txt": "fcc93c0b91630cc0f709dd9ced00e4a983175fbe68f31e41d1260335e0305c21",
    "pgt/dslam/7scenes/redkitchen_test.txt": "08776ade3bded977b7c4c2f432836592692d831f0cf246544eebe307e4deed2a",
    "pgt/dslam/7scenes/redkitchen_train.txt": "fc51c6a2f71cb6752314c720bf9c9a923fa24eb3d5e43ee21dbaa5aa6f782beb",
    "pgt/dslam/7scenes/stairs_test.txt": "bfbe02fe0321d85c3f89dac221bbabb4a6230ea53ee7af7b3611c6c8aa122b6f",
    "pgt/dslam/7scenes/stairs_train.txt": "eee0ce3c4f7c22567d0e79f690c5f3791da2fd5007c7dff407fbfe0526845d67",
    "pgt/sfm/7scenes/chess_test.txt": "d74a7f9b665e3d9e434072712e1aef2087b9247650aecd1108f631ef4c784dc8",
    "pgt/sfm/7scenes/chess_train.txt": "ea2e77dde507e7537190b337ffceca42a0cb0d3060eb0430e2ec369c4fb74b03",
    "pgt/sfm/7scenes/fire_test.txt": "3ebcf3a4001b9553398c70a8ac517b4c4b0855131f3d6bb6872437c49a7cb66c",
    "pgt/sfm/7scenes/fire_train.txt": "6a7acb30be15123581b5ef2ffa274b3c0177fa964c41666647448fde517f9a4c",
    "pgt/sfm/7scenes/heads_test.txt": "02bf44688c372e1dc7247bf2f7a711c055e99e3bf8182b6e6c018c5ca3a2090c",
    "pgt/sfm/7scenes/heads_train.txt": "ec94c37cf3eb3108d16d598d7460df7b7253d25ac790a68b9e7c2af68fae1f79",
    "pgt/sfm/7scenes/office_test.txt": "58e9440f4558174c9283c205593a0dcf9cf87c978a2ca595c0df3073bdb153da",
    "pgt/sfm/7scenes/office_train.txt": "1e07bfc926d8fb7d586ba3db66261cf7c23c295c1e9f8b20e94a4e31c003a36d",
    "pgt/sfm/7scenes/pumpkin_test.txt": "9bcdb40711fbd3be431d290a755c05e30c8ae9131dcb35ff9ac73c3c1d65fa43",
    "pgt/sfm/7scenes/pumpkin_train.txt": "bde35865923565891ed7952faf7a76d18ab828099a5441eed864d1364e11e487",
    "pgt/sfm/7scenes/redkitchen_test.txt": "1f85de67dc27c4f5e38334442756616d2c8ddc0d6363b55024063985a9446c2c",
    "pgt/sfm/7scenes/redkitchen_train.txt": "29e3bbde7ec59a1962fbb57c903d0d5c90b3a4a554922a3faabae34c0a40ca59",
    "pgt/sfm/7scenes/stairs_test.txt": "8d8b811ca8d03dcd782edee38586b93fc1b8ce2089827a85aed657a8bf90b60b",
    "pgt/sfm/7scenes/stairs_train.txt": "fa7d86ee1fda39d540cf52f63496050b0a50ad4a8e496db67f3dba90512907fb",
}
MIRROR_ENV = "LIPMAP_DOWNLOAD_MIRROR"
MARKER = ".lipmap-download.json"
STAGED = ".lipmap-download-staged"  # in ROOT/<scene>: its archive is unpacked, the seq-NN.zip files wait there
DOWNLOADS = "downloads"  # ROOT/downloads/<name>: archives and unfinished transfers
PGT_SOURCES = ("dslam", "sfm")


@dataclass
class DownloadConfig:
    retries: int = 5  # further tries of one transfer after a network error; each resumes where the last stopped
    retry_wait_s: float = 2.0  # wait before try k: retry_wait_s * k
    timeout_s: float = 60.0  # socket timeout of one request
    chunk_bytes: int = 1 << 20
    keep_archives: bool = False  # keep ROOT/downloads/*.zip after unpacking (the scenes alone are skipped anyway)


@dataclass(frozen=True)
class Remote:
    """One file to fetch: ``name`` is its path under a mirror and under ROOT (pgt) or ROOT/downloads (archives)."""

    name: str  # "7scenes/chess.zip", "pgt/sfm/7scenes/chess_train.txt", "hloc/7scenes_sfm_triangulated.zip"
    url: str
    sha256: str | None = None


class DownloadError(InputError):
    """A transfer or an archive that failed; names the URL, the local file and what to do."""

    def __init__(self, problem: str, url: str | None, path, hint: str | None = None):
        self.url = url
        self.failures: list[DownloadError] = []  # the summary error of download_7scenes lists the items here
        super().__init__(problem if url is None else f"{problem} [from {url}]", path, hint)


class _Retry(Exception):
    """A transfer that stopped early and can be resumed."""


def official_url(name: str) -> str:
    """The URL of ``name`` (a :class:`Remote` name) at its publisher's site."""
    source, _, rest = name.partition("/")
    if source == "7scenes":
        return SOURCES["7scenes"].format(file=rest)
    if source == "pgt":
        return SOURCES["pgt"].format(file="LICENSE" if rest == "LICENSE" else name)
    if source == "hloc":
        return SOURCES["hloc"].format(file=HLOC_DRIVE_IDS[Path(rest).stem])
    raise ValueError(f"unknown source of {name!r}")


def remote(name: str, mirror: str | None = None, sha256: dict | None = None) -> Remote:
    """The :class:`Remote` of ``name``, from ``mirror`` (or $LIPMAP_DOWNLOAD_MIRROR) when given, with its checksum."""
    mirror = mirror or os.environ.get(MIRROR_ENV) or None
    url = f"{mirror.rstrip('/')}/{name}" if mirror else official_url(name)
    return Remote(name, url, (PUBLISHED_SHA256 if sha256 is None else sha256).get(name))


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def _content_range(value: str | None) -> tuple[int | None, int | None]:
    """``bytes START-END/TOTAL`` (or ``bytes */TOTAL``) -> (START, TOTAL); None where absent."""
    m = re.fullmatch(r"bytes (?:(\d+)-\d+|\*)/(\d+|\*)", (value or "").strip())
    if not m:
        return None, None
    return (None if m.group(1) is None else int(m.group(1))), (None if m.group(2) == "*" else int(m.group(2)))


def _transfer(url: str, part: Path, conf: DownloadConfig, desc: str) -> None:
    """One request: append the rest of ``url`` to ``part`` (or rewrite it); _Retry when it stops early."""
    from tqdm import tqdm

    have = part.stat().st_size if part.exists() else 0
    headers = {"User-Agent": f"lipmap/{__version__}"}
    if have:
        headers["Range"] = f"bytes={have}-"
    try:
        resp = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=conf.timeout_s)
    except urllib.error.HTTPError as e:
        if e.code == 416 and have:  # nothing left to send: the .part may already be whole
            _, total = _content_range(e.headers.get("Content-Range"))
            if total == have:
                return
            part.unlink()
            raise _Retry(f"the server refused to resume at byte {have}; starting over") from None
        raise
    with resp:
        if resp.headers.get_content_type() == "text/html":
            raise DownloadError("the server sent a web page instead of the file (Google Drive does so when the "
                                "file's daily download quota is used up)", url, part.with_suffix(""),
                                "open the URL in a browser, save the file at this path, and run again")
        if resp.status == 206:
            start, total = _content_range(resp.headers.get("Content-Range"))
            if start != have:
                part.unlink()
                raise _Retry(f"the server resumed at byte {start}, not {have}; starting over")
            mode = "ab"
        else:  # a whole file, also when the server ignored the Range request
            have, mode = 0, "wb"
            length = resp.headers.get("Content-Length")
            total = int(length) if length and length.isdigit() else None
        with open(part, mode) as f, tqdm(total=total, initial=have, unit="B", unit_scale=True, unit_divisor=1024,
                                         desc=desc, leave=False) as bar:
            try:
                while chunk := resp.read(conf.chunk_bytes):
                    f.write(chunk)
                    bar.update(len(chunk))
            except (http.client.HTTPException, OSError) as e:
                raise _Retry(f"the transfer stopped at byte {bar.n}: {e!r}") from None
    size = part.stat().st_size
    if total is not None and size != total:
        raise _Retry(f"the connection closed after {size} of {total} bytes")


def fetch(r: Remote, dest: Path, conf: DownloadConfig | None = None) -> Path:
    """Download ``r`` to ``dest`` through ``dest.part``, resuming it; returns ``dest``.

    ``dest`` itself is only ever a complete file (right length, right SHA-256 when ``r.sha256``), so an
    existing ``dest`` is returned as it is.
    """
    conf = conf or DownloadConfig()
    dest = Path(dest)
    if dest.exists():
        return dest
    part = dest.with_name(dest.name + ".part")
    dest.parent.mkdir(parents=True, exist_ok=True)
    for attempt in range(conf.retries + 1):
        if attempt:
            time.sleep(conf.retry_wait_s * attempt)
        try:
            _transfer(r.url, part, conf, desc=r.name)
            break
        except _Retry as e:
            reason = str(e)
        except urllib.error.HTTPError as e:
            if e.code < 500 and e.code not in (408, 429):
                raise DownloadError(f"the server answered HTTP {e.code} {e.reason}", r.url, dest,
                                    "if the file has moved, fetch it by hand and put it at this path "
                                    "(benchmarks/7scenes/README.md lists the sources)") from None
            reason = f"HTTP {e.code} {e.reason}"
        except (urllib.error.URLError, http.client.HTTPException, OSError) as e:
            reason = repr(getattr(e, "reason", e))
        logger.warning("%s: %s (try %d of %d)", r.url, reason, attempt + 1, conf.retries + 1)
    else:
        raise DownloadError(f"download failed after {conf.retries + 1} tries: {reason}", r.url, part,
                            "run the same command again: it resumes from the bytes already in this .part file")
    if r.sha256 is not None:
        got = sha256_of(part)
        if got != r.sha256:
            part.unlink()
            raise DownloadError(f"SHA-256 mismatch (got {got}, expected {r.sha256})", r.url, dest,
                                "the downloaded file was deleted; run again, and if it fails again the source has "
                                "changed: fetch the file by hand and compare")
    part.replace(dest)
    return dest


def _check_zip(path: Path, url: str, what: str) -> None:
    """Raise DownloadError (and delete ``path``) unless every member of the zip reads back with its CRC."""
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
        problem = None if bad is None else f"member {bad!r} fails its CRC check"
    except (zipfile.BadZipFile, zlib.error, OSError, EOFError) as e:
        problem = f"not a readable zip archive ({e})"
    if problem:
        path.unlink()
        raise DownloadError(f"{what} is damaged: {problem}", url, path,
                            "the file was deleted; run the same command again to fetch it anew; if it fails again, "
                            "download the URL by hand and put it at this path")


def _extract(path: Path, dest: Path, prefix: str, url: str, desc: str) -> None:
    """Unpack the zip ``path`` into ``dest``; every member must lie under ``prefix`` (a folder name + '/')."""
    from tqdm import tqdm

    with zipfile.ZipFile(path) as zf:
        members = [m for m in zf.infolist() if not m.filename.startswith("__MACOSX/")]
        stray = [m.filename for m in members if not m.filename.startswith(prefix) or ".." in Path(m.filename).parts]
        if stray:
            raise DownloadError(f"unexpected archive layout: {stray[0]!r} is not under {prefix}", url, path,
                                "the archive is not the expected one; check the URL or the mirror")
        for m in tqdm(members, desc=f"unpack {desc}", unit="file", leave=False):
            zf.extract(m, dest)


def _write_marker(folder: Path, **info) -> None:
    (folder / MARKER).write_text(json.dumps({"lipmap": __version__, **info}, indent=1) + "\n")


def scene_is_complete(scene_dir: Path) -> bool:
    """True when ``scene_dir`` was finished by this module, or holds both splits and all their sequence folders."""
    if (scene_dir / MARKER).exists():
        return True
    try:
        seqs = read_split(scene_dir / "TrainSplit.txt") + read_split(scene_dir / "TestSplit.txt")
    except InputError:
        return False
    return (all(any((scene_dir / f"seq-{s:02d}").glob("*.pose.txt")) for s in seqs)
            and not any(scene_dir.glob("seq-*.zip")) and not (scene_dir / STAGED).exists())


def fetch_scene(root: Path, scene: str, conf: DownloadConfig, mirror: str | None = None) -> Path:
    """ROOT/<scene> unpacked from Microsoft's ``<scene>.zip`` and its nested ``seq-NN.zip`` files.

    The scene archive is deleted as soon as its ``seq-NN.zip`` files are out (``STAGED`` marks that), and each of
    those once its frames are out, so the disk holds at most about twice the scene; an interrupted run goes on from
    the files left.
    """
    scene_dir = root / scene
    if scene_is_complete(scene_dir):
        logger.info("Skipping %s: already unpacked in %s", scene, scene_dir)
        return scene_dir
    r = remote(f"7scenes/{scene}.zip", mirror)
    staged = scene_dir / STAGED
    if not staged.exists():
        archive = fetch(r, root / DOWNLOADS / r.name, conf)
        _check_zip(archive, r.url, f"the archive of {scene}")
        _extract(archive, root, f"{scene}/", r.url, scene)
        staged.write_text(f"{r.url}\n")
        if not conf.keep_archives:
            archive.unlink()
    for inner in sorted(scene_dir.glob("seq-*.zip")):
        try:
            _check_zip(inner, r.url, f"{inner.name}, unpacked from {scene}.zip,")
        except DownloadError:
            staged.unlink()  # the next run fetches the scene archive again
            raise
        _extract(inner, scene_dir, f"{inner.stem}/", r.url, f"{scene}/{inner.name}")
        inner.unlink()
    seqs = read_split(scene_dir / "TrainSplit.txt") + read_split(scene_dir / "TestSplit.txt")
    missing = [f"seq-{s:02d}" for s in seqs if not (scene_dir / f"seq-{s:02d}").is_dir()]
    if missing:
        raise DownloadError(f"the archive lacks {', '.join(missing)}, which the split files list", r.url, scene_dir,
                            "delete this folder and run again; if it happens again the archive is not the expected one")
    _write_marker(scene_dir, source=r.url, sequences=seqs)
    staged.unlink()
    logger.info("%s: %d sequences in %s", scene, len(seqs), scene_dir)
    return scene_dir


def pgt_names(scene: str) -> list[str]:
    """The published pseudo-GT files of ``scene`` (paths under ROOT, as in the publisher's repository)."""
    return [f"pgt/{src}/7scenes/{scene}_{split}.txt" for src in PGT_SOURCES for split in ("train", "test")]


def fetch_published(root: Path, name: str, conf: DownloadConfig, mirror: str | None = None,
                    sha256: dict | None = None) -> Path:
    """ROOT/<name> (a small file fetched as it is); an existing copy with the wrong checksum is fetched again."""
    r = remote(name, mirror, sha256)
    dest = root / name
    if dest.exists():
        if r.sha256 is None or sha256_of(dest) == r.sha256:
            logger.debug("Skipping %s: present", dest)
            return dest
        logger.warning("%s does not have the published checksum: fetching it again", dest)
        dest.unlink()
    return fetch(r, dest, conf)


def fetch_hloc(root: Path, what: str, conf: DownloadConfig, mirror: str | None = None) -> Path:
    """ROOT/<what>/ from hloc's archive ``<what>.zip`` (``what``: a key of ``HLOC_DRIVE_IDS``), as hloc unpacks it."""
    out = root / what
    if (out / MARKER).exists():
        logger.info("Skipping %s: already unpacked", out)
        return out
    r = remote(f"hloc/{what}.zip", mirror)
    archive = fetch(r, root / DOWNLOADS / r.name, conf)
    _check_zip(archive, r.url, f"the archive {archive.name}")
    _extract(archive, root, f"{what}/", r.url, what)
    _write_marker(out, source=r.url, archive_bytes=archive.stat().st_size)
    if not conf.keep_archives:
        archive.unlink()
    return out


def parse_scenes(scenes) -> list[str]:
    """``None``/"all"/"chess,fire"/a list -> scene names, each checked against the seven."""
    if scenes is None or scenes == "all" or scenes == ["all"]:
        return list(SEVENSCENES_SCENES)
    names = [s.strip() for s in scenes.split(",")] if isinstance(scenes, str) else list(scenes)
    unknown = [s for s in names if s not in SEVENSCENES_SCENES]
    if unknown or not names:
        raise InputError(f"unknown 7-Scenes scene {unknown[0] if unknown else '(none)'!r}; choose among "
                         f"{', '.join(SEVENSCENES_SCENES)} or 'all'")
    return list(dict.fromkeys(names))


def download_7scenes(root, scenes=None, pgt: bool = True, hloc_models: bool = False, retrieval: bool = False,
                     mirror: str | None = None, conf: DownloadConfig | None = None,
                     sha256: dict | None = None) -> Path:
    """Fetch and unpack 7-Scenes ``scenes`` (default all) under ``root``; returns ``root``.

    ``pgt``: the published pseudo GT (ROOT/pgt/...); ``hloc_models`` / ``retrieval``: hloc's SIFT SfM models and
    DenseVLAD pairs (one archive each for all scenes). ``mirror``: a base URL replacing every official one.
    ``sha256``: {name: digest} replacing ``PUBLISHED_SHA256`` (for a mirror of other files). Every item is tried;
    the DownloadError raised at the end lists those that failed (the others are complete and will be skipped).
    """
    root, names = Path(root), parse_scenes(scenes)
    conf = conf or DownloadConfig()
    root.mkdir(parents=True, exist_ok=True)
    jobs = []
    for scene in names:
        jobs.append((f"scene {scene}", lambda s=scene: fetch_scene(root, s, conf, mirror)))
        if pgt:
            jobs += [(n, lambda n=n: fetch_published(root, n, conf, mirror, sha256)) for n in pgt_names(scene)]
    if pgt:
        jobs.append(("pgt/LICENSE", lambda: fetch_published(root, "pgt/LICENSE", conf, mirror, sha256)))
    for flag, what in ((hloc_models, "7scenes_sfm_triangulated"), (retrieval, "7scenes_densevlad_retrieval_top_10")):
        if flag:
            jobs.append((what, lambda w=what: fetch_hloc(root, w, conf, mirror)))
    failed = []
    for label, job in jobs:
        try:
            job()
        except DownloadError as e:
            logger.error("%s failed: %s", label, e.problem)
            failed.append(e)
    if failed:
        lines = "\n  - ".join(str(e) for e in failed)
        err = DownloadError(f"{len(failed)} of {len(jobs)} items failed (the others are complete):\n  - {lines}\n",
                            None, root, "run the same command again to retry them; finished items are skipped")
        err.failures = failed
        raise err
    logger.info("7-Scenes ready in %s (check it: lipmap-loc info --dataset 7scenes --root %s)", root, root)
    return root


def add_download_parser(subparsers) -> argparse.ArgumentParser:
    """`lipmap-loc download 7scenes --root DATA [--scenes chess,fire|all] [--no-pgt] [--hloc-models] [--retrieval]`."""
    from lipmap.cliargs import int_at_least

    p = subparsers.add_parser("download", help="download 7-Scenes with its pseudo ground truth (resumable)",
                              description="\n\n".join(__doc__.split("\n\n")[:2]),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", choices=["7scenes"])
    p.add_argument("--root", type=Path, required=True, help="dataset root: scenes go to ROOT/<scene>")
    p.add_argument("--scenes", default="all", help=f"comma-separated, from {', '.join(SEVENSCENES_SCENES)}; or 'all'")
    p.add_argument("--pgt", action=argparse.BooleanOptionalAction, default=True,
                   help="the published pseudo ground truth (sfm, dslam) in ROOT/pgt (default: on; 0.4-2.5 MB a scene)")
    p.add_argument("--hloc-models", action="store_true",
                   help="hloc's SIFT SfM models, ROOT/7scenes_sfm_triangulated (one Google Drive archive, all scenes)")
    p.add_argument("--retrieval", action="store_true",
                   help="hloc's DenseVLAD query pairs, ROOT/7scenes_densevlad_retrieval_top_10 (Google Drive)")
    p.add_argument("--mirror", default=None, help=f"base URL holding the files as MIRROR/<name> (also ${MIRROR_ENV})")
    p.add_argument("--keep-archives", action="store_true", help="keep ROOT/downloads/*.zip after unpacking")
    p.add_argument("--retries", type=int_at_least(0), default=DownloadConfig.retries, help="tries after a network error, each resuming")
    p.set_defaults(func=cli_download)
    return p


def cli_download(args) -> Path:
    if args.retries < 0:
        raise InputError(f"--retries takes a number >= 0, got {args.retries}")
    conf = DownloadConfig(retries=args.retries, keep_archives=args.keep_archives)
    root = download_7scenes(args.root, args.scenes, pgt=args.pgt, hloc_models=args.hloc_models,
                            retrieval=args.retrieval, mirror=args.mirror, conf=conf)
    print(root)
    return root


__all__ = ["DownloadConfig", "DownloadError", "Remote", "SOURCES", "PUBLISHED_SHA256", "download_7scenes", "fetch",
           "fetch_scene", "fetch_published", "fetch_hloc", "official_url", "remote", "add_download_parser"]
