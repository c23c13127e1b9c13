"""LiP-Map line mapping: 2D line to plane-edge assignment, line losses, extraction, merging, tracks."""
