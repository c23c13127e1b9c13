"""The joint line-plane optimization step of a LiP-Map map (paper Sec. 3.3): the line term built from a
:class:`~lipmap.mapping.pipeline.MappingConfig`, and ``planes.h5`` made or reused under a stamp of its own.

The planes' stamp digests only the code that shapes them (:data:`lipmap.artifacts.PLANES_CODE`), so that a change to
line extraction, tracks or on-plane lines remakes ``linemap.h5`` from the same planes instead of re-optimizing
them (minutes per mini scene, hours per full 7-Scenes scene).
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path


def lines_settings(conf, lines_source=None) -> dict:
    """What the 2D lines of a map depend on: the detector preset's settings, or the imported source."""
    if lines_source is not None:
        return {"import": str(Path(lines_source).resolve())}
    from ..lines2d import get_conf as lines_conf

    return {"detector": asdict(lines_conf(conf.lines))}


def line_supervision(lines_by_view: dict, conf):
    """The line term of the joint optimization with the settings of ``conf`` (a ``MappingConfig``)."""
    from .supervision import LineSupervision

    return LineSupervision(lines_by_view, weight=conf.line_weight, pixels_per_line=conf.pixels_per_line,
                           use_group=conf.group_loss, seed=conf.seed, endpoint_weight=conf.endpoint_weight,
                           robust_scale=conf.robust_scale, max_assign_frac=conf.max_assign_frac,
                           euc_inside_only=conf.euc_inside_only, depth_gate=conf.line_depth_gate,
                           hard_first_hit=conf.hard_first_hit, exclusive_pixels=conf.one_line_per_pixel)


def _plane_settings(conf, lines_source=None):
    from ..planes.config import PlaneOptConfig

    extra = {"line_term": line_supervision({}, conf).settings(), "lines": lines_settings(conf, lines_source)}
    return PlaneOptConfig.preset(conf.planes, seed=conf.seed), extra


def planes_stamp(scene, conf, lines_source=None):
    """The :class:`~lipmap.artifacts.Stamp` of the ``planes.h5`` that :func:`fit_planes_with_lines` makes for the
    mapping views of ``scene`` (after keyframe selection) with ``conf``."""
    from ..planes.train import planes_stamp as stamp_of

    pconf, extra = _plane_settings(conf, lines_source)
    return stamp_of(scene, pconf, extra)


def planes_variant_dir(parent, scene, conf, lines_source=None) -> Path:
    """``parent/planes-<preset>-<digest>``: one folder per plane optimization, shared by the map variants that
    differ only after it (extraction, tracks, on-plane lines, or their code)."""
    from ..artifacts import variant_dir

    return variant_dir(parent, f"planes-{conf.preset}", planes_stamp(scene, conf, lines_source))


def fit_planes_with_lines(scene, lines_by_view: dict, out_dir: Path, conf, lines_source=None, overwrite=False):
    """Joint line-plane optimization (:func:`lipmap.planes.train.fit_planes` with the line term);
    writes or reuses ``out_dir/planes.h5`` and ``planes.ply``. Returns Planes."""
    from ..planes import io as pio
    from ..planes.train import fit_planes

    pconf, extra = _plane_settings(conf, lines_source)
    path = fit_planes(scene, out_dir, pconf, extra_loss=line_supervision(lines_by_view, conf), overwrite=overwrite,
                      stamp_extra=extra)
    return pio.load_planes(path)
