"""Reading and writing images, depth and normal maps with clear errors; atomic file writes."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError


def _check_size(arr: np.ndarray, expected_size, path, what: str):
    if expected_size is None:
        return
    w, h = expected_size
    if arr.shape[:2] != (h, w):
        raise InputError(f"{what} has size {arr.shape[1]}x{arr.shape[0]}, expected {w}x{h}", path)


def _truncated_jpeg(path: Path) -> bool:
    with open(path, "rb") as f:
        if f.read(2) != b"\xff\xd8":
            return False
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 64))  # some writers pad after the marker
        return b"\xff\xd9" not in f.read()


def read_color(path, gray: bool = False, expected_size=None) -> np.ndarray:
    """RGB uint8 (H, W, 3), or grayscale (H, W) with ``gray``."""
    path = Path(path)
    if not path.exists():
        raise InputError("image file is missing", path)
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise InputError("image cannot be decoded (corrupt or not an image)", path)
    if _truncated_jpeg(path):  # OpenCV decodes these without error, filling the lost part with grey
        raise InputError("image is truncated (JPEG ends before its end-of-image marker)", path)
    if not gray:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    _check_size(img, expected_size, path, "image")
    return img


def read_depth(path, expected_size=None, scale: float = 1000.0) -> np.ndarray:
    """Depth PNG (uint16, ``scale`` units per metre; 0 and 65535 invalid) -> float32 metres, 0 = invalid."""
    path = Path(path)
    if not path.exists():
        raise InputError("depth file is missing", path)
    raw = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if raw is None:
        raise InputError("depth map cannot be decoded (corrupt or not a PNG)", path)
    if raw.ndim != 2:
        raise InputError(f"depth map must be single-channel, got {raw.shape[2]} channels", path)
    if raw.dtype != np.uint16:
        raise InputError(f"depth map must be 16-bit (uint16 millimetres), got {raw.dtype}", path)
    _check_size(raw, expected_size, path, "depth map")
    depth = raw.astype(np.float32) / scale
    depth[(raw == 0) | (raw == 65535)] = 0.0
    return depth


def write_depth(path, depth_m: np.ndarray, scale: float = 1000.0):
    raw = np.clip(np.round(np.nan_to_num(depth_m) * scale), 0, 65534).astype(np.uint16)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), raw):
            raise OSError(f"cannot write {path}")


def write_color(path, rgb: np.ndarray, jpeg_quality: int = 95):
    path = Path(path)
    with atomic_path(path) as tmp:
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if path.suffix.lower() in (".jpg", ".jpeg") else []
        if not cv2.imwrite(str(tmp), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), params):
            raise OSError(f"cannot write {path}")


def write_normals(path, normals: np.ndarray):
    """Camera-frame unit normals (H, W, 3) -> 16-bit RGB PNG, (n + 1) / 2 scaled to 65535; 0 = invalid."""
    valid = np.isfinite(normals).all(-1) & (np.linalg.norm(np.nan_to_num(normals), axis=-1) > 0.5)
    enc = np.clip(np.round((np.nan_to_num(normals) + 1.0) * 0.5 * 65534) + 1, 1, 65535).astype(np.uint16)
    enc[~valid] = 0
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), enc[..., ::-1]):
            raise OSError(f"cannot write {path}")


def read_normals(path, expected_size=None) -> np.ndarray:
    """Inverse of :func:`write_normals` (also reads float .npy); invalid normals are 0."""
    path = Path(path)
    if not path.exists():
        raise InputError("normal map is missing", path)
    if path.suffix == ".npy":
        n = np.load(path).astype(np.float32)
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 3 or raw.dtype != np.uint16:
            raise InputError("normal map must be a 16-bit 3-channel PNG", path)
        raw = raw[..., ::-1]
        n = (raw.astype(np.float32) - 1) / 65534 * 2.0 - 1.0
        n[(raw == 0).all(-1)] = 0
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normal map must be HxWx3, got {n.shape}", path)
    _check_size(n, expected_size, path, "normal map")
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(norm > 0.5, n / np.maximum(norm, 1e-8), 0).astype(np.float32)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    A run killed mid-write leaves at most a ``.tmp`` file, never a half-written artifact that a
    later run would trust.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; artifacts get the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path, text: str):
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def commit_batches(n_todo: int, n_existing: int = 0, base: int = 16, growth: float = 0.25) -> list:
    """``[(start, end), ...]`` batches over ``n_todo`` new items of a file rewritten atomically per batch.

    Every atomic commit copies the whole file, so fixed batches cost O(n^2) bytes (a 7,000-image features file
    copied 440 times). Each batch here holds at least ``growth`` x the items already in the file, so the copies
    add up to ~(1 + 1 / growth) x the final size: O(n). An interrupted run loses at most one batch.
    """
    out, start = [], 0
    while start < n_todo:
        size = max(base, int(growth * (n_existing + start)))
        out.append((start, min(n_todo, start + size)))
        start = out[-1][1]
    return out
