"""Line correspondences checked with the ground-truth pose, the per-scene figures made of them, and the
per-iteration gates of the line query."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap import geometry as geo
from lipmap.mapping.assign import corner_edges
from lipmap.poses import make_T
from lipmap.testing import SMALL_CAMERA, wall_scene
from localization.linequery import LineQuery, LineQueryConfig, correct_line_matches
from localization.config import LocalizationConfig
from localization.pipeline import line_match_stats
from localization.query import line_query_schedule


def test_a_match_is_correct_within_2_px_and_1_degree_under_the_ground_truth():
    corners, views = wall_scene()
    T = views[0].cam_from_world
    lines3d = corner_edges(corners[:1])[0]  # (4, 2, 3)
    seg, _ = geo.project_segments(lines3d, T, SMALL_CAMERA)
    det = seg.copy()
    d = seg[1, 1] - seg[1, 0]
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    det[1] += 3.0 * n  # 3 px beside its line: wrong
    det[2] += 1.5 * n  # 1.5 px: right
    det[3] = det[3, ::-1]  # endpoints swapped: still the same line
    ok = correct_line_matches(det, lines3d, T, SMALL_CAMERA)
    assert ok.tolist() == [True, False, True, True]
    swapped = correct_line_matches(det, lines3d[[1, 0, 2, 3]], T, SMALL_CAMERA)  # matched to another edge
    assert swapped.tolist() == [False, False, True, True]
    assert not correct_line_matches(det, lines3d, None, SMALL_CAMERA).any()


def test_line_match_stats_pool_the_queries():
    recs = [{"point+line": {"n_line_matches": 10, "n_line_matches_correct": 8, "n_line_inliers": 6, "n_line_inliers_correct": 6}},
            {"point+line": {"n_line_matches": 30, "n_line_matches_correct": 12, "n_line_inliers": 10, "n_line_inliers_correct": 8}},
            {"point+line": {"success": False}}]  # a failed query has no line figures
    s = line_match_stats(recs)
    assert s["line_match_precision"] == pytest.approx(20 / 40) and s["line_inlier_precision"] == pytest.approx(14 / 16)
    assert s["median_line_matches"] == 20 and s["median_line_matches_correct"] == 10
    assert line_match_stats([{"point+line": {}}]) == {}


def test_line_query_schedule():
    assert len(line_query_schedule(LocalizationConfig(line_iters=3))) == 3
    sched = line_query_schedule(LocalizationConfig(line_gates=((8, 3), (2, 1))))
    assert [(c.max_dist_px, c.max_angle_deg) for c in sched] == [(8.0, 3.0), (2.0, 1.0)]
    assert all(c.method == LineQueryConfig().method for c in sched)
