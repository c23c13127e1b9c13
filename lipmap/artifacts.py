"""Artifacts that know what made them: a stamp (step name + settings + digest) stored with each cached
file, and the one rule for reusing it.

A step that finds its artifact reuses it only when the stamp's digest equals the digest of the current
settings and inputs; an artifact made otherwise, or with no stamp, is never reused silently: the step
stops with a :class:`StaleArtifactError` that names both settings, unless asked to overwrite. Pipelines
that may hold several variants side by side (``lipmap-loc eval`` with ``--method lift`` and then
``lipmap`` into one OUT) put each in its own folder named by the digest (:func:`variant_dir`).

Where the stamp lives: HDF5 files carry it in the root attribute ``lipmap_stamp`` (written in the same
atomic write as the data, see :meth:`Stamp.h5_attrs`); other files and folders in a sidecar
``<name>.stamp.json`` (a folder: ``<folder>/lipmap-stamp.json``).
"""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tokenize
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from . import logger
from .errors import InputError

STAMP_ATTR = "lipmap_stamp"


def canonical_json(obj) -> str:
    """Deterministic JSON of settings: sorted keys, paths and other objects as strings."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def digest(obj, n: int = 12) -> str:
    """Short sha256 of :func:`canonical_json` of ``obj``."""
    return hashlib.sha256(canonical_json(obj).encode()).hexdigest()[:n]


def _canonical_bytes(a) -> bytes:
    # rounded, and -0.0 made 0.0: the same pose read or computed twice must give the same bytes
    return (np.round(np.asarray(a, dtype=np.float64), 9) + 0.0).tobytes()


def views_key(views) -> dict:
    """What a step reads from a list of views besides their files: names, cameras, poses, depth sensor.

    Poses are rounded to 1e-9 so that a reload of the same pose files gives the same key.
    """
    h = hashlib.sha256()
    for v in views:
        h.update(v.name.encode())
        h.update(canonical_json(list(v.camera.params) + [v.camera.width, v.camera.height]).encode())
        if v.cam_from_world is not None:
            h.update(_canonical_bytes(v.cam_from_world))
        if getattr(v, "depth_camera", None) is not None:
            h.update(canonical_json(list(v.depth_camera.params)).encode())
        if getattr(v, "color_from_depth", None) is not None:
            h.update(_canonical_bytes(v.color_from_depth))
    return {"n": len(views), "sha": h.hexdigest()[:16]}


def scene_key(scene, views=None) -> dict:
    """The inputs of a step that reads ``views`` (default: the mapping views) of ``scene``: the scene's
    identity, its pose source and depth handling, its metadata (a synthetic scene's preset) and the views."""
    # where the pose lists lie and how the focal is described are not inputs: the views' poses and cameras are
    meta = {k: v for k, v in (scene.meta or {}).items() if k not in ("skipped_frames", "pgt_files", "focal_source")}
    return {
        "dataset": scene.dataset,
        "scene": scene.name,
        "pose_source": scene.pose_source,
        "depth_registered": bool(scene.depth_registered),
        "meta": digest(meta),
        "views": views_key(scene.mapping if views is None else views),
    }


# the modules whose code makes a line map (and its planes): a map made by other code is not reused. Viewers,
# evaluation and the artifact plumbing are left out, so changing them keeps the maps
MAPPING_CODE = ("mapping", "planes", "datasets", "lines2d.py", "lift.py", "linemap.py", "geometry.py", "normals.py",
                "frames.py", "imageio.py", "poses.py", "scene.py", "presets.py")


# the part of it that shapes planes.h5: the plane optimization, the line term and what they import, and the code that
# reads their inputs (scenes, frames, depth, 2D lines). tests/test_artifacts.py checks that it holds every lipmap
# module the plane step imports, so that a plane dependency left out cannot let stale planes be reused
PLANES_CODE = ("planes", "mapping/joint.py", "mapping/supervision.py", "mapping/assign.py", "mapping/losses.py",
               "mapping/depth_lookup.py", "mapping/keyframes.py", "datasets", "lines2d.py", "geometry.py", "normals.py",
               "frames.py", "imageio.py", "poses.py", "scene.py", "presets.py")


def _covered(rel: Path, only: tuple) -> bool:
    """Whether ``rel`` (a path inside a package) is one of, or lies in one of, the entries ``only``."""
    return any(rel.parts[: len(Path(e).parts)] == Path(e).parts for e in only)


def code_tokens(source: bytes) -> bytes:
    """What of a Python file can change what it does: its tokens without comments, blank lines and docstrings
    (a string that is a statement of its own), so that editing prose does not discard artifacts that took hours.
    A file that does not tokenize is taken byte for byte."""
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.ENCODING}
    try:
        toks = [t for t in tokenize.tokenize(io.BytesIO(source).readline) if t.type not in skip]
    except (tokenize.TokenError, SyntaxError):
        return source
    starts = {tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT}
    out, drop = [], set()
    for i, t in enumerate(toks):
        prev = toks[i - 1].type if i else tokenize.NEWLINE
        nxt = toks[i + 1].type if i + 1 < len(toks) else tokenize.NEWLINE
        if t.type == tokenize.STRING and prev in starts and nxt in (tokenize.NEWLINE, tokenize.ENDMARKER):
            drop |= {i, i + 1}  # a docstring, and the end of its line
        if i not in drop:
            out.append(f"{t.type}:{t.string}")
    return "\n".join(out).encode()


