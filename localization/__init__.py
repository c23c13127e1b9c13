"""lipmap localization: 2D-3D point matches (built-in SIFT pipeline or hloc's files), retrieval,
initial pose from points, line queries and joint point+line refinement.

Submodules are imported on use (``from localization import points``) so that ``import
localization`` stays light. The per-query API (:mod:`localization.api`): ``from localization import Localizer``,
and ``estimate_pose_point_line`` in the shape of LIMAP's ``pl_estimate_absolute_pose``.
"""

# the per-query API, imported on first use
_API = {"Localizer": "api", "QueryResult": "api", "PoseEstimate": "api", "LineMatches": "api",
        "estimate_pose_point_line": "api", "LocalizationConfig": "config", "LineRescueConfig": "config",
        "PointLinePoseConfig": "estimate", "PointPoseConfig": "estimate", "LineQueryConfig": "linequery"}


def __getattr__(name):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(f".{_API[name]}", __name__), name)
    raise AttributeError(f"module 'localization' has no attribute {name!r}")


__all__ = list(_API)
