"""2D line segments per image: LSD detection (OpenCV), import of external detections, the HDF5 cache.

Artifact ``lines2d.h5`` (hloc-style): one group per image name (``seq-01/frame-000000.color.png``;
the '/' makes nested groups, as in hloc's features.h5), each holding

    lines   (N, 4) float32   x1, y1, x2, y2 in COLMAP pixel convention (pixel centre at i + 0.5)
    scores  (N,)   float32   detector confidence (LSD: -log10 NFA; imports: their score; else length)

and file attributes ``detector`` (name) and ``conf`` (JSON of the settings). Lines are stored
longest first. An image where nothing was found has an empty (0, 4) ``lines`` dataset.

Pixel conventions at the boundaries:
- OpenCV's LSD puts pixel centres at integers: we add 0.5 on import.
- HAWP / LiP-Map ``WireframeGraph`` JSON: coordinates are continuous with the origin at the image
  corner (HAWP scales heat-map cell coordinates by image/heat-map size, which is exact only in
  that convention), i.e. already COLMAP-like: default offset 0. Pass ``pixel_offset=0.5`` if your
  files were made with integer pixel centres.
- Plain arrays (.npz/.npy/.txt/.h5): assumed COLMAP convention unless ``pixel_offset`` says otherwise.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Optional, Sequence, Union

import h5py
import numpy as np
from tqdm import tqdm

from . import logger
from .errors import InputError
from .geometry import clip_segments_to_image
from .imageio import atomic_path, commit_batches, read_color
from .presets import resolve

REFERENCE_SIZE = (640, 480)


@dataclass(frozen=True)
class LineDetectorConfig:
    """LSD settings. ``min_length`` is in pixels at 640x480 and scales with the image diagonal."""

    name: str = "lsd"
    min_length: float = 15.0
    max_lines: int = 2000  # keep the longest; 0 = no cap
    refine: str = "adv"  # "none", "std" or "adv" (adv gives NFA scores)
    scale: float = 0.8
    sigma_scale: float = 0.6
    quant: float = 2.0
    ang_th: float = 22.5
    log_eps: float = 0.0
    density_th: float = 0.7
    n_bins: int = 1024

    def min_length_for(self, width: int, height: int) -> float:
        ref = float(np.hypot(*REFERENCE_SIZE))
        return self.min_length * float(np.hypot(width, height)) / ref

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)


confs = {
    "lsd": LineDetectorConfig(),
    "lsd-fast": LineDetectorConfig(refine="std"),
    "lsd-dense": LineDetectorConfig(min_length=10.0, max_lines=4000),
    "lsd-long": LineDetectorConfig(min_length=30.0, max_lines=500),
}


def get_conf(conf: Union[None, str, LineDetectorConfig, dict] = None) -> LineDetectorConfig:
    """A :class:`LineDetectorConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "2D line detector", default="lsd")


# ----------------------------------------------------------------------------------------------
# detection
# ----------------------------------------------------------------------------------------------
def _lsd(conf: LineDetectorConfig):
    import cv2

    refine = {"none": cv2.LSD_REFINE_NONE, "std": cv2.LSD_REFINE_STD, "adv": cv2.LSD_REFINE_ADV}[conf.refine]
    return cv2.createLineSegmentDetector(
        refine, conf.scale, conf.sigma_scale, conf.quant, conf.ang_th, conf.log_eps, conf.density_th, conf.n_bins
    )


def filter_lines(lines: np.ndarray, scores: np.ndarray, min_length: float, max_lines: int):
    """Drop lines shorter than ``min_length``, sort longest first, keep at most ``max_lines`` (0: all)."""
    lines = np.asarray(lines, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    length = np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1])
    keep = np.isfinite(lines).all(1) & (length >= min_length)
    order = np.flatnonzero(keep)[np.argsort(-length[keep], kind="stable")]
    if max_lines and len(order) > max_lines:
        order = order[:max_lines]
    return lines[order], scores[order]


def detect_lines_image(image: np.ndarray, conf: Union[None, str, LineDetectorConfig] = None):
    """LSD on one image.

    Args:
        image: :math:`(H, W)` uint8 grayscale or :math:`(H, W, 3)` RGB.
        conf: preset name or :class:`LineDetectorConfig`.

    Returns:
        **lines** :math:`(N, 4)` float64 (x1, y1, x2, y2), COLMAP pixel convention, longest first;
        **scores** :math:`(N,)` (-log10 NFA with refine="adv", else segment length).
    """
    conf = get_conf(conf)
    if image.ndim == 3:
        import cv2

        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.dtype != np.uint8:
        raise InputError(f"LSD needs an 8-bit image, got {image.dtype}")
    h, w = image.shape
    out = _lsd(conf).detect(image)
    raw = out[0]
    if raw is None or len(raw) == 0:
        return np.zeros((0, 4)), np.zeros(0)
    lines = raw.reshape(-1, 4).astype(np.float64) + 0.5  # OpenCV pixel centres at integers -> COLMAP
    # LSD's refinement can put an endpoint a fraction of a pixel outside the image
    clipped, inside = clip_segments_to_image(lines, w, h)
    lines = np.where(inside[:, None], clipped.reshape(-1, 4), np.nan)
    nfa = out[3] if len(out) > 3 else None
    if nfa is not None and len(nfa) == len(lines):
        scores = nfa.reshape(-1).astype(np.float64)
    else:
        scores = np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1])
    return filter_lines(lines, scores, conf.min_length_for(w, h), conf.max_lines)


# ----------------------------------------------------------------------------------------------
# HDF5 cache
# ----------------------------------------------------------------------------------------------
def list_names(h5_path) -> list:
    """Image names stored in a lines2d.h5 (groups holding a ``lines`` dataset)."""
    h5_path = Path(h5_path)
    if not h5_path.exists():
        return []
    names = []
    with h5py.File(h5_path, "r") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Group) and "lines" in obj and isinstance(obj["lines"], h5py.Dataset):
                names.append(name)

        f.visititems(visit)
    return sorted(names)


def load_lines(h5_path, name: str, with_scores: bool = False):
    """(N, 4) float32 lines of image ``name`` (and the (N,) scores with ``with_scores``)."""
    h5_path = Path(h5_path)
    if not h5_path.exists():
        raise InputError("line file is missing", h5_path)
    with h5py.File(h5_path, "r") as f:
        if name not in f or "lines" not in f[name]:
            raise InputError(f"no lines stored for image {name!r}", h5_path, hint="run detect_lines first")
        g = f[name]
        lines = g["lines"][()].astype(np.float32).reshape(-1, 4)
        if not with_scores:
            return lines
        scores = g["scores"][()].astype(np.float32) if "scores" in g else np.ones(len(lines), np.float32)
        return lines, scores


def _write_groups(out_h5: Path, results: dict, attrs: dict, overwrite_names: Iterable = ()):
    """Atomically add ``{name: (lines, scores)}`` groups to ``out_h5`` (copying what is already there)."""
    with atomic_path(out_h5) as tmp:
        if out_h5.exists():
            shutil.copyfile(out_h5, tmp)
        with h5py.File(tmp, "a") as f:
            for k, v in attrs.items():
                f.attrs[k] = v
            for name, (lines, scores) in results.items():
                if name in f:
                    del f[name]
                g = f.create_group(name)
                g.create_dataset("lines", data=np.asarray(lines, np.float32).reshape(-1, 4))
                g.create_dataset("scores", data=np.asarray(scores, np.float32).reshape(-1))


def lines_stamp(detector: str, settings: dict):
    """The :class:`~lipmap.artifacts.Stamp` of a ``lines2d.h5`` made by ``detector`` with ``settings``."""
    from .artifacts import Stamp

    return Stamp("lines2d", {"detector": detector, "conf": settings})


def _start(out_h5: Path, stamp, overwrite: bool) -> set:
    """Names already in ``out_h5`` when the same settings made it (resume); raises if others did."""
    from .artifacts import reuse

    return set(list_names(out_h5)) if reuse(out_h5, stamp, overwrite, "2D lines") else set()


def _image_items(images, image_root=None):
    """(name, loader) pairs from Views or image paths."""
    items = []
    for im in images:
        if hasattr(im, "load_color") and hasattr(im, "name"):
            items.append((im.name, (lambda v=im: v.load_color(gray=True))))
        else:
            p = Path(im)
            if image_root is not None:
                name = p.relative_to(image_root).as_posix() if p.is_absolute() else p.as_posix()
                p = p if p.is_absolute() else Path(image_root) / p
            else:
                name = p.name
            items.append((name, (lambda q=p: read_color(q, gray=True))))
    return items


def detect_lines(
    images: Sequence,
    out_h5,
    conf: Union[None, str, LineDetectorConfig, dict] = None,
    overwrite: bool = False,
    image_root=None,
    commit_every: int = 100,
) -> Path:
    """Detect 2D lines in every image and cache them in ``out_h5`` (lines2d.h5).

    Args:
        images: :class:`~lipmap.scene.View` objects, or image paths (named relative to
            ``image_root`` when given, else by file name).
        out_h5: output file; images already in it are skipped unless ``overwrite``.
        conf: preset name ("lsd", "lsd-fast", "lsd-dense", "lsd-long"), dict of overrides or conf.
        commit_every: results are written (atomically) every this many images at least (more as the file
            grows, :func:`lipmap.imageio.commit_batches`), so an interrupted run keeps what it finished.

    Returns:
        the path of ``out_h5``.
    """
    conf = get_conf(conf)
    out_h5 = Path(out_h5)
    conf_json = conf.to_json()
    stamp = lines_stamp(conf.name, asdict(conf))
    done = _start(out_h5, stamp, overwrite)
    items = _image_items(images, image_root)
    todo = [(n, ld) for n, ld in items if n not in done]
    if len(todo) < len(items):
        logger.info("Skipping %d images already in %s.", len(items) - len(todo), out_h5)
    logger.info("Detecting 2D lines in %d images with %s.", len(todo), conf_json)
    attrs = {"detector": conf.name, "conf": conf_json, "pixel_convention": "colmap (pixel centre at i + 0.5)",
             **stamp.h5_attrs()}
    pending, n_lines = {}, []
    ends = {end for _, end in commit_batches(len(todo), len(done), commit_every)}
    for i, (name, load) in enumerate(tqdm(todo, desc="lines2d", disable=len(todo) < 2)):
        lines, scores = detect_lines_image(load(), conf)
        if len(lines) == 0:
            logger.warning("No lines detected in %s.", name)
        pending[name] = (lines, scores)
        n_lines.append(len(lines))
        if i + 1 in ends:
            _write_groups(out_h5, pending, attrs)
            pending = {}
    if pending or not out_h5.exists():
        _write_groups(out_h5, pending, attrs)
    if n_lines:
        logger.info("Detected %.1f lines per image (min %d, max %d).", np.mean(n_lines), min(n_lines), max(n_lines))
    return out_h5


# ----------------------------------------------------------------------------------------------
# import of detections made elsewhere
# ----------------------------------------------------------------------------------------------
def read_wireframe_json(path, image_size: Optional[tuple] = None, min_score: float = 0.0, pixel_offset: float = 0.0):
    """Lines from a HAWP / LiP-Map ``WireframeGraph`` JSON file.

    The file holds ``vertices`` (K, 2), ``vertices-score`` (K,), ``edges`` (M, 2) vertex indices,
    ``edges-weights`` (M,) and the detection resolution ``height``, ``width``.

    Args:
        image_size: (W, H) of the image the lines are for; coordinates are rescaled from the
            detection resolution when it differs (exact in corner-origin coordinates).
        min_score: drop edges whose weight is below this.
        pixel_offset: added to every coordinate after rescaling (0.5 if the file has integer
            pixel centres).

    Returns:
        **lines** (M', 4) and **scores** (M',).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read WireframeGraph JSON: {e}", path) from e
    for key in ("vertices", "edges"):
        if key not in data:
            raise InputError(f"WireframeGraph JSON lacks the key {key!r}", path)
    V = np.asarray(data["vertices"], dtype=np.float64).reshape(-1, 2) if len(data["vertices"]) else np.zeros((0, 2))
    E = np.asarray(data["edges"], dtype=np.int64).reshape(-1, 2) if len(data["edges"]) else np.zeros((0, 2), np.int64)
    w = np.asarray(data.get("edges-weights", np.ones(len(E))), dtype=np.float64).reshape(-1)
    if len(w) != len(E):
        raise InputError(f"{len(E)} edges but {len(w)} edges-weights", path)
    if len(E) and (E.min() < 0 or E.max() >= len(V)):
        raise InputError(f"edge vertex index out of range (K={len(V)} vertices)", path)
    lines = np.concatenate([V[E[:, 0]], V[E[:, 1]]], axis=1) if len(E) else np.zeros((0, 4))
    if image_size is not None and "width" in data and "height" in data:
        sx = image_size[0] / float(data["width"])
        sy = image_size[1] / float(data["height"])
        lines = lines * np.array([sx, sy, sx, sy])
    lines = lines + pixel_offset
    keep = w >= min_score
    return lines[keep], w[keep]


def read_lines_array(path, name: Optional[str] = None, pixel_offset: float = 0.0):
    """N x 4 lines from .npz (key "lines" or the first array), .npy, .txt (N rows of 4; a first
    line holding only the count is skipped) or .h5 (dataset at ``name``, or group ``name``/lines).

    Returns:
        **lines** (N, 4) and **scores** (N,) ("scores" array when present, else lengths).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("line file is missing", path)
    scores = None
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(path) as z:
                if not z.files:
                    raise InputError("npz file holds no arrays", path)
                arr = z["lines"] if "lines" in z.files else z[z.files[0]]
                scores = z["scores"] if "scores" in z.files else None
        elif suffix == ".npy":
            arr = np.load(path)
        elif suffix in (".h5", ".hdf5"):
            if name is None:
                raise InputError("an HDF5 line file needs the image name", path)
            with h5py.File(path, "r") as f:
                if name not in f:
                    raise InputError(f"no entry for image {name!r}", path)
                obj = f[name]
                if isinstance(obj, h5py.Group):
                    if "lines" not in obj:
                        raise InputError(f"group {name!r} has no 'lines' dataset", path)
                    arr = obj["lines"][()]
                    scores = obj["scores"][()] if "scores" in obj else None
                else:
                    arr = obj[()]
        elif suffix == ".txt":
            rows = [r.split() for r in path.read_text().splitlines() if r.strip()]
            if rows and len(rows[0]) == 1:
                rows = rows[1:]
            arr = np.array([[float(x) for x in r[:4]] for r in rows]) if rows else np.zeros((0, 4))
        else:
            raise InputError(f"unsupported line file type {suffix!r}", path, hint="use .npz, .npy, .txt, .h5 or .json")
    except (ValueError, OSError) as e:
        if isinstance(e, InputError):
            raise
        raise InputError(f"cannot read lines: {e}", path) from e
    arr = np.asarray(arr, dtype=np.float64)
    if arr.size == 0:
        arr = arr.reshape(0, 4)
    if arr.ndim == 3 and arr.shape[1:] == (2, 2):
        arr = arr.reshape(-1, 4)
    if arr.ndim != 2 or arr.shape[1] < 4:
        raise InputError(f"lines must be an N x 4 array (x1, y1, x2, y2), got shape {arr.shape}", path)
    lines = arr[:, :4] + pixel_offset
    if scores is None or len(scores) != len(lines):
        scores = np.hypot(lines[:, 2] - lines[:, 0], lines[:, 3] - lines[:, 1])
    return lines, np.asarray(scores, dtype=np.float64).reshape(-1)


def _find_line_file(source: Path, name: str) -> Optional[Path]:
    stem_rel = Path(name).with_suffix("").as_posix()
    bases = [name, stem_rel, Path(name).name, Path(name).stem, stem_rel.replace("/", "-"), name.replace("/", "-")]
    cands = [source / (b + ext) for ext in (".json", ".npz", ".npy", ".txt") for b in bases]
    for c in cands:
        if c.is_file():
            return c
    return None


def _read_any(path: Path, name, size, min_score, offset):
    if path.suffix.lower() == ".json":
        return read_wireframe_json(path, size, min_score, offset)
    return read_lines_array(path, name, offset)


def import_lines(
    images: Sequence,
    source,
    out_h5,
    pixel_offset: Optional[float] = None,
    min_score: float = 0.0,
    min_length: float = 0.0,
    max_lines: int = 0,
    overwrite: bool = False,
    detector_name: str = "imported",
) -> Path:
    """Import 2D lines detected elsewhere into ``lines2d.h5``.

    Args:
        images: Views (their ``name`` and camera size are used) or image names.
        source: an HDF5 file (a dataset, or a group with ``lines``, per image name), or a folder with
            one file per image: ``<name>.json`` (WireframeGraph), ``.npz``, ``.npy`` or ``.txt``,
            looked up by the full name, the name without extension, the file stem, or the name with
            '/' replaced by '-'.
        pixel_offset: added to coordinates; default 0 (COLMAP convention assumed, see module doc).
        min_score: WireframeGraph edge-weight threshold.
        min_length, max_lines: optional filtering as for detection (pixels, 0 = none).

    Returns:
        the path of ``out_h5``.
    """
    source, out_h5 = Path(source), Path(out_h5)
    if not source.exists():
        raise InputError("line source is missing", source)
    offset = 0.0 if pixel_offset is None else float(pixel_offset)
    settings = {"source": str(source.resolve()), "pixel_offset": offset, "min_score": min_score,
                "min_length": min_length, "max_lines": max_lines}
    conf_json = json.dumps(settings, sort_keys=True)
    stamp = lines_stamp(detector_name, settings)
    done = _start(out_h5, stamp, overwrite)
    results = {}
    for im in tqdm(images, desc="import lines", disable=len(images) < 2):
        name = im.name if hasattr(im, "name") else str(im)
        if name in done:
            continue
        size = (im.camera.width, im.camera.height) if hasattr(im, "camera") else None
        if source.is_file():
            if source.suffix.lower() in (".h5", ".hdf5"):
                lines, scores = read_lines_array(source, name, offset)
            elif len(images) == 1:
                lines, scores = _read_any(source, name, size, min_score, offset)
            else:
                raise InputError(
                    "a single-image line file cannot serve several images", source,
                    hint="pass a folder with one file per image, or an HDF5 file with one entry per image",
                )
        else:
            f = _find_line_file(source, name)
            if f is None:
                raise InputError(f"no line file for image {name!r}", source, hint="expected <name>.json/.npz/.npy/.txt")
            lines, scores = _read_any(f, name, size, min_score, offset)
        lines, scores = filter_lines(lines, scores, min_length, max_lines)
        if len(lines) == 0:
            logger.warning("No lines imported for %s.", name)
        results[name] = (lines, scores)
    attrs = {"detector": detector_name, "conf": conf_json, "pixel_convention": "colmap (pixel centre at i + 0.5)",
             **stamp.h5_attrs()}
    if results or not out_h5.exists():
        _write_groups(out_h5, results, attrs)
    logger.info("Imported lines for %d images into %s.", len(results), out_h5)
    return out_h5


__all__ = [
    "LineDetectorConfig",
    "confs",
    "get_conf",
    "detect_lines_image",
    "detect_lines",
    "filter_lines",
    "load_lines",
    "list_names",
    "read_wireframe_json",
    "read_lines_array",
    "import_lines",
    "lines_stamp",
]
