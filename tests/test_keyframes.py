"""Keyframe selection by camera motion: known answers on constructed trajectories."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap.mapping.keyframes import KeyframeConfig, frame_number, keyframe_views, select_keyframes
from lipmap.poses import invert_T, make_T
from lipmap.scene import Camera, View

CAM = Camera(64, 48, (50.0, 50.0, 32.0, 24.0))


def view(name, center, yaw_deg=0.0):
    R_wc = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return View(name, CAM, invert_T(make_T(R_wc, np.asarray(center, float))), color_path=None)


def test_translation_threshold_keeps_every_fifth_view_of_a_12mm_walk():
    views = [view(f"seq-01/frame-{i:06d}.color.png", [0.012 * i, 0, 0]) for i in range(31)]
    idx = select_keyframes(views, KeyframeConfig(min_translation=0.05, min_rotation_deg=0, max_frame_gap=0))
    # 4 steps (4.8 cm) stay under 5 cm, the 5th (6 cm) makes the next keyframe
    assert idx.tolist() == [0, 5, 10, 15, 20, 25, 30]


def test_rotation_threshold_alone():
    views = [view(f"seq-01/f{i}", [0, 0, 0], yaw_deg=2.0 * i) for i in range(10)]
    idx = select_keyframes(views, KeyframeConfig(min_translation=0.0, min_rotation_deg=5.0))
    assert idx.tolist() == [0, 3, 6, 9]


def test_either_motion_makes_a_keyframe_and_a_new_sequence_always_does():
    views = [view("seq-01/a", [0, 0, 0]), view("seq-01/b", [0.01, 0, 0], yaw_deg=10),  # turned
             view("seq-01/c", [0.02, 0, 0], yaw_deg=10),  # barely moved since b
             view("seq-02/d", [0.02, 0, 0], yaw_deg=10)]  # same pose, another sequence
    assert select_keyframes(views).tolist() == [0, 1, 3]


def test_disabled_keeps_every_posed_view_and_views_without_pose_are_skipped():
    views = [view(f"seq-01/f{i}", [0, 0, 0]) for i in range(4)]
    views[2] = View("seq-01/f2", CAM, None, color_path=None)
    assert select_keyframes(views, KeyframeConfig(0, 0)).tolist() == [0, 1, 3]
    assert select_keyframes(views).tolist() == [0]
    assert [v.name for v in keyframe_views(views, KeyframeConfig(0, 0))] == ["seq-01/f0", "seq-01/f1", "seq-01/f3"]


def test_frame_numbers_are_read_from_the_file_name():
    assert frame_number("seq-01/frame-000120.color.png") == 120
    assert frame_number("db/img_0042.jpg") == 42
    assert frame_number("seq-07/query.png") is None


def test_the_frame_gap_keeps_a_subsampled_set_whole_and_bounds_a_still_camera():
    # every 5th frame of a slow walk (2 cm apart): motion alone keeps every 3rd, the gap keeps all
    sub = [view(f"seq-01/frame-{5 * i:06d}.color.png", [0.02 * i, 0, 0]) for i in range(12)]
    assert select_keyframes(sub, KeyframeConfig(max_frame_gap=0)).tolist() == [0, 3, 6, 9]
    assert select_keyframes(sub).tolist() == list(range(12))
    # a camera that does not move at 30 Hz: one keyframe every 5 frames
    still = [view(f"seq-01/frame-{i:06d}.color.png", [0, 0, 0]) for i in range(16)]
    assert select_keyframes(still).tolist() == [0, 5, 10, 15]
    # names without frame numbers: motion only
    assert select_keyframes([view(f"seq-01/v{c}", [0, 0, 0]) for c in "abc"]).tolist() == [0]


@pytest.mark.shared
def test_redkitchen_mini_keeps_every_frame_with_the_defaults(redkitchen_root):
    from lipmap.datasets import load_scene

    scene = load_scene("7scenes", redkitchen_root, "redkitchen")
    # every 10th frame: 4 of them moved < 5 cm and turned < 5 deg, and the frame gap keeps them
    assert len(select_keyframes(scene.mapping)) == len(scene.mapping) == 50
    assert len(select_keyframes(scene.mapping, KeyframeConfig(max_frame_gap=0))) == 46


@pytest.mark.parametrize("method", ["lipmap", "lift"])
def test_the_map_stamp_records_the_keyframe_thresholds(synthetic_root, method):
    """Both methods map the keyframes only, so a map made with other thresholds is never reused (it was for lift)."""
    from lipmap.datasets import load_scene
    from lipmap.mapping.pipeline import get_conf, mapping_stamp

    scene = load_scene("synthetic", synthetic_root, "room-s3")
    every = {"preset": "fast", "keyframes": {"min_translation": 0, "min_rotation_deg": 0}}
    assert mapping_stamp(scene, get_conf(every), method).digest != mapping_stamp(scene, get_conf("fast"), method).digest
