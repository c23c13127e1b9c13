"""The ``LineMap`` artifact: 3D line segments, their 2D tracks, support counts and optional planes.

``linemap.h5`` layout (flat arrays with offsets, so thousands of tracks load in one read each):

    lines               (N, 2, 3) float64   3D segments, metres, world frame
    supports            (N, 2)    int32     per line: number of images, number of 2D lines
    tracks/offsets      (N + 1,)  int64     observations of line i: rows offsets[i]:offsets[i+1]
    tracks/image_index  (T,)      int32     index into tracks/image_names
    tracks/image_names  (K,)      str       image names (hloc-style relative paths)
    tracks/line_index   (T,)      int32     index of the 2D line in that image's lines2d.h5 entry
    tracks/segments     (T, 4)    float64   the 2D segment x1 y1 x2 y2 (COLMAP pixel convention)
    planes/<key>                            optional planar primitives, stored as given
                                            (center (K,3), rotation wxyz (K,4), radii (K,4), ...)
    attrs: format="lipmap.linemap", version=1, metadata=<JSON>

LIMAP export (``to_limap``) writes ``<folder>/finaltracks/track_<i>.txt`` exactly as LIMAP's
``LineTrack::Write`` (cvg/limap, limap/base/linetrack.cc):

    x1 y1 z1 x2 y2 z2                 3D start and end
    n_lines n_images                  n_images = number of distinct image ids
    image_id_list id_0 ... id_{n-1}
    line_id_list l_0 ... l_{n-1}
    line2d_list
    x1 y1 x2 y2                       one row per observation
    END

plus ``<folder>/image_list.txt`` in LIMAP's ``save_txt_imname_list`` format (first line
``number of images, K``, then one image name per line): image id k is the k-th name (0-based).
2D segments are written in our COLMAP pixel convention (LIMAP takes them as given; its projection
uses the same intrinsics, so with COLMAP-convention intrinsics they agree).
"""
from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Optional, Sequence, Union

import h5py
import numpy as np

from . import logger
from .errors import InputError
from .imageio import atomic_path

FORMAT = "lipmap.linemap"
VERSION = 1


class Observation(NamedTuple):
    """One 2D support of a 3D line: the image, the 2D line's index in that image, the 2D segment."""

    image_name: str
    line2d_index: int
    segment: np.ndarray  # (4,) x1 y1 x2 y2


def _supports_from_tracks(tracks) -> np.ndarray:
    return np.array([[len({o[0] for o in t}), len(t)] for t in tracks], dtype=np.int32).reshape(-1, 2)


