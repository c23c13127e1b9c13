"""Plane I/O: ``planes.h5`` (HDF5, atomic write) and a planar-mesh PLY any viewer opens."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import h5py
import numpy as np
import torch

from ..errors import InputError
from ..imageio import atomic_path
from .primitives import Planes, triangle_mesh

FORMAT_VERSION = 1


def save_planes(path, planes: Planes, attrs: Optional[dict] = None, stamp=None) -> Path:
    """Write ``planes`` to HDF5: datasets ``center`` (K,3), ``quat`` (K,4, wxyz), ``radii`` (K,4, x+ x- y+ y-).

    ``attrs`` (e.g. the optimisation config and history) is stored as JSON in the file attribute
    ``meta``; ``stamp`` (:class:`lipmap.artifacts.Stamp`) records the settings that made the planes.
    The write is atomic: a killed run never leaves a half-written file.
    """
    path = Path(path)
    arrays = planes.numpy()
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, v in arrays.items():
                f.create_dataset(k, data=v.astype(np.float32))
            f.attrs["format"] = "lipmap-planes"
            f.attrs["version"] = FORMAT_VERSION
            f.attrs["meta"] = json.dumps(attrs or {}, default=str)
            for k, v in (stamp.h5_attrs() if stamp is not None else {}).items():
                f.attrs[k] = v
    return path


def load_planes(path, device=None, dtype=torch.float32) -> Planes:
    """Read a file written by :func:`save_planes`."""
    path = Path(path)
    if not path.exists():
        raise InputError("planes file is missing", path)
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("center", "quat", "radii") if k not in f]
            if missing:
                raise InputError(f"not a planes file: datasets {missing} missing", path)
            arrays = {k: np.asarray(f[k]) for k in ("center", "quat", "radii")}
    except OSError as e:
        raise InputError(f"cannot read HDF5 ({e})", path) from e
    try:
        return Planes(*(torch.as_tensor(arrays[k], dtype=dtype, device=device) for k in ("center", "quat", "radii")))
    except InputError as e:
        raise InputError(e.problem, path) from e


def load_planes_meta(path) -> dict:
    with h5py.File(path, "r") as f:
        return json.loads(f.attrs.get("meta", "{}"))


def export_planes_ply(path, planes: Planes, colors: Optional[np.ndarray] = None) -> Path:
    """Planar mesh PLY (binary; two triangles per plane, 4 vertices per plane).

    Faces are coloured by their normal ((n + 1) / 2) unless ``colors`` (K, 3) uint8 is given.
    """
    import trimesh

    V, F = triangle_mesh(planes)
    if colors is None:
        with torch.no_grad():
            n = planes.normal.detach().cpu().numpy()
        colors = np.clip((n + 1.0) * 127.5, 0, 255).astype(np.uint8)
    colors = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    face_colors = np.repeat(np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], 1), 2, axis=0)
    mesh = trimesh.Trimesh(vertices=V, faces=F, face_colors=face_colors, process=False)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
    return path
