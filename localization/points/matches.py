"""2D-3D point matches of a query from its 2D-2D matches to database images with 3D points (hloc's ``localize_sfm``)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from lipmap import logger
from lipmap.errors import InputError

from .. import hloc_io
from ..hloc_io import ModelIndex


@dataclass
class PointMatches:
    """2D-3D point matches of one query; unpacks as ``p2d, p3d, point3D_ids``.

    Attributes:
        p2d: (N, 2) query keypoints, COLMAP pixel convention.
        p3d: (N, 3) world points.
        point3D_ids: (N,) ids in the reconstruction.
        keypoint_idx: (N,) index of each query keypoint in the features file.
    """

    p2d: np.ndarray
    p3d: np.ndarray
    point3D_ids: np.ndarray
    keypoint_idx: np.ndarray

    def __iter__(self):
        return iter((self.p2d, self.p3d, self.point3D_ids))

    def __len__(self) -> int:
        return len(self.p2d)

    def subset(self, idx: np.ndarray) -> "PointMatches":
        return PointMatches(self.p2d[idx], self.p3d[idx], self.point3D_ids[idx], self.keypoint_idx[idx])


def point_matches_for_query(query_name: str, retrieved: Iterable[str], features_h5, matches_h5, reconstruction) -> PointMatches:
    """2D-3D matches of one query from its matches to retrieved database images (hloc's localize_sfm).

    Each query keypoint gets the 3D points of the database keypoints it matched; a keypoint
    matched to several 3D points (through different database images) keeps one entry per
    distinct 3D point, and repeated (keypoint, 3D point) pairs are kept once.

    Args:
        reconstruction: a pycolmap.Reconstruction, a :class:`~localization.hloc_io.ModelIndex`
            (reuse it across queries) or an SfM folder.

    Returns:
        :class:`PointMatches`, sorted by (keypoint index, 3D point id).
    """
    if isinstance(reconstruction, ModelIndex):
        model = reconstruction
    elif isinstance(reconstruction, (str, Path)):
        model = ModelIndex(hloc_io.read_sfm(reconstruction), reconstruction)
    else:
        model = ModelIndex(reconstruction)
    kpq = hloc_io.read_keypoints(features_h5, query_name)
    rows = []
    with hloc_io.open_h5(matches_h5) as mfd:
        for db_name in dict.fromkeys(retrieved):  # unique, order kept
            ids = model.point3D_ids(db_name)
            m, _ = hloc_io.read_matches_from(mfd, query_name, db_name, matches_h5)
            if len(m) == 0:
                continue
            if m[:, 0].max() >= len(kpq) or m[:, 1].max() >= len(ids):
                raise InputError(
                    f"matches of ({query_name}, {db_name}) index keypoints beyond the query's {len(kpq)} features "
                    f"or the model image's {len(ids)} points2D (features and model from different runs?)",
                    matches_h5,
                )
            pid = ids[m[:, 1]]
            ok = pid >= 0
            rows.append(np.stack([m[ok, 0], pid[ok]], 1))
    if rows:
        rows = np.unique(np.concatenate(rows), axis=0)
    else:
        rows = np.zeros((0, 2), np.int64)
    return PointMatches(
        p2d=kpq[rows[:, 0]], p3d=model.xyz(rows[:, 1]), point3D_ids=rows[:, 1].astype(np.int64), keypoint_idx=rows[:, 0]
    )


def point_matches_from_hloc(query: str, sfm_dir, features_h5, matches_h5, pairs, model: Optional[ModelIndex] = None,
                            pairs_name=None):
    """2D-3D point matches of one query from hloc's outputs, the way hloc's ``localize_sfm`` builds them.

    Args:
        query: query image name (a group in ``features_h5``).
        sfm_dir: COLMAP model of the database images (ignored when ``model`` is given).
        features_h5, matches_h5: hloc files holding the query's keypoints and query-db matches.
        pairs: a pairs file path, or a list of (query, db) pairs / db names; those of ``query``
            are used, in order.
        model: a :class:`ModelIndex` reused across queries (read from ``sfm_dir`` if None).
        pairs_name: the file a pairs list was read from, named in error messages.

    Returns:
        :class:`PointMatches` - p2d (N, 2) COLMAP convention, p3d (N, 3),
        point3D_ids (N,); unpacks as ``p2d, p3d, ids``.
    """
    if model is None:
        model = ModelIndex(hloc_io.read_sfm(sfm_dir), sfm_dir)
    pairs_path = Path(pairs) if isinstance(pairs, (str, Path)) else None
    pair_list = hloc_io.read_pairs(pairs_path) if pairs_path is not None else [tuple(p) for p in pairs]
    pairs_path = pairs_path or pairs_name
    retrieved = hloc_io.pairs_by_query(pair_list).get(query, [])
    if not Path(features_h5).exists():
        raise InputError("features file is missing", features_h5)
    with hloc_io.open_h5(features_h5) as fd:
        if query not in fd:
            raise InputError(
                f"query {query!r} (from pairs {pairs_path or 'list'}) has no group {query!r} in the features file",
                features_h5,
            )
    for name in retrieved:
        if name not in model:
            raise InputError(
                f"image {name!r} (paired with {query!r}) is not in the SfM model {sfm_dir}", pairs_path or sfm_dir
            )
    if not retrieved:
        logger.warning("no database images paired with query %s", query)
    return point_matches_for_query(query, retrieved, features_h5, matches_h5, model)
