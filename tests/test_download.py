"""`lipmap-loc download 7scenes` (localization/download.py) against a local HTTP server: no test reaches the internet.

The server holds small archives laid out like Microsoft's (a scene zip holding seq-NN.zip files), pseudo-GT files
and hloc-like archives; it honours Range requests, can cut a transfer after N bytes and serve a damaged archive.
"""
from __future__ import annotations

import hashlib
import io
import re
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from lipmap import InputError
from lipmap.datasets import load_scene
from localization import download as dl
from localization.cli import main as cli_main

FAST = dl.DownloadConfig(retries=2, retry_wait_s=0.0, timeout_s=10.0, chunk_bytes=256)


class _Handler(BaseHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest's output clean
        pass

    def do_GET(self):
        srv = self.server
        name, rng = self.path.lstrip("/"), self.headers.get("Range")
        srv.log.append((name, rng))
        data = srv.files.get(name)
        if data is None:
            self.send_error(404)
            return
        start = int(re.fullmatch(r"bytes=(\d+)-", rng).group(1)) if rng and srv.ranges else 0
        if start >= len(data) > 0:
            self.send_response(416)
            self.send_header("Content-Range", f"bytes */{len(data)}")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        self.send_response(206 if start else 200)
        if start:
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        body = data[start:]
        self.send_header("Content-Type", srv.types.get(name, "application/octet-stream"))
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        cut = srv.cut.pop(name, None)
        if cut is not None:  # a dropped connection: fewer bytes than announced, then close
            self.wfile.write(body[:cut])
            self.close_connection = True
            return
        self.wfile.write(body)


@pytest.fixture()
def server(monkeypatch):
    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", dl.MIRROR_ENV):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    srv.files, srv.cut, srv.types, srv.log, srv.ranges = {}, {}, {}, [], True
    srv.url = f"http://127.0.0.1:{srv.server_address[1]}"
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def _pose_text(angle: float, t) -> str:
    """A camera-to-world pose in the official layout (tab-separated, CRLF)."""
    c, s = np.cos(angle), np.sin(angle)
    T = np.array([[c, -s, 0, t[0]], [s, c, 0, t[1]], [0, 0, 1, t[2]], [0, 0, 0, 1.0]])
    return "".join("\t".join(f"{v: .7e}" for v in row) + "\t\r\n" for row in T)


def _frames(seed: int, seq: int, n: int) -> dict[str, bytes]:
    """``seq-NN/frame-NNNNNN.{color.png,depth.png,pose.txt}`` -> bytes: tiny real PNGs, valid poses."""
    rng = np.random.default_rng(seed * 100 + seq)
    out = {}
    for i in range(n):
        stem = f"seq-{seq:02d}/frame-{i:06d}"
        out[f"{stem}.color.png"] = cv2.imencode(".png", rng.integers(0, 255, (6, 8, 3), dtype=np.uint8))[1].tobytes()
        out[f"{stem}.depth.png"] = cv2.imencode(".png", rng.integers(500, 3000, (6, 8), dtype=np.uint16))[1].tobytes()
        out[f"{stem}.pose.txt"] = _pose_text(0.1 * i + seq, rng.normal(size=3)).encode()
    return out


def _zip(members: dict[str, bytes], method=zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _scene(seed: int, scene: str) -> tuple[bytes, dict[str, bytes]]:
    """Microsoft's layout: ``<scene>.zip`` holding the split files and ``seq-NN.zip`` files (seq-01 train, seq-02 test).
    Returns the archive and the files it unpacks to (relative to the scene folder)."""
    frames = {1: _frames(seed, 1, 3), 2: _frames(seed, 2, 2)}
    files = {"TrainSplit.txt": b"sequence1\r\n", "TestSplit.txt": b"sequence2\r\n"}
    outer = {f"{scene}/{k}": v for k, v in files.items()}
    for seq, fr in frames.items():
        outer[f"{scene}/seq-{seq:02d}.zip"] = _zip(fr)
        files.update(fr)
    return _zip(outer, zipfile.ZIP_STORED), files


def _damage(archive: bytes, member: str) -> bytes:
    """``archive`` with one byte of ``member``'s stored data flipped: the zip opens, the member fails its CRC."""
    info = zipfile.ZipFile(io.BytesIO(archive)).getinfo(member)
    header = archive[info.header_offset:info.header_offset + 30]
    start = info.header_offset + 30 + int.from_bytes(header[26:28], "little") + int.from_bytes(header[28:30], "little")
    pos = start + info.compress_size // 2
    return archive[:pos] + bytes([archive[pos] ^ 0xFF]) + archive[pos + 1:]


def _pgt_files(scenes) -> dict[str, bytes]:
    """The published layout: one line per frame of _scene's train (seq-01, 3 frames) and test (seq-02, 2) splits."""
    out = {"pgt/LICENSE": b"BSD 3-Clause License (test copy)\n"}
    for scene in scenes:
        for name in dl.pgt_names(scene):
            seq, n = (1, 3) if name.endswith("_train.txt") else (2, 2)
            out[name] = "".join(f"seq-{seq:02d}/frame-{i:06d}.color.png 1 0 0 0 0.{i} 0.{seq} 0.3 525.5\n"
                                for i in range(n)).encode()
    return out


def _sha(files: dict[str, bytes]) -> dict[str, str]:
    return {k: hashlib.sha256(v).hexdigest() for k, v in files.items()}


def _assert_scene(root: Path, scene: str, files: dict[str, bytes], pgt: bool = False):
    for rel, data in files.items():
        assert (root / scene / rel).read_bytes() == data, rel
    assert not list((root / scene).glob("seq-*.zip"))  # the nested archives are gone once unpacked
    s = load_scene("7scenes", root, scene)
    assert (len(s.mapping), len(s.query)) == (3, 2)
    if pgt:  # the pseudo GT sits where the loader reads the published layout (ROOT/pgt/<source>/7scenes/)
        s = load_scene("7scenes", root, scene, pose_source="sfm")
        assert np.allclose(s.query[1].cam_from_world[:3, 3], [0.1, 0.2, 0.3])


def test_cut_transfer_resumes_and_a_damaged_archive_fails_alone(server, tmp_path):
    chess, chess_files = _scene(1, "chess")
    fire, fire_files = _scene(2, "fire")
    heads, heads_files = _scene(3, "heads")
    pgt = _pgt_files(["chess", "fire", "heads"])
    server.files.update({"7scenes/chess.zip": chess, "7scenes/fire.zip": _damage(fire, "fire/seq-01.zip"),
                         "7scenes/heads.zip": heads, **pgt})
    cut = len(heads) * 2 // 5
    server.cut["7scenes/heads.zip"] = cut
    root = tmp_path / "data"

    with pytest.raises(dl.DownloadError) as e:
        dl.download_7scenes(root, "chess,fire,heads", mirror=server.url, conf=FAST, sha256=_sha(pgt))
    msg = str(e.value)
    fire_zip = root / "downloads" / "7scenes" / "fire.zip"
    assert f"{server.url}/7scenes/fire.zip" in msg and str(fire_zip) in msg and "fire/seq-01.zip" in msg
    assert "CRC" in msg and "run the same command again" in msg and len(e.value.failures) == 1
    assert not fire_zip.exists() and not (root / "fire" / "seq-01").exists()  # deleted, not half-unpacked

    # the cut transfer went on from the byte where it stopped, and gave the right files byte for byte
    assert [r for n, r in server.log if n == "7scenes/heads.zip"] == [None, f"bytes={cut}-"]
    _assert_scene(root, "chess", chess_files, pgt=True)
    _assert_scene(root, "heads", heads_files, pgt=True)
    for name, data in pgt.items():
        assert (root / name).read_bytes() == data
    assert not list((root / "downloads").rglob("*.part")) and not list((root / "downloads").rglob("*.zip"))

    # a second run fetches only what failed: the finished scenes and pseudo-GT files are not requested again
    server.files["7scenes/fire.zip"] = fire
    server.log.clear()
    dl.download_7scenes(root, "chess,fire,heads", mirror=server.url, conf=FAST, sha256=_sha(pgt))
    assert server.log == [("7scenes/fire.zip", None)]
    _assert_scene(root, "fire", fire_files)
    server.log.clear()
    dl.download_7scenes(root, "chess,fire,heads", mirror=server.url, conf=FAST, sha256=_sha(pgt))
    assert server.log == []


def test_a_part_file_left_by_an_earlier_run_is_resumed(server, tmp_path):
    chess, files = _scene(1, "chess")
    server.files["7scenes/chess.zip"] = chess
    part = tmp_path / "downloads" / "7scenes" / "chess.zip.part"
    part.parent.mkdir(parents=True)
    part.write_bytes(chess[:1000])
    dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    assert server.log == [("7scenes/chess.zip", "bytes=1000-")]
    _assert_scene(tmp_path, "chess", files)


def test_an_interrupted_unpack_goes_on_from_the_files_left(server, tmp_path, monkeypatch):
    chess, files = _scene(1, "chess")
    server.files["7scenes/chess.zip"] = chess
    real_extract = dl._extract

    def killed_at_seq_02(path, *args):
        if path.name == "seq-02.zip":
            raise KeyboardInterrupt
        real_extract(path, *args)

    monkeypatch.setattr(dl, "_extract", killed_at_seq_02)
    with pytest.raises(KeyboardInterrupt):
        dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    monkeypatch.setattr(dl, "_extract", real_extract)
    assert not (tmp_path / "downloads" / "7scenes" / "chess.zip").exists()  # the archive went once unpacked
    assert not dl.scene_is_complete(tmp_path / "chess")
    server.log.clear()
    dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    assert server.log == []  # seq-02.zip was still in the scene folder
    _assert_scene(tmp_path, "chess", files)


def test_a_damaged_inner_archive_sends_the_next_run_back_to_the_scene_archive(server, tmp_path):
    chess, files = _scene(1, "chess")
    with zipfile.ZipFile(io.BytesIO(chess)) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    inner = members["chess/seq-02.zip"]
    members["chess/seq-02.zip"] = _damage(inner, zipfile.ZipFile(io.BytesIO(inner)).namelist()[0])
    server.files["7scenes/chess.zip"] = _zip(members, zipfile.ZIP_STORED)  # its own CRCs hold: only seq-02 is bad
    with pytest.raises(dl.DownloadError, match=r"seq-02.zip, unpacked from chess.zip, is damaged: member 'seq-02/"):
        dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    server.files["7scenes/chess.zip"] = chess
    server.log.clear()
    dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    assert server.log == [("7scenes/chess.zip", None)]
    _assert_scene(tmp_path, "chess", files)


def test_a_scene_unpacked_by_other_means_is_not_fetched_again(server, tmp_path):
    _, files = _scene(1, "chess")
    for rel, data in files.items():
        (tmp_path / "chess" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "chess" / rel).write_bytes(data)
    (tmp_path / "chess" / "seq-02.zip").write_bytes(b"left by an interrupted unzip")
    assert not dl.scene_is_complete(tmp_path / "chess")
    (tmp_path / "chess" / "seq-02.zip").unlink()
    dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    assert server.log == []


def test_a_server_without_range_support_sends_the_whole_file_again(server, tmp_path):
    chess, files = _scene(1, "chess")
    server.files["7scenes/chess.zip"], server.ranges = chess, False
    server.cut["7scenes/chess.zip"] = 700
    dl.download_7scenes(tmp_path, ["chess"], pgt=False, mirror=server.url, conf=FAST)
    assert server.log == [("7scenes/chess.zip", None), ("7scenes/chess.zip", "bytes=700-")]
    _assert_scene(tmp_path, "chess", files)


def test_a_wrong_checksum_or_a_missing_file_names_the_url_and_the_file(server, tmp_path):
    pgt = _pgt_files(["chess"])
    server.files.update(pgt)
    sha = _sha(pgt)
    bad = "pgt/sfm/7scenes/chess_test.txt"
    sha[bad] = "0" * 64
    with pytest.raises(dl.DownloadError) as e:  # chess.zip is not on the server: HTTP 404, not retried
        dl.download_7scenes(tmp_path, "chess", mirror=server.url, conf=FAST, sha256=sha)
    msg = str(e.value)
    assert "SHA-256 mismatch" in msg and f"{server.url}/{bad}" in msg and str(tmp_path / bad) in msg
    assert "HTTP 404" in msg and f"{server.url}/7scenes/chess.zip" in msg and len(e.value.failures) == 2
    assert [n for n, _ in server.log].count("7scenes/chess.zip") == 1
    assert not (tmp_path / bad).exists() and not list(tmp_path.rglob("*.part"))
    assert all((tmp_path / n).read_bytes() == pgt[n] for n in pgt if n != bad)


def test_hloc_archives_unpack_as_hloc_does_and_a_web_page_is_refused(server, tmp_path):
    pairs = b"seq-03/frame-000000.color.png seq-01/frame-000000.color.png\n"
    server.files["hloc/7scenes_densevlad_retrieval_top_10.zip"] = _zip(
        {"7scenes_densevlad_retrieval_top_10/chess_top10.txt": pairs})
    server.files["hloc/7scenes_sfm_triangulated.zip"] = b"<html>Google Drive quota exceeded</html>"
    server.types["hloc/7scenes_sfm_triangulated.zip"] = "text/html; charset=utf-8"
    with pytest.raises(dl.DownloadError, match="web page instead of the file"):
        dl.fetch_hloc(tmp_path, "7scenes_sfm_triangulated", FAST, server.url)
    out = dl.fetch_hloc(tmp_path, "7scenes_densevlad_retrieval_top_10", FAST, server.url)
    assert (out / "chess_top10.txt").read_bytes() == pairs


def test_cli_download_uses_the_mirror_variable_and_reports_failures(server, tmp_path, monkeypatch, capsys):
    chess, files = _scene(1, "chess")
    fire, _ = _scene(2, "fire")
    server.files.update({"7scenes/chess.zip": chess, "7scenes/fire.zip": fire[: len(fire) // 2]})
    monkeypatch.setenv(dl.MIRROR_ENV, server.url)
    assert cli_main(["download", "7scenes", "--root", str(tmp_path), "--scenes", "chess", "--no-pgt"]) == 0
    _assert_scene(tmp_path, "chess", files)
    assert cli_main(["download", "7scenes", "--root", str(tmp_path), "--scenes", "chess,fire", "--no-pgt",
                     "--retries", "0"]) == 2
    err = capsys.readouterr().err
    assert f"{server.url}/7scenes/fire.zip" in err and "not a readable zip archive" in err


def test_scene_names_and_official_urls():
    assert dl.parse_scenes("all") == list(dl.SEVENSCENES_SCENES)
    assert dl.parse_scenes("fire, chess,fire") == ["fire", "chess"]
    with pytest.raises(InputError, match="unknown 7-Scenes scene 'kitchen'"):
        dl.parse_scenes("chess,kitchen")
    # convention pin: the URLs of hloc's 7Scenes README and the pinned pseudo-GT repository
    assert dl.official_url("7scenes/chess.zip") == (
        "http://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/chess.zip")
    assert dl.official_url("pgt/sfm/7scenes/chess_test.txt").endswith(
        f"visloc_pseudo_gt_limitations/{dl.PGT_COMMIT}/pgt/sfm/7scenes/chess_test.txt")
    assert dl.official_url("pgt/LICENSE").endswith(f"{dl.PGT_COMMIT}/LICENSE")
    assert "1IbS2vLmxr1N0f3CEnd_wsYlgclwTyvB1" in dl.official_url("hloc/7scenes_densevlad_retrieval_top_10.zip")
    assert set(dl.PUBLISHED_SHA256) == {n for s in dl.SEVENSCENES_SCENES for n in dl.pgt_names(s)} | {"pgt/LICENSE"}
