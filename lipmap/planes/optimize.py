"""The plane optimization's public names, kept importable from here; each lives in the module of its concern.

:mod:`~lipmap.planes.config` (settings and presets), :mod:`~lipmap.planes.targets` (a view's depth and normals on
its training grid), :mod:`~lipmap.planes.losses` (the plane loss), :mod:`~lipmap.planes.structure` (pruning and
splitting), :mod:`~lipmap.planes.optimizer` (Adam and the step) and :mod:`~lipmap.planes.train` (the loop and the
pipeline step).
"""
from .config import PlaneOptConfig, confs, select_device
from .losses import plane_loss
from .structure import PlaneIndexMap, prune_and_split
from .targets import TargetStore, ViewTarget, prepare_targets, training_camera, view_target
from .train import HISTORY_KEYS, ExtraLoss, Schedule, fit_planes, optimize_planes, planes_stamp, render_target

__all__ = ["PlaneOptConfig", "confs", "select_device", "plane_loss", "PlaneIndexMap", "prune_and_split", "TargetStore",
           "ViewTarget", "prepare_targets", "training_camera", "view_target", "HISTORY_KEYS", "ExtraLoss", "Schedule",
           "fit_planes", "optimize_planes", "planes_stamp", "render_target"]