def source_digest(packages, only: Optional[tuple] = None) -> str:
    """Digest of the ``.py`` files (relative path and :func:`code_tokens`) of ``packages`` (folders), restricted to
    the entries ``only`` (folders or files, relative to the package: ``"planes"``, ``"mapping/joint.py"``) when
    given."""
    h = hashlib.sha256()
    for pkg in packages:
        pkg = Path(pkg)
        for f in sorted(pkg.rglob("*.py")):
            rel = f.relative_to(pkg)
            if only is not None and not _covered(rel, only):
                continue
            h.update(f"{pkg.name}/{rel.as_posix()}".encode())
            h.update(code_tokens(f.read_bytes()))
    return h.hexdigest()[:12]


def mapping_code_digest() -> str:
    """:func:`source_digest` of the ``lipmap`` modules in :data:`MAPPING_CODE`."""
    return source_digest([Path(__file__).parent], MAPPING_CODE)


def planes_code_digest() -> str:
    """:func:`source_digest` of the ``lipmap`` modules in :data:`PLANES_CODE`."""
    return source_digest([Path(__file__).parent], PLANES_CODE)


@dataclass(frozen=True)
class Stamp:
    """``step`` name and the JSON-able ``settings`` (including input keys) that made an artifact."""

    step: str
    settings: dict

    @property
    def digest(self) -> str:
        return digest({"step": self.step, "settings": self.settings})

    def to_json(self) -> str:
        return json.dumps({"step": self.step, "digest": self.digest, "settings": json.loads(canonical_json(self.settings))},
                          sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "Stamp":
        d = json.loads(text)
        return cls(d["step"], d["settings"])

    def h5_attrs(self) -> dict:
        """Root attributes to write with an HDF5 artifact (in the same atomic write)."""
        return {STAMP_ATTR: self.to_json()}


def _sidecar(path: Path) -> Path:
    # a folder (a COLMAP model) carries its stamp inside, so that it moves and globs as one thing
    return path / "lipmap-stamp.json" if path.is_dir() else path.parent / (path.name + ".stamp.json")


def _is_h5(path: Path) -> bool:
    return path.suffix in (".h5", ".hdf5")


def read_stamp(path) -> Optional[Stamp]:
    """The stamp of ``path`` (None when it has none or it is unreadable)."""
    path = Path(path)
    try:
        if _is_h5(path) and path.is_file():
            import h5py

            with h5py.File(path, "r") as f:
                text = f.attrs.get(STAMP_ATTR)
            return None if text is None else Stamp.from_json(text)
        side = _sidecar(path)
        return Stamp.from_json(side.read_text()) if side.exists() else None
    except (OSError, ValueError, KeyError):
        return None


def write_stamp(path, stamp: Stamp) -> None:
    """Stamp an artifact already written: an HDF5 attribute, else the sidecar file (atomic)."""
    from .imageio import write_text_atomic

    path = Path(path)
    if _is_h5(path):
        import h5py

        with h5py.File(path, "a") as f:
            f.attrs[STAMP_ATTR] = stamp.to_json()
    else:
        write_text_atomic(_sidecar(path), stamp.to_json())


def remove(path) -> None:
    """Delete an artifact (file or folder) and its sidecar stamp."""
    path = Path(path)
    if path.is_dir():
        shutil.rmtree(path)
        return
    if path.exists():
        path.unlink()
    side = _sidecar(path)
    if side.exists():
        side.unlink()


class StaleArtifactError(InputError):
    """An artifact exists that other settings made (or whose settings are unknown)."""


def _diff(a, b, path: str = "") -> list:
    """(path, old, new) for each differing leaf; a subtree present on one side only is one entry."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            sub = f"{path}.{k}" if path else str(k)
            if k not in a or k not in b:
                out.append((sub, a.get(k, "<unset>"), b.get(k, "<unset>")))
            else:
                out += _diff(a[k], b[k], sub)
        return out
    return [] if a == b else [(path, a, b)]


def _short(v) -> str:
    text = repr(v) if not isinstance(v, dict) else "{...}"
    return text if len(text) <= 40 else text[:37] + "..."


def describe_difference(old: Stamp, new: Stamp, limit: int = 6) -> str:
    """``key: old -> new`` for the settings that differ, shallowest first (at most ``limit`` of them)."""
    if old.step != new.step:
        return f"step {old.step!r} -> {new.step!r}"
    diffs = _diff(json.loads(canonical_json(old.settings)), json.loads(canonical_json(new.settings)))
    diffs.sort(key=lambda d: (d[0].count("."), d[0]))
    parts = [f"{k}: {_short(a)} -> {_short(b)}" for k, a, b in diffs[:limit]]
    if len(diffs) > limit:
        parts.append(f"and {len(diffs) - limit} more")
    return "; ".join(parts) or "same settings, other lipmap version"


def reuse(path, stamp: Stamp, overwrite: bool = False, what: str = "", replace_stale: bool = False) -> bool:
    """The reuse rule. True: ``path`` exists and ``stamp`` made it - skip the work (or resume it).

    False: there is nothing to reuse (missing, or removed because ``overwrite``). Raises
    :class:`StaleArtifactError` naming both settings when it exists but was made otherwise.
    ``replace_stale``: an artifact made otherwise (or with no stamp) is removed and made again instead;
    for cheap steps whose artifact is a pure function of the stamped inputs, and for artifacts stamped
    after they are written (no stamp there means an interrupted step).
    """
    path = Path(path)
    if not path.exists():
        if _sidecar(path).exists():
            _sidecar(path).unlink()
        return False
    old = read_stamp(path)
    if old is not None and old.digest == stamp.digest and not overwrite:
        logger.info("Reusing %s: %s was made with the same settings (%s).", what or stamp.step, path, stamp.digest)
        return True
    if overwrite or replace_stale:
        if not overwrite:
            logger.info("%s: %s was made with other settings; making it again.", what or stamp.step, path)
        remove(path)
        return False
    if old is None:
        problem = f"exists with no record of the settings that made it; it is not reused for {stamp.step} ({stamp.digest})"
    else:
        problem = (f"was made by {old.step} with other settings ({old.digest}) than asked now ({stamp.digest}): "
                   f"{describe_difference(old, stamp)}")
    raise StaleArtifactError(problem, path, hint="pass --overwrite (overwrite=True) or another output folder")


def variant_dir(parent, label: str, stamp: Stamp) -> Path:
    """``parent/<label>-<digest[:8]>``: the folder of one variant, so that variants made with other settings
    (``map-lift-fast-…`` and ``map-lipmap-fast-…``) coexist instead of replacing or impersonating each other."""
    return Path(parent) / f"{label}-{stamp.digest[:8]}"
