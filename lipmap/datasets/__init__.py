"""Dataset readers producing :class:`lipmap.scene.Scene`: 7-Scenes and synthetic scenes (same layout)."""
from __future__ import annotations

from ..errors import InputError

DATASETS = ("7scenes", "synthetic")


def load_scene(dataset: str, root, scene: str, **kw):
    """Load ``scene`` of ``dataset`` under ``root``; keyword arguments go to SevenScenesConfig."""
    from .sevenscenes import load_scene as _load

    if dataset not in DATASETS:
        raise InputError(f"unknown dataset {dataset!r}; choose one of {', '.join(DATASETS)}")
    return _load(root, scene, dataset=dataset, **kw)


def list_scenes(dataset: str, root) -> list[str]:
    from .sevenscenes import list_scenes as _list

    return _list(root)
