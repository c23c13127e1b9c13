"""Settings of the built-in point pipeline (SIFT, pairs, matching, triangulation) and their named presets."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from lipmap.presets import resolve


@dataclass
class SiftConfig:
    """pycolmap SIFT options (COLMAP defaults except the keypoint budget)."""

    max_keypoints: int = 4096  # COLMAP keeps the coarsest-scale features when over budget
    first_octave: int = -1  # -1 = upsample once (COLMAP default): more small-scale features, ~2x slower
    peak_threshold: float = 0.02 / 3
    edge_threshold: float = 10.0
    max_num_orientations: int = 2
    upright: bool = False
    num_threads: int = -1

    @property
    def name(self) -> str:
        return f"sift-n{self.max_keypoints}" + ("" if self.first_octave == -1 else f"-o{self.first_octave}")


@dataclass
class MatchConfig:
    """Descriptor matching: mutual nearest neighbour + Lowe's ratio test (hloc's NN-ratio)."""

    ratio: float = 0.8  # on Euclidean distances, as hloc and COLMAP
    mutual: bool = True
    max_distance: Optional[float] = None  # Euclidean, unit descriptors (COLMAP uses 0.7); None = off

    @property
    def name(self) -> str:
        return f"nn{'-mutual' if self.mutual else ''}-ratio{self.ratio:g}"


@dataclass
class PairsConfig:
    """Mapping pairs from known poses: frustum overlap (sampled at nominal depths) + viewing angle."""

    num_neighbors: int = 10
    max_angle_deg: float = 60.0
    min_overlap: float = 0.2
    depths: tuple = (1.0, 2.0, 3.5)  # metres; indoor scenes. Scale with the scene for others.
    grid: tuple = (8, 6)


@dataclass
class TriangulationConfig:
    """Geometric verification with the known poses, then COLMAP's triangulator (poses held fixed)."""

    max_epipolar_error: float = 4.0  # px, Sampson distance w.r.t. the known relative pose
    min_inliers: int = 15  # a pair with fewer verified matches is dropped
    min_angle_deg: float = 1.5  # COLMAP default triangulation angle
    max_reproj_error: float = 4.0  # px, COLMAP's complete/merge thresholds
    ignore_two_view_tracks: bool = True
    seed: int = 0
    num_threads: int = -1


@dataclass
class PointsConfig:
    """The whole built-in point pipeline; ``name`` records the settings in artifact names."""

    sift: SiftConfig = field(default_factory=SiftConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)


confs = {
    "sift-n4096": PointsConfig(),
    "sift-n2048": PointsConfig(sift=SiftConfig(max_keypoints=2048)),
    # fast: no upsampling; for tests and quick runs
    "sift-n1024-fast": PointsConfig(sift=SiftConfig(max_keypoints=1024, first_octave=0)),
}


def get_conf(conf=None) -> PointsConfig:
    """A :class:`PointsConfig` from a preset name, a dict of overrides or itself (:func:`lipmap.presets.resolve`)."""
    return resolve(conf, confs, "point pipeline", default="sift-n4096")
