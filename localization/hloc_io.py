"""hloc's files: features.h5, matches.h5, pairs, results and SfM models - the ONE I/O layer for them.

Our own built-in pipeline writes exactly these layouts, so every file it writes is an hloc file
and every hloc file can replace one of ours.

Formats (as hloc's ``extract_features.py``, ``match_features.py`` and ``utils/io.py`` write/read them):

- ``features.h5``: one group per image name (the relative path, so ``seq-01/frame-000000.color.png``
  is a nested group); datasets ``keypoints`` (N, 2) with pixel centres at INTEGER coordinates
  (OpenCV convention; hloc adds 0.5 before handing them to COLMAP), ``descriptors`` (D, N),
  ``scores`` (N,), ``image_size`` [w, h]; float arrays may be float16; ``keypoints.attrs
  ["uncertainty"]`` may exist (detection noise in pixels).
- ``matches.h5``: group ``names_to_pair(q, r)`` = ``q.replace('/', '-') + '/' + r.replace('/', '-')``
  (older files: ``'_'`` as separator, one flat group); ``matches0`` (N0,) int (hloc writes int16),
  -1 = unmatched, indexed by the FIRST image's keypoints; ``matching_scores0`` (N0,) (float16 in hloc).
  A pair may be stored in either order.
- pairs file: ``name0 name1`` per line. Results file: ``name qw qx qy qz tx ty tz``, cam_from_world.

Conventions here: every keypoint array this module RETURNS is in COLMAP pixel convention (hloc + 0.5)
and float64; descriptors are returned as (N, D) float32. Writers take the same and convert back.
"""
from __future__ import annotations

import contextlib
import shutil
from pathlib import Path
from typing import Iterable, Optional

import h5py
import numpy as np

from lipmap.errors import InputError
from lipmap.imageio import atomic_path, write_text_atomic
from lipmap.poses import qt_from_T, T_from_qt

# ----------------------------------------------------------------------------------------------
# pair naming
# ----------------------------------------------------------------------------------------------


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's matches.h5 group name of an image pair (current layout)."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def names_to_pair_old(name0: str, name1: str) -> str:
    """hloc's group name in older matches.h5 files (``'_'`` between the two names)."""
    return names_to_pair(name0, name1, separator="_")


def find_pair(hfile: h5py.File, name0: str, name1: str, path=None) -> tuple[str, bool]:
    """Group name of (name0, name1) in an open matches file and whether it is stored reversed.

    Tries the current naming in both orders, then the old one, as hloc's ``find_pair`` does.
    Raises InputError naming the file and the keys it tried.
    """
    tried = []
    for key_fn in (names_to_pair, names_to_pair_old):
        for reverse, (a, b) in ((False, (name0, name1)), (True, (name1, name0))):
            key = key_fn(a, b)
            tried.append(key)
            if key in hfile and isinstance(hfile[key], h5py.Group):
                return key, reverse
    raise InputError(
        f"no matches for the pair ({name0}, {name1}); tried groups {tried}",
        path or hfile.filename,
        "was it matched with a different pairs file?",
    )


# ----------------------------------------------------------------------------------------------
# features.h5
# ----------------------------------------------------------------------------------------------


def open_h5(path, mode: str = "r") -> h5py.File:
    path = Path(path)
    if mode == "r" and not path.exists():
        raise InputError("HDF5 file is missing", path)
    try:
        return h5py.File(str(path), mode)
    except OSError as e:
        raise InputError(f"cannot open as HDF5: {e}", path) from None


