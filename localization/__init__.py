"""lipmap localization: 2D-3D point matches (built-in SIFT pipeline or hloc's files), retrieval,
initial pose from points, line queries and joint point+line refinement.

Submodules are imported on use (``from localization import points``) so that ``import
localization`` stays light. The per-query API: ``from localization import Localizer`` (:mod:`localization.api`).
"""

# the per-query API, imported on first use
_API = ("Localizer", "QueryResult", "PoseEstimate", "LineMatches", "LocalizationConfig")


def __getattr__(name):
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'localization' has no attribute {name!r}")


__all__ = list(_API)