@dataclass
class LineMap:
    """3D lines (N, 2, 3) with one track (list of :class:`Observation`) per line.

    ``supports`` (N, 2) = (n_images, n_lines) per line; computed from the tracks when not given
    (a method may give larger counts than the kept track, e.g. before track filtering).
    ``planes``: optional dict of arrays describing planar primitives (stored as given).
    ``metadata``: JSON-serialisable dict (method, config, ...).
    """

    lines: np.ndarray
    tracks: list = None
    supports: Optional[np.ndarray] = None
    planes: Optional[dict] = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        self.lines = np.asarray(self.lines, dtype=np.float64)
        if self.lines.size == 0:
            self.lines = self.lines.reshape(0, 2, 3)
        if self.lines.ndim != 3 or self.lines.shape[1:] != (2, 3):
            raise InputError(f"LineMap lines must be (N, 2, 3), got {self.lines.shape}")
        n = len(self.lines)
        if self.tracks is None:
            self.tracks = [[] for _ in range(n)]
        if len(self.tracks) != n:
            raise InputError(f"LineMap has {n} lines but {len(self.tracks)} tracks")
        self.tracks = [
            [Observation(str(o[0]), int(o[1]), np.asarray(o[2], dtype=np.float64).reshape(4)) for o in t]
            for t in self.tracks
        ]
        if self.supports is None:
            self.supports = _supports_from_tracks(self.tracks)
        self.supports = np.asarray(self.supports, dtype=np.int32).reshape(-1, 2)
        if len(self.supports) != n:
            raise InputError(f"LineMap has {n} lines but {len(self.supports)} support rows")
        if self.planes is not None:
            self.planes = {k: np.asarray(v) for k, v in self.planes.items()}

    def __len__(self) -> int:
        return len(self.lines)

    @property
    def lengths(self) -> np.ndarray:
        return np.linalg.norm(self.lines[:, 1] - self.lines[:, 0], axis=-1)

    def image_names(self) -> list:
        """Sorted distinct image names over all tracks."""
        return sorted({o.image_name for t in self.tracks for o in t})

    def subset(self, index) -> "LineMap":
        """A LineMap of the selected lines (bool mask or integer indices); planes are kept."""
        idx = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=int)
        planes = self.planes
        if planes is not None and "edge_line" in planes:
            # the plane-edge -> line table (used by the raycast line query) follows the renumbering
            new_id = np.full(len(self), -1, dtype=np.int64)
            new_id[idx] = np.arange(len(idx))
            el = np.asarray(planes["edge_line"])
            planes = {**planes, "edge_line": np.where(el >= 0, new_id[np.clip(el, 0, None)], -1)}
        return LineMap(self.lines[idx], [self.tracks[i] for i in idx], self.supports[idx], planes, dict(self.metadata))

    # ------------------------------------------------------------------------------------------
    # HDF5
    # ------------------------------------------------------------------------------------------
    def save(self, path, stamp=None) -> Path:
        """Write ``linemap.h5`` atomically (see the module docstring for the layout); ``stamp``
        (:class:`lipmap.artifacts.Stamp`) records the settings and inputs that made the map."""
        path = Path(path)
        names = self.image_names()
        name_id = {n: i for i, n in enumerate(names)}
        counts = np.array([len(t) for t in self.tracks], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        obs = [o for t in self.tracks for o in t]
        image_index = np.array([name_id[o.image_name] for o in obs], dtype=np.int32)
        line_index = np.array([o.line2d_index for o in obs], dtype=np.int32)
        segments = np.array([o.segment for o in obs], dtype=np.float64).reshape(-1, 4)
        with atomic_path(path) as tmp:
            with h5py.File(tmp, "w") as f:
                f.attrs["format"] = FORMAT
                f.attrs["version"] = VERSION
                f.attrs["metadata"] = json.dumps(self.metadata, default=_json_default)
                for k, v in (stamp.h5_attrs() if stamp is not None else {}).items():
                    f.attrs[k] = v
                f.create_dataset("lines", data=self.lines)
                f.create_dataset("supports", data=self.supports)
                g = f.create_group("tracks")
                g.create_dataset("offsets", data=offsets)
                g.create_dataset("image_index", data=image_index)
                g.create_dataset("image_names", data=np.array(names, dtype=object), dtype=h5py.string_dtype())
                g.create_dataset("line_index", data=line_index)
                g.create_dataset("segments", data=segments)
                if self.planes is not None:
                    gp = f.create_group("planes")
                    for k, v in self.planes.items():
                        gp.create_dataset(k, data=v)
        return path

    @classmethod
    def load(cls, path) -> "LineMap":
        """Read a ``linemap.h5`` written by :meth:`save`."""
        path = Path(path)
        if not path.exists():
            raise InputError("line map file is missing", path)
        try:
            with h5py.File(path, "r") as f:
                if f.attrs.get("format") != FORMAT:
                    raise InputError(f"not a lipmap line map (format attribute {f.attrs.get('format')!r})", path)
                for key in ("lines", "supports", "tracks/offsets", "tracks/image_index", "tracks/image_names",
                            "tracks/line_index", "tracks/segments"):
                    if key not in f:
                        raise InputError(f"line map lacks the dataset {key!r}", path)
                lines = f["lines"][()]
                supports = f["supports"][()]
                offsets = f["tracks/offsets"][()]
                image_index = f["tracks/image_index"][()]
                names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["tracks/image_names"][()]]
                line_index = f["tracks/line_index"][()]
                segments = f["tracks/segments"][()].reshape(-1, 4)
                planes = {k: f["planes"][k][()] for k in f["planes"]} if "planes" in f else None
                metadata = json.loads(f.attrs.get("metadata", "{}"))
        except OSError as e:
            raise InputError(f"cannot read line map: {e}", path) from e
        n = len(lines)
        T = len(image_index)
        if len(offsets) != n + 1 or offsets[0] != 0 or offsets[-1] != T or np.any(np.diff(offsets) < 0):
            raise InputError(f"inconsistent track offsets for {n} lines and {T} observations", path)
        if len(line_index) != T or len(segments) != T:
            raise InputError("track arrays have different lengths", path)
        if T and (image_index.min() < 0 or image_index.max() >= len(names)):
            raise InputError("track image index out of range", path)
        tracks = [
            [Observation(names[image_index[k]], int(line_index[k]), segments[k]) for k in range(offsets[i], offsets[i + 1])]
            for i in range(n)
        ]
        return cls(lines, tracks, supports, planes, metadata)

    # ------------------------------------------------------------------------------------------
    # PLY
    # ------------------------------------------------------------------------------------------
    def to_ply(self, path, binary: bool = True) -> Path:
        """Lines as a PLY of 2N vertices and N edges (``vertex1``, ``vertex2``), readable by MeshLab,
        Open3D (``read_line_set``) and CloudCompare."""
        write_ply_lines(path, self.lines, binary=binary)
        return Path(path)

    # ------------------------------------------------------------------------------------------
    # LIMAP
    # ------------------------------------------------------------------------------------------
    def to_limap(self, folder, image_names: Optional[Sequence[str]] = None, overwrite: bool = True) -> Path:
        """Write LIMAP's ``finaltracks/track_<i>.txt`` and ``image_list.txt`` into ``folder``.

        Args:
            image_names: fixes the image ids (id = index in this list); default: sorted names of
                all tracks. Every observed image must be in it.

        Returns:
            the ``finaltracks`` folder.
        """
        folder = Path(folder)
        names = list(image_names) if image_names is not None else self.image_names()
        name_id = {n: i for i, n in enumerate(names)}
        missing = {o.image_name for t in self.tracks for o in t} - set(name_id)
        if missing:
            raise InputError(f"{len(missing)} observed images are not in image_names, e.g. {sorted(missing)[0]!r}")
        out = folder / "finaltracks"
        tmp = folder / ".finaltracks.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        for i, (line, track) in enumerate(zip(self.lines, self.tracks)):
            (tmp / f"track_{i}.txt").write_text(_limap_track_text(line, track, name_id))
        if out.exists():
            if not overwrite:
                shutil.rmtree(tmp)
                raise InputError("LIMAP track folder exists", out, hint="pass overwrite=True")
            shutil.rmtree(out)
        tmp.rename(out)
        with atomic_path(folder / "image_list.txt") as p:
            p.write_text(f"number of images, {len(names)}\n" + "".join(n + "\n" for n in names))
        logger.info("Wrote %d LIMAP tracks to %s.", len(self), out)
        return out

    @classmethod
    def from_limap(cls, folder, image_list: Union[None, str, Path, Sequence[str], dict] = None) -> "LineMap":
        """Read LIMAP line tracks.

        Args:
            folder: the ``finaltracks`` folder or its parent.
            image_list: image names by id: a file (LIMAP ``image_list.txt`` format, or one name per
                line), a list (id = index) or a dict {id: name}. Default: ``image_list.txt`` in the
                folder or its parent when present; otherwise images are named by their id ("17").

        Raises:
            InputError: naming the file and line of a malformed track.
        """
        folder = Path(folder)
        if (folder / "finaltracks").is_dir():
            folder = folder / "finaltracks"
        if not folder.is_dir():
            raise InputError("LIMAP track folder is missing", folder)
        id_to_name = _read_image_list(image_list, folder)
        files = {}
        for p in folder.iterdir():
            m = re.fullmatch(r"track_(\d+)\.txt", p.name)
            if m:
                files[int(m.group(1))] = p
        if sorted(files) != list(range(len(files))):
            raise InputError(f"track files are not numbered 0..{len(files) - 1} without gaps", folder)
        lines, tracks = [], []
        for i in range(len(files)):
            line, obs = _parse_limap_track(files[i])
            lines.append(line)
            if id_to_name is not None:
                unknown = sorted({img for img, _, _ in obs} - set(id_to_name))
                if unknown:
                    raise InputError(f"image id {unknown[0]} is not in the image list ({len(id_to_name)} names)", files[i])
            tracks.append(
                [Observation(id_to_name[img] if id_to_name is not None else str(img), lid, seg) for img, lid, seg in obs]
            )
        if id_to_name is None and tracks:
            logger.warning("No image list for %s: images are named by their LIMAP ids.", folder)
        return cls(np.array(lines).reshape(-1, 2, 3), tracks, metadata={"method": "limap-import", "source": str(folder)})


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def edge_line_mask(lm: LineMap) -> np.ndarray:
    """(N,) bool: the lines of a ``lipmap`` map that are plane edges (the paper's output), read from the
    planes' edge -> line table (``planes["edge_line"]``); the rest are detections lifted onto the planes
    (``MappingConfig.on_plane_lines``). All False for maps without that table."""
    mask = np.zeros(len(lm), dtype=bool)
    if lm.planes is not None and "edge_line" in lm.planes:
        el = np.asarray(lm.planes["edge_line"]).ravel()
        mask[el[el >= 0]] = True
    return mask


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "__dataclass_fields__"):
        from dataclasses import asdict

        return asdict(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _fmt(x: float) -> str:
    return repr(float(x))  # shortest exact float64 text: the export -> import round trip is lossless


def _limap_track_text(line: np.ndarray, track: list, name_id: dict) -> str:
    img_ids = [name_id[o.image_name] for o in track]
    rows = [" ".join(_fmt(v) for v in line.reshape(6)) + " ", f"{len(track)} {len(set(img_ids))}"]
    rows.append("image_id_list " + "".join(f"{i} " for i in img_ids))
    rows.append("line_id_list " + "".join(f"{o.line2d_index} " for o in track))
    rows.append("line2d_list")
    rows += [" ".join(_fmt(v) for v in o.segment) + " " for o in track]
    rows.append("END")
    return "\n".join(rows) + "\n"


def _parse_limap_track(path: Path):
    """One LIMAP track file -> (line (2, 3), [(image_id, line_id, segment (4,)), ...])."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read LIMAP track: {e}", path) from e
    rows = text.splitlines()
    pos = 0

    def fail(problem):
        raise InputError(f"line {pos + 1}: {problem}", path)

    def row() -> list:
        if pos >= len(rows):
            fail("unexpected end of file")
        return rows[pos].split()

    def numbers(tokens, n, kind, what):
        if len(tokens) != n:
            fail(f"expected {n} values ({what}), got {len(tokens)}")
        try:
            vals = [kind(t) for t in tokens]
        except ValueError:
            fail(f"non-numeric value in {what}: {' '.join(tokens)!r}")
        if kind is float and not np.all(np.isfinite(vals)):
            fail(f"non-finite value in {what}")
        return vals

    line = np.array(numbers(row(), 6, float, "3D start and end")).reshape(2, 3)
    pos += 1
    n_lines, n_images = numbers(row(), 2, int, "n_lines n_images")
    if n_lines < 0 or n_images < 0:
        fail("negative counts")
    pos += 1
    tok = row()
    if not tok or tok[0] != "image_id_list":
        fail("expected 'image_id_list'")
    img_ids = numbers(tok[1:], n_lines, int, "image ids")
    if len(set(img_ids)) != n_images:
        fail(f"n_images is {n_images} but the image id list has {len(set(img_ids))} distinct ids")
    pos += 1
    tok = row()
    if not tok or tok[0] != "line_id_list":
        fail("expected 'line_id_list'")
    line_ids = numbers(tok[1:], n_lines, int, "2D line ids")
    pos += 1
    segs = np.full((n_lines, 4), np.nan)
    if pos < len(rows) and rows[pos].split() == ["line2d_list"]:
        pos += 1
        for k in range(n_lines):
            segs[k] = numbers(row(), 4, float, "2D segment x1 y1 x2 y2")
            pos += 1
    elif pos < len(rows) and rows[pos].strip() != "END":
        fail("expected 'line2d_list' or 'END'")
    # optional blocks written by LIMAP (node ids, scores, per-view 3D lines) until END
    while pos < len(rows):
        tok = row()
        if not tok:
            pos += 1
            continue
        if tok[0] == "END":
            break
        if tok[0] in ("node_id_list", "score_list"):
            numbers(tok[1:], n_lines, float, tok[0])
            pos += 1
        elif tok[0] == "line3d_list":
            pos += 1
            for _ in range(n_lines):
                numbers(row(), 6, float, "per-observation 3D line")
                pos += 1
        else:
            fail(f"unexpected content {rows[pos].strip()[:40]!r}")
    return line, list(zip(img_ids, line_ids, segs))


def _read_image_list(image_list, folder: Path) -> Optional[dict]:
    if image_list is None:
        for cand in (folder / "image_list.txt", folder.parent / "image_list.txt"):
            if cand.is_file():
                image_list = cand
                break
        else:
            return None
    if isinstance(image_list, dict):
        return {int(k): str(v) for k, v in image_list.items()}
    if isinstance(image_list, (str, Path)):
        p = Path(image_list)
        if not p.is_file():
            raise InputError("image list file is missing", p)
        rows = [r.strip() for r in p.read_text().splitlines() if r.strip()]
        if rows and rows[0].startswith("number of images"):
            try:
                n = int(rows[0].split(",")[1])
            except (IndexError, ValueError):
                raise InputError("line 1: expected 'number of images, K'", p) from None
            rows = rows[1:]
            if len(rows) != n:
                raise InputError(f"header says {n} images, found {len(rows)} names", p)
        return dict(enumerate(rows))
    return dict(enumerate(str(n) for n in image_list))


def write_ply_lines(path, lines: np.ndarray, binary: bool = True, colors: Optional[np.ndarray] = None):
    """PLY with vertices (2N) and edges (N); optional per-edge uint8 RGB colours (N, 3)."""
    lines = np.asarray(lines, dtype=np.float64).reshape(-1, 2, 3)
    n = len(lines)
    verts = lines.reshape(-1, 3).astype(np.float32)
    edges = np.arange(2 * n, dtype=np.int32).reshape(-1, 2)
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"comment lipmap line map, {n} lines",
        f"element vertex {2 * n}",
        "property float x",
        "property float y",
        "property float z",
        f"element edge {n}",
        "property int vertex1",
        "property int vertex2",
    ]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8).reshape(n, 3)
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            if binary:
                f.write(verts.astype("<f4").tobytes())
                if colors is None:
                    f.write(edges.astype("<i4").tobytes())
                else:
                    rec = np.zeros(n, dtype=[("a", "<i4"), ("b", "<i4"), ("r", "u1"), ("g", "u1"), ("bl", "u1")])
                    rec["a"], rec["b"] = edges[:, 0], edges[:, 1]
                    rec["r"], rec["g"], rec["bl"] = colors.T
                    f.write(rec.tobytes())
            else:
                f.write("".join(f"{x:.7g} {y:.7g} {z:.7g}\n" for x, y, z in verts).encode())
                for k, (a, b) in enumerate(edges):
                    extra = "" if colors is None else " " + " ".join(str(int(c)) for c in colors[k])
                    f.write(f"{a} {b}{extra}\n".encode())


def read_ply_lines(path) -> np.ndarray:
    """Read back (N, 2, 3) lines from a PLY written by :func:`write_ply_lines` (float32 precision)."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path)
    header = data[:end].decode("ascii").splitlines()
    fmt = header[1].split()[1]
    nv = ne = 0
    has_color = any("uchar red" in h for h in header)
    for h in header:
        if h.startswith("element vertex"):
            nv = int(h.split()[2])
        elif h.startswith("element edge"):
            ne = int(h.split()[2])
    body = data[end + len(b"end_header\n"):]
    if fmt == "binary_little_endian":
        verts = np.frombuffer(body[: nv * 12], dtype="<f4").reshape(nv, 3)
        if has_color:
            rec = np.frombuffer(body[nv * 12:], dtype=[("a", "<i4"), ("b", "<i4"), ("c", "u1", 3)], count=ne)
            edges = np.stack([rec["a"], rec["b"]], 1)
        else:
            edges = np.frombuffer(body[nv * 12: nv * 12 + ne * 8], dtype="<i4").reshape(ne, 2)
    else:
        rows = body.decode().splitlines()
        verts = np.array([[float(x) for x in r.split()[:3]] for r in rows[:nv]]).reshape(nv, 3)
        edges = np.array([[int(x) for x in r.split()[:2]] for r in rows[nv: nv + ne]], dtype=int).reshape(ne, 2)
    return verts[edges].astype(np.float64)


def add_linemap_export_parser(subparsers):
    """`linemap-export`: linemap.h5 -> PLY and/or LIMAP finaltracks (or LIMAP -> linemap.h5)."""
    p = subparsers.add_parser("linemap-export", help="export a line map to PLY / LIMAP tracks, or import LIMAP tracks")
    p.add_argument("linemap", type=Path, help="linemap.h5, or a LIMAP folder holding finaltracks/")
    p.add_argument("--ply", type=Path, help="write the lines as a PLY (vertices + edges)")
    p.add_argument("--limap", type=Path, help="write LIMAP finaltracks/ and image_list.txt into this folder")
    p.add_argument("--h5", type=Path, help="write linemap.h5 (e.g. after reading LIMAP tracks)")
    p.add_argument("--image-list", type=Path, help="LIMAP image list when reading tracks (default: beside them)")
    p.set_defaults(func=cli_linemap_export)
    return p


def cli_linemap_export(args):
    path = Path(args.linemap)
    lm = LineMap.from_limap(path, args.image_list) if path.is_dir() else LineMap.load(path)
    if not (args.ply or args.limap or args.h5):
        raise InputError("nothing to do: give --ply, --limap and/or --h5")
    if args.ply:
        lm.to_ply(args.ply)
    if args.limap:
        lm.to_limap(args.limap)
    if args.h5:
        lm.save(args.h5)
    logger.info("Exported %d lines.", len(lm))
    return lm


__all__ = ["LineMap", "Observation", "edge_line_mask", "write_ply_lines", "read_ply_lines",
           "add_linemap_export_parser", "cli_linemap_export"]