@contextlib.contextmanager
def h5_update(path, fresh: bool = False):
    """Open an HDF5 artifact for adding items, atomically: a copy is edited and renamed on success.

    A run killed mid-write leaves the previous file intact (hloc appends in place and can leave a
    corrupt file behind). ``fresh`` starts an empty file instead of copying the existing one.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.exists() and not fresh:
            shutil.copyfile(path, tmp)
            mode = "a"
        else:
            mode = "w"
        with h5py.File(str(tmp), mode) as fd:
            yield fd


def list_h5_names(path) -> list[str]:
    """Names of the groups that hold datasets (image names in features.h5), sorted."""
    names = set()
    with open_h5(path) as fd:

        def visit(_, obj):
            if isinstance(obj, h5py.Dataset):
                names.add(obj.parent.name.strip("/"))

        fd.visititems(visit)
    return sorted(names)


def _dataset(grp_or_file, key: str, path, what: str) -> h5py.Dataset:
    if key not in grp_or_file:
        raise InputError(f"{what}: missing dataset {key!r}", path)
    ds = grp_or_file[key]
    if not isinstance(ds, h5py.Dataset):
        raise InputError(f"{what}: {key!r} is a group, expected a dataset", path)
    return ds


def _numeric(arr: np.ndarray, path, what: str, integer: bool = False) -> np.ndarray:
    kind = arr.dtype.kind
    ok = "iu" if integer else "iuf"
    if kind not in ok:
        want = "an integer" if integer else "a numeric"
        raise InputError(f"{what} must have {want} dtype, got {arr.dtype}", path)
    return arr


def _image_group(fd: h5py.File, name: str, path) -> h5py.Group:
    if name not in fd or not isinstance(fd[name], h5py.Group):
        raise InputError(f"image {name!r} has no group in the features file", path)
    return fd[name]


def read_keypoints(path, name: str, return_uncertainty: bool = False):
    """Keypoints of image ``name`` from an hloc features file.

    Returns:
        **keypoints** (N, 2) float64 in COLMAP convention (the file's values + 0.5), and with
        ``return_uncertainty`` also the ``uncertainty`` attribute (float or None).
    """
    with open_h5(path) as fd:
        return _read_keypoints(fd, name, path, return_uncertainty)


def _read_keypoints(fd, name, path, return_uncertainty=False):
    grp = _image_group(fd, name, path)
    ds = _dataset(grp, "keypoints", path, f"image {name!r}")
    kp = _numeric(ds[()], path, f"{name}/keypoints")
    if kp.ndim != 2 or kp.shape[1] != 2:
        raise InputError(f"{name}/keypoints must have shape (N, 2), got {kp.shape}", path)
    kp = kp.astype(np.float64) + 0.5  # hloc/OpenCV origin -> COLMAP origin
    if not np.all(np.isfinite(kp)):
        raise InputError(f"{name}/keypoints contains NaN or infinite values", path)
    if return_uncertainty:
        u = ds.attrs.get("uncertainty")
        return kp, (None if u is None else float(np.asarray(u).reshape(-1)[0]))
    return kp


def read_features(path, name: str) -> dict:
    """All of an image's features: keypoints (N, 2) COLMAP convention float64, descriptors (N, D)
    float32 (the file stores D x N), scores (N,) float32 or None, image_size (w, h) or None,
    uncertainty float or None."""
    with open_h5(path) as fd:
        kp, unc = _read_keypoints(fd, name, path, return_uncertainty=True)
        grp = fd[name]
        desc = _numeric(_dataset(grp, "descriptors", path, f"image {name!r}")[()], path, f"{name}/descriptors")
        if desc.ndim != 2 or desc.shape[1] != len(kp):
            raise InputError(
                f"{name}/descriptors must have shape (D, N) with N = {len(kp)} keypoints, got {desc.shape}", path
            )
        scores = None
        if "scores" in grp:
            scores = _numeric(grp["scores"][()], path, f"{name}/scores").astype(np.float32).reshape(-1)
            if len(scores) != len(kp):
                raise InputError(f"{name}/scores has {len(scores)} values for {len(kp)} keypoints", path)
        size = None
        if "image_size" in grp:
            size = tuple(int(v) for v in _numeric(grp["image_size"][()], path, f"{name}/image_size").reshape(-1))
            if len(size) != 2:
                raise InputError(f"{name}/image_size must be [w, h], got {size}", path)
    return {
        "keypoints": kp,
        "descriptors": np.ascontiguousarray(desc.T.astype(np.float32)),
        "scores": scores,
        "image_size": size,
        "uncertainty": unc,
    }


def write_features(
    fd: h5py.File,
    name: str,
    keypoints: np.ndarray,
    descriptors: np.ndarray,
    scores: Optional[np.ndarray] = None,
    image_size: Optional[tuple] = None,
    uncertainty: Optional[float] = None,
    extra: Optional[dict] = None,
    as_half: bool = False,
):
    """Write one image's features into an open features file in hloc's layout.

    Args:
        keypoints: (N, 2) COLMAP convention (stored minus 0.5, hloc/OpenCV convention).
        descriptors: (N, D) (stored transposed, D x N; float16 kept, anything else as float32).
        scores: (N,); image_size: (w, h); uncertainty: pixels, stored as keypoints.attrs.
        extra: more per-image datasets (e.g. SIFT ``scales``, ``oris``).
        as_half: store float arrays as float16, like hloc's default.
    """
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2:  # reshape(0, -1) cannot infer D for an image without features
        descriptors = descriptors.reshape(len(keypoints), -1)
    # float16 descriptors stay float16 (lossless for SIFT, which COLMAP quantises to uint8 / 512)
    desc_dtype = np.float16 if descriptors.dtype == np.float16 else np.float32
    data = {"keypoints": (keypoints - 0.5).astype(np.float32), "descriptors": descriptors.T.astype(desc_dtype)}
    if scores is not None:
        data["scores"] = np.asarray(scores, dtype=np.float32).reshape(-1)
    if image_size is not None:
        data["image_size"] = np.asarray(image_size, dtype=np.int64).reshape(2)
    for k, v in (extra or {}).items():
        data[k] = np.asarray(v)
    if as_half:
        data = {k: (v.astype(np.float16) if v.dtype == np.float32 else v) for k, v in data.items()}
    if name in fd:
        del fd[name]
    grp = fd.create_group(name)
    for k, v in data.items():
        grp.create_dataset(k, data=v)
    if uncertainty is not None:
        grp["keypoints"].attrs["uncertainty"] = float(uncertainty)


# ----------------------------------------------------------------------------------------------
# matches.h5
# ----------------------------------------------------------------------------------------------


def read_matches(path, name0: str, name1: str) -> tuple[np.ndarray, np.ndarray]:
    """Matches between two images, whichever order and naming the file uses.

    Returns:
        **matches** (M, 2) int64 (keypoint index in name0, keypoint index in name1) and
        **scores** (M,) float32 (ones if the file has no ``matching_scores0``).
    """
    with open_h5(path) as fd:
        return read_matches_from(fd, name0, name1, path)


def read_matches_from(fd, name0, name1, path):
    key, reverse = find_pair(fd, name0, name1, path)
    grp = fd[key]
    m0 = _numeric(_dataset(grp, "matches0", path, f"pair {key!r}")[()], path, f"{key}/matches0", integer=True)
    m0 = m0.astype(np.int64).reshape(-1)
    if "matching_scores0" in grp:
        s0 = _numeric(grp["matching_scores0"][()], path, f"{key}/matching_scores0").astype(np.float32).reshape(-1)
        if len(s0) != len(m0):
            raise InputError(f"{key}: matching_scores0 has {len(s0)} values, matches0 has {len(m0)}", path)
    else:
        s0 = np.ones(len(m0), np.float32)
    if np.any(m0 < -1):
        raise InputError(f"{key}/matches0 holds negative indices other than -1", path)
    idx = np.flatnonzero(m0 > -1)
    matches = np.stack([idx, m0[idx]], -1)
    if reverse:
        matches = matches[:, ::-1]
    return np.ascontiguousarray(matches), s0[idx]


def write_matches(fd: h5py.File, name0: str, name1: str, matches0: np.ndarray, scores0: np.ndarray):
    """Write one pair in hloc's current layout; ``matches0`` (N0,) indexed by name0's keypoints, -1 = none."""
    key = names_to_pair(name0, name1)
    if key in fd:
        del fd[key]
    grp = fd.create_group(key)
    grp.create_dataset("matches0", data=np.asarray(matches0, dtype=np.int32))
    grp.create_dataset("matching_scores0", data=np.asarray(scores0, dtype=np.float32))


def pair_in_file(fd: h5py.File, name0: str, name1: str) -> bool:
    try:
        find_pair(fd, name0, name1)
        return True
    except InputError:
        return False


# ----------------------------------------------------------------------------------------------
# text files
# ----------------------------------------------------------------------------------------------


def read_pairs(path) -> list[tuple[str, str]]:
    """hloc pairs file -> [(name0, name1)] in file order (blank lines and '#' comments skipped)."""
    path = Path(path)
    if not path.exists():
        raise InputError("pairs file is missing", path)
    pairs = []
    for i, line in enumerate(path.read_text().splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise InputError(f"line {i + 1}: expected 'name0 name1', got {line!r}", path)
        pairs.append((parts[0], parts[1]))
    return pairs


def write_pairs(path, pairs: Iterable[tuple[str, str]]) -> Path:
    pairs = list(pairs)
    for a, b in pairs:
        if any(c.isspace() for c in a + b):
            raise InputError(f"image names with whitespace cannot go in a pairs file: {a!r} {b!r}", path)
    write_text_atomic(path, "".join(f"{a} {b}\n" for a, b in pairs))
    return Path(path)


def check_pairs_in_features(pairs: list[tuple[str, str]], features_h5, pairs_path=None):
    """InputError naming the pairs file, the line and the missing key if a paired image has no features."""
    have = set(list_h5_names(features_h5))
    for i, (a, b) in enumerate(pairs):
        for name in (a, b):
            if name not in have:
                raise InputError(
                    f"pair {i + 1} ({a} {b}): image {name!r} has no group in the features file {features_h5}",
                    pairs_path or features_h5,
                )


def pairs_by_query(pairs: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """{name0: [name1, ...]} keeping file order (hloc's ``parse_retrieval``)."""
    out: dict[str, list[str]] = {}
    for a, b in pairs:
        out.setdefault(a, []).append(b)
    return out


def write_results(path, poses: dict) -> Path:
    """hloc results file: ``name qw qx qy qz tx ty tz`` (cam_from_world) per query, sorted by name."""
    lines = []
    for name in sorted(poses):
        q, t = qt_from_T(poses[name])
        lines.append(f"{name} " + " ".join(f"{v:.10g}" for v in (*q, *t)) + "\n")
    write_text_atomic(path, "".join(lines))
    return Path(path)


def read_results(path) -> dict[str, np.ndarray]:
    """hloc results file -> {name: cam_from_world 4x4}."""
    path = Path(path)
    if not path.exists():
        raise InputError("results file is missing", path)
    out = {}
    for i, line in enumerate(path.read_text().splitlines()):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) != 8:
            raise InputError(f"line {i + 1}: expected 'name qw qx qy qz tx ty tz', got {line!r}", path)
        try:
            vals = np.array([float(v) for v in parts[1:]])
        except ValueError:
            raise InputError(f"line {i + 1}: non-numeric pose values", path) from None
        qn = np.linalg.norm(vals[:4])
        if not np.all(np.isfinite(vals)) or qn < 1e-8:
            raise InputError(f"line {i + 1}: invalid pose values", path)
        if parts[0] in out:
            raise InputError(f"line {i + 1}: query {parts[0]!r} appears twice", path)
        out[parts[0]] = T_from_qt(vals[:4] / qn, vals[4:])
    return out


# ----------------------------------------------------------------------------------------------
# SfM model
# ----------------------------------------------------------------------------------------------


def read_sfm(sfm_dir):
    """A COLMAP model folder (binary or text) as a pycolmap.Reconstruction."""
    import pycolmap

    sfm_dir = Path(sfm_dir)
    if not sfm_dir.is_dir():
        raise InputError("SfM model folder is missing", sfm_dir)
    if not any((sfm_dir / f"images.{ext}").exists() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model: no images.bin / images.txt", sfm_dir)
    try:
        return pycolmap.Reconstruction(str(sfm_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on corrupt files
        hint = None
        if "point3D_id" in str(e):  # hloc's create_reference_sfm drops images from tracks but not their 2D indices
            hint = ("a track names 2D points of images the model no longer has, as in hloc's sfm_sift, which pycolmap 4 "
                    "refuses; localize from the model triangulated from the features (e.g. sfm_superpoint+superglue)")
        raise InputError(f"cannot read the COLMAP model: {str(e).strip().splitlines()[-1][:300]}", sfm_dir, hint) from None


class ModelIndex:
    """Per-image keypoint -> 3D point id lookups and the 3D points of a reconstruction, cached.

    Reading ``image.points2D`` through pycolmap is slow per keypoint; a localization run asks for
    the same database images again and again, so each image's table is built once.
    """

    def __init__(self, reconstruction, path=None):
        self.rec = reconstruction
        self.path = path
        self._by_name = {im.name: im_id for im_id, im in reconstruction.images.items()}
        self._ids: dict[str, np.ndarray] = {}
        self._xyz: dict[int, np.ndarray] = {}

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def image_names(self) -> list[str]:
        return sorted(self._by_name)

    def point3D_ids(self, name: str) -> np.ndarray:
        """(N,) int64 3D point id of each keypoint of image ``name``, -1 where none."""
        if name not in self._ids:
            if name not in self._by_name:
                raise InputError(f"image {name!r} is not in the SfM model", self.path)
            image = self.rec.images[self._by_name[name]]
            ids = np.full(image.num_points2D(), -1, dtype=np.int64)
            for idx in image.get_observation_point2D_idxs():
                ids[idx] = image.points2D[idx].point3D_id
            self._ids[name] = ids
        return self._ids[name]

    def num_points2D(self, name: str) -> int:
        """Number of 2D points (keypoints, observed or not) of image ``name`` in the model."""
        if name not in self._by_name:
            raise InputError(f"image {name!r} is not in the SfM model", self.path)
        return int(self.rec.images[self._by_name[name]].num_points2D())

    def cam_from_world(self, name: str) -> np.ndarray:
        """(4, 4) pose of image ``name`` in the model (a starting pose for the line query of a weak query)."""
        if name not in self._by_name:
            raise InputError(f"image {name!r} is not in the SfM model", self.path)
        T = np.eye(4)
        T[:3] = np.asarray(self.rec.images[self._by_name[name]].cam_from_world().matrix(), dtype=float)
        return T

    def xyz(self, point3D_ids: np.ndarray) -> np.ndarray:
        """(M, 3) world coordinates of 3D point ids."""
        out = np.empty((len(point3D_ids), 3))
        for i, pid in enumerate(np.asarray(point3D_ids).tolist()):
            if pid not in self._xyz:
                self._xyz[pid] = np.asarray(self.rec.points3D[pid].xyz, dtype=float)
            out[i] = self._xyz[pid]
        return out
