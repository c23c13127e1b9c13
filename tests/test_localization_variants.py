"""benchmarks/localization_variants.py: a map that differs from the default only in extraction settings starts from the
default map's planes; any other map keeps its own plane optimization."""
from argparse import Namespace

from conftest import benchmark_module

variants = benchmark_module("localization_variants.py")


def _conf(mapping: dict):
    from localization.cli import _mapping_conf
    from localization.pipeline import LocalizationConfig

    return LocalizationConfig(mapping=_mapping_conf(Namespace(preset=LocalizationConfig().mapping, keyframes=None), **mapping))


def _folder(scene, scene_dir, conf):
    return variants.map_folder(scene, scene_dir, conf.mapping, conf.seed)


def test_extraction_only_variant_starts_from_the_default_planes(synthetic_root, tmp_path):
    from lipmap.datasets import load_scene

    scene = load_scene("synthetic", synthetic_root, "room-s3")
    default = _folder(scene, tmp_path, _conf({}))
    default.mkdir(parents=True)
    for f in ("planes.h5", "lines2d.h5"):
        (default / f).write_bytes(f.encode())

    gate = _conf({"extract": {"max_dist": 6.0, "max_angle": 0.06}})
    variants.reuse_default_planes(scene, tmp_path, gate)
    dst = _folder(scene, tmp_path, gate)
    assert dst != default
    assert (dst / "planes.h5").read_bytes() == b"planes.h5" and (dst / "lines2d.h5").read_bytes() == b"lines2d.h5"
    (dst / "planes.h5").write_bytes(b"own")  # a folder that has its planes keeps them
    variants.reuse_default_planes(scene, tmp_path, gate)
    assert (dst / "planes.h5").read_bytes() == b"own"


def test_only_extraction_overrides_reuse_planes():
    assert variants.extraction_only({"extract": {"max_dist": 6.0}, "plane_depth_tol": 0.05})
    assert not variants.extraction_only({})  # the default map is the source itself
    assert not variants.extraction_only({"lines": "lsd-dense"})  # the line term sees other lines
    assert not variants.extraction_only({"extract": {"max_dist": 6.0}, "line_depth_gate": 0.3})
