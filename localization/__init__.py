"""lipmap localization: 2D-3D point matches (built-in SIFT pipeline or hloc's files), retrieval,
initial pose from points, line queries and joint point+line refinement.

Submodules are imported on use (``from localization import points``) so that ``import
localization`` stays light.
"""
