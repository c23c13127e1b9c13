"""Line-assisted visual localization with LiP-Map line maps (points from SIFT or hloc, lines from the map)."""
