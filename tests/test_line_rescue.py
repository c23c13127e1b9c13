"""Lines for queries whose points alone give no trustworthy pose (localization.pipeline.LineRescueConfig)."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lipmap.poses import make_T, pose_errors
from lipmap.scene import Camera
from localization.linequery import LineQuery, LineQueryConfig
from localization.config import LineRescueConfig, LocalizationConfig
from localization.query import localize_query, rescue_pose, retrieved_poses
from localization.points import PointMatches

CAM = Camera(640, 480, (525, 525, 320, 240))


def _project(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * 525 + [320, 240]


def _scene(seed=0, n_lines=40, n_pts=3):
    """A camera, map lines in front of it (a box of 3D segments), their detections and a few 2D-3D points."""
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.from_euler("xyz", rng.uniform(-10, 10, 3), degrees=True).as_matrix(), rng.uniform(-0.3, 0.3, 3))
    Tinv = np.linalg.inv(T)
    a = np.c_[rng.uniform(-1.2, 1.2, (n_lines, 2)), rng.uniform(2, 4, n_lines)]
    b = a + rng.normal(0, 0.4, (n_lines, 3))
    ends = np.stack([a, b], 1) @ Tinv[:3, :3].T + Tinv[:3, 3]  # world
    l2 = np.concatenate([_project(T, ends[:, 0]), _project(T, ends[:, 1])], 1)
    d = l2[:, 2:] - l2[:, :2]
    l2 = np.concatenate([l2[:, :2] + 0.1 * d, l2[:, 2:] - 0.1 * d], 1) + rng.normal(0, 0.3, (n_lines, 4))
    Xc = np.c_[rng.uniform(-1, 1, (n_pts, 2)), rng.uniform(2, 4, n_pts)]
    X = Xc @ Tinv[:3, :3].T + Tinv[:3, 3]
    pm = PointMatches(p2d=_project(T, X), p3d=X, point3D_ids=np.arange(n_pts), keypoint_idx=np.arange(n_pts))
    return T, ends, l2, pm


def _off(T, cm, deg):
    dR = Rotation.from_euler("yx", [deg, 0.5 * deg], degrees=True).as_matrix()
    return make_T(dR @ T[:3, :3], T[:3, 3] + [cm / 100, -cm / 200, 0.0])


def test_top_k_candidates_per_query_line():
    T, ends, l2, _ = _scene()
    lq = LineQuery(ends)
    one = lq.match(l2, T, CAM, LineQueryConfig(max_dist_px=30, max_angle_deg=5, min_margin=0, one_to_one=False))
    three = lq.match(l2, T, CAM, LineQueryConfig(max_dist_px=30, max_angle_deg=5, max_candidates=3, one_to_one=False))
    assert np.all(np.bincount(three["query_idx"], minlength=len(l2)) <= 3)
    assert len(three["query_idx"]) > len(one["query_idx"])
    assert set(zip(one["query_idx"], one["line_idx"])) <= set(zip(three["query_idx"], three["line_idx"]))


def test_rescue_recovers_a_pose_the_narrow_gates_cannot():
    for seed in range(4):
        T, ends, l2, pm = _scene(seed)
        prior = _off(T, 8, 3)  # a retrieved view 8 cm / 3 deg away
        lq = LineQuery(ends)
        narrow = lq.match(l2, prior, CAM, LineQueryConfig(max_dist_px=8, max_angle_deg=3))
        assert np.sum(narrow["query_idx"] == narrow["line_idx"]) < 10  # the usual first gate finds few right lines
        conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(weak_inliers=12))
        far = _off(T, 60, 40)  # a useless prior beside it must not win
        r = rescue_pose(pm, l2, [far, prior], lq, CAM, conf)
        assert r is not None and r["n_line_inliers"] >= 8
        dt, dr = pose_errors(T, r["cam_from_world"])
        assert dt < 0.005 and dr < 0.2


class _Points:
    def __init__(self, pm, model):
        self.pm, self.model = pm, model

    def matches_for(self, name):
        return self.pm

    def retrieved_for(self, name):
        return ["db1", "db2"]


class _Model:
    def __init__(self, poses):
        self.poses = poses

    def __contains__(self, name):
        return name in self.poses

    def cam_from_world(self, name):
        return self.poses[name]


def test_localize_query_rescues_a_query_with_too_few_points():
    T, ends, l2, pm = _scene(1)
    points = _Points(pm, _Model({"db1": _off(T, 60, 40), "db2": _off(T, 6, 2)}))
    lq = LineQuery(ends)
    off = localize_query("q", CAM, points, l2, lq, LocalizationConfig())
    assert not off["point"]["success"] and not off["point+line"]["success"]  # 3 points: no pose to start from
    # the lines stand 2-4 m in front of this camera, so its hypotheses lie outside their box + 0.5 m: only the
    # retrieved images' poses can start the lines
    conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(weak_inliers=12, prior_views=2))
    assert [p.tolist() for p in retrieved_poses("q", points, 2)] == \
        [points.model.cam_from_world("db1").tolist(), points.model.cam_from_world("db2").tolist()]
    rec = localize_query("q", CAM, points, l2, lq, conf, cam_from_world_gt=T)
    pl = rec["point+line"]
    assert not rec["point"]["success"] and pl["success"] and pl["rescued"] and pl["used_lines"]
    assert pose_errors(T, np.array(pl["cam_from_world"]))[0] < 0.005
    assert pl["n_line_matches_correct"] >= 0.9 * pl["n_line_matches"]


def test_p3p_hypotheses_hold_the_true_pose():
    from localization.hypotheses import HypothesisConfig, p3p_hypotheses

    T, ends, l2, pm = _scene(2, n_pts=6)
    poses, inl = p3p_hypotheses(pm.p2d, pm.p3d, CAM, HypothesisConfig())
    assert len(poses) >= 20 and inl.max() == 6  # C(6, 3) triples, up to 4 solutions each
    best = poses[np.argmax(inl)]
    assert pose_errors(T, best)[0] < 1e-6


def test_lines_score_the_true_pose_above_wrong_ones():
    from localization.hypotheses import HypothesisConfig, LineEvidence, line_verified_poses

    T, ends, l2, pm = _scene(3, n_lines=60, n_pts=6)
    ev = LineEvidence(l2, CAM, HypothesisConfig())
    far = make_T(T[:3, :3], T[:3, 3] + [0, 0, 30.0])  # 30 m back: the map is tiny in the image
    s = ev.score(np.stack([T, _off(T, 5, 2), far]), ends)
    assert s[0] >= 0.8 * len(ends) and s[1] < 0.3 * s[0] and s[2] == 0
    # two wrong matches among five: RANSAC's count cannot tell the triples apart, lines can
    p2d = pm.p2d[:5].copy()
    p2d[3:] += [[80, -40], [-60, 70]]
    # (this camera stands 2-4 m before the lines, outside their box grown by the default 0.5 m)
    poses = line_verified_poses(p2d, pm.p3d[:5], l2, ends, CAM, HypothesisConfig(box_margin=5.0))
    assert poses and pose_errors(T, poses[0])[0] < 1e-6


@pytest.mark.parametrize("bins", [8, 12])
def test_line_scores_agree_with_the_reference(bins):
    """The fast score (endpoints for all, samples only where a line lands in the image, the last samples only where
    the first left it a chance) gives the reference's counts, for poses at, near and far from the truth, turned away
    (lines behind the camera), or at the map (a line through the camera's plane); with 12 bins the bit table is 16
    bits wide."""
    from localization.hypotheses import HypothesisConfig, LineEvidence

    T, ends, l2, _ = _scene(5, n_lines=80)
    rng = np.random.default_rng(1)
    poses = [T] + [_off(T, cm, deg) for cm, deg in [(1, 0.2), (3, 1), (10, 3), (40, 10)]]
    poses += [make_T(Rotation.from_euler("y", a, degrees=True).as_matrix() @ T[:3, :3], T[:3, 3]) for a in (60, 100, 180)]
    poses += [make_T(T[:3, :3], T[:3, 3] + [0, 0, -3.0]), make_T(T[:3, :3], T[:3, 3] + rng.normal(0, 1, 3))]
    poses = np.stack(poses)
    # every sample, two of three, any sample: the early drop of lines that already missed too often must not change a count
    for conf in (HypothesisConfig(angle_bins=bins), HypothesisConfig(angle_bins=bins, min_agree=0.4, samples=3),
                 HypothesisConfig(angle_bins=bins, min_agree=1.0, samples=4), HypothesisConfig(angle_bins=bins, min_agree=0.1)):
        ev = LineEvidence(l2, CAM, conf)
        fast, ref = ev.score(poses, ends), ev.score_reference(poses, ends)
        np.testing.assert_array_equal(fast, ref)
        assert fast[0] >= 0.8 * len(ends) and fast[-3:-1].min() < fast[0]
    assert ev.score(poses[:0], ends).shape == (0,) and np.all(ev.score(poses, ends[:0]) == 0)


def test_line_evidence_masks_hold_the_pixels_near_detections():
    """The per-direction masks hold every pixel centre within max_dist_px of a detection of that direction bin,
    and hardly any beyond (exact point-segment distances)."""
    from localization.hypotheses import HypothesisConfig, LineEvidence

    rng = np.random.default_rng(0)
    W, H = CAM.width, CAM.height
    L = np.c_[rng.uniform(0, W, 30), rng.uniform(0, H, 30), rng.uniform(0, W, 30), rng.uniform(0, H, 30)]
    L = L[np.linalg.norm(L[:, 2:] - L[:, :2], axis=1) >= 40]
    conf = HypothesisConfig()
    ev = LineEvidence(L, CAM, conf)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5  # COLMAP pixel centres
    P = np.stack([xx, yy], -1).reshape(-1, 2)
    ang = np.mod(np.arctan2(L[:, 3] - L[:, 1], L[:, 2] - L[:, 0]), np.pi)
    width = np.pi / conf.angle_bins
    for b in range(conf.angle_bins):
        # a line counts in its own bin and the neighbour nearest to its angle
        own = np.floor(ang / width).astype(int) % conf.angle_bins
        frac = ang / width - np.floor(ang / width)
        nxt = np.where(frac >= 0.5, own + 1, own - 1) % conf.angle_bins
        d = np.full(len(P), np.inf)
        for a, e in zip(L[(own == b) | (nxt == b), :2], L[(own == b) | (nxt == b), 2:]):
            ab = e - a
            t = np.clip((P - a) @ ab / (ab @ ab), 0, 1)
            d = np.minimum(d, np.linalg.norm(P - a - t[:, None] * ab, axis=1))
        exact = (d <= conf.max_dist_px).reshape(H, W)
        near = ev.near[b].astype(bool)
        assert (exact & ~near).sum() <= 0.01 * max(exact.sum(), 1)  # misses almost none
        assert (near & ~(d <= conf.max_dist_px + 1.0).reshape(H, W)).sum() == 0  # and nothing a pixel further


def test_rescue_starts_near_an_earlier_one_are_skipped():
    from localization.query import distinct_poses

    T, *_ = _scene(4)
    starts = [T, _off(T, 6, 2), _off(T, 30, 2), _off(T, 4, 8), _off(T, 31, 2.5)]
    kept = distinct_poses(starts, LineRescueConfig().same_pose_m, LineRescueConfig().same_pose_deg)
    # 6 cm / 2 deg from the first repeats it; 30 cm away or 8 deg turned does not; the last repeats the third
    assert [any(K is S for K in kept) for S in starts] == [True, False, True, True, False]


def test_each_rescue_stage_takes_its_own_number_of_candidates():
    T, ends, l2, pm = _scene(5)
    lq = LineQuery(ends)
    used = []
    match = lq.match

    def spy(lines2d, T0, camera, conf, visible=None):
        used.append(conf.max_candidates)
        return match(lines2d, T0, camera, conf, visible)

    lq.match = spy
    rescue = LineRescueConfig(weak_inliers=12, candidates=3, gates=((30, 5), (15, 3, 1)))
    r = rescue_pose(pm, l2, [_off(T, 8, 3)], lq, CAM, replace(LocalizationConfig(), line_rescue=rescue))
    assert used == [3, 1]  # the first stage the default's 3, the second its own 1
    assert r is not None and pose_errors(T, r["cam_from_world"])[0] < 0.005


def test_robust_refinement_ignores_outlying_lines_and_counts_inliers():
    from localization.estimate import refine_pnpl_pose

    T, ends, l2, pm = _scene(6, n_lines=40, n_pts=6)
    bad = l2.copy()
    d = bad[:10, 2:] - bad[:10, :2]
    nrm = np.c_[-d[:, 1], d[:, 0]] / np.linalg.norm(d, axis=1, keepdims=True)
    bad[:10] += 15 * np.tile(nrm, 2)  # 10 lines moved 15 px off, across their direction
    start = _off(T, 3, 1)
    args = (pm.p2d, pm.p3d, bad.reshape(-1, 2, 2), ends, CAM, start)
    r = refine_pnpl_pose(*args, point_scale=3.0, line_scale=3.0, max_reproj_error=6.0, max_line_error=2.0)
    dt, dr = pose_errors(T, r["cam_from_world"])
    assert r["success"] and dt < 0.003 and dr < 0.1
    assert r["n_inliers"] == 6 and not r["line_inliers"][:10].any() and r["line_inliers"][10:].mean() > 0.9
    # the scales are pixels: at 100 px the outliers pull the pose
    loose = refine_pnpl_pose(*args, point_scale=100.0, line_scale=100.0, max_reproj_error=6.0, max_line_error=2.0)
    assert pose_errors(T, loose["cam_from_world"])[0] > 3 * dt


def test_rescue_by_refinement_recovers_the_pose_and_tests_visibility_once_per_start():
    for seed in range(3):
        T, ends, l2, pm = _scene(seed)
        lq = LineQuery(ends)
        calls = []
        vis = lq.visible_lines
        lq.visible_lines = lambda *a, **k: calls.append(1) or vis(*a, **k)
        rescue = LineRescueConfig(weak_inliers=12, solver="refine")
        r = rescue_pose(pm, l2, [_off(T, 60, 40), _off(T, 8, 3)], lq, CAM, replace(LocalizationConfig(), line_rescue=rescue))
        assert r is not None and r["n_line_inliers"] >= 8
        dt, dr = pose_errors(T, r["cam_from_world"])
        assert dt < 0.005 and dr < 0.2
        assert len(calls) == 2  # one per start, not per stage


@pytest.mark.parametrize("case", ["weakly held", "unconfirmed"])
def test_a_rescue_that_is_a_guess_gives_way_to_the_point_only_pose(monkeypatch, case):
    """A rescued pose whose last round keeps fewer than ``min_final_lines`` line inliers, or that no narrowing round
    confirms, is dropped; a query with a (weak) point-only pose then narrows from that pose as if no rescue had run."""
    import localization.query as Q

    T, ends, l2, pm = _scene(3, n_pts=8)
    point_only = _off(T, 1, 0.2)
    monkeypatch.setattr(Q, "estimate_pose_points", lambda *a, **k: {
        "success": True, "cam_from_world": point_only, "n_inliers": 8, "inliers": np.ones(8, bool)})
    monkeypatch.setattr(Q, "rescue_pose", lambda *a, **k: {"cam_from_world": _off(T, 40, 10), "inliers": np.ones(8, bool)})
    m = {"line_idx": np.arange(30), "lines2d": np.zeros((30, 2, 2)), "lines3d": np.zeros((30, 2, 3))}
    calls = []

    def rounds(pm, l2, T0, camera, lq, conf, plconf, strong=False):
        calls.append((T0, strong))
        if len(calls) > 1:
            return T, m, np.arange(30) < 25, True, None
        return (T0, m, np.arange(30) < 10, True, None) if case == "weakly held" else (T0, None, None, False, None)

    monkeypatch.setattr(Q, "refine_with_lines", rounds)
    monkeypatch.setattr(Q, "confirm_with_lines", lambda *a: rounds(*a, strong=True))  # the rescued pose's round
    conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(min_final_lines=20 if case == "weakly held" else 0))
    rec, detail = Q.localize_matches(pm, l2, CAM, LineQuery(ends), conf)
    pl = rec["point+line"]
    assert pl["success"] and not pl["rescued"] and pl["n_line_inliers"] == 25
    assert len(calls) == 2 and calls[0][1] and calls[1][0] is point_only and not calls[1][1]
    np.testing.assert_array_equal(np.array(pl["cam_from_world"]), T)


@pytest.mark.parametrize("held_by", [None, 3, 6])
def test_a_weak_point_only_pose_that_few_lines_hold_fails(monkeypatch, held_by):
    """A weak point-only pose (fewer than ``weak_inliers`` inliers) that the rescue did not replace is a guess when its
    narrowing rounds keep fewer than ``min_final_lines`` line inliers, or take none: the query fails with the reason
    (on the held-out split each such pose lay metres off). Held by enough lines, or with the test off, it stands."""
    import localization.query as Q

    T, ends, l2, pm = _scene(3, n_pts=8)
    point_only = _off(T, 300, 120)
    monkeypatch.setattr(Q, "estimate_pose_points", lambda *a, **k: {
        "success": True, "cam_from_world": point_only, "n_inliers": 4, "inliers": np.arange(8) < 4})
    monkeypatch.setattr(Q, "rescue_pose", lambda *a, **k: None)
    m = {"line_idx": np.arange(8), "lines2d": np.zeros((8, 2, 2)), "lines3d": np.zeros((8, 2, 3))}
    monkeypatch.setattr(Q, "refine_with_lines", lambda pm, l2, T0, *a, **k: (
        (T0, None, None, False, None) if held_by is None else (T0, m, np.arange(8) < held_by, True, None)))
    pl = Q.localize_matches(pm, l2, CAM, LineQuery(ends), LocalizationConfig())[0]["point+line"]
    if held_by == 6:
        assert pl["success"] and not pl["rescued"] and pl["n_line_inliers"] == 6
    else:
        assert not pl["success"]
        assert f"weak point-only pose (4 inliers < 20) that the line rescue did not replace, held by {held_by or 0} line " \
               "inliers < 6" in pl["reason"]
    off = replace(LocalizationConfig(), line_rescue=LineRescueConfig(min_final_lines=0))
    pl = Q.localize_matches(pm, l2, CAM, LineQuery(ends), off)[0]["point+line"]
    assert pl["success"] and np.allclose(pl["cam_from_world"], point_only)


@pytest.mark.parametrize("solver, ransac", [("near", "pnpl_near_start"), ("ransac", "pnpl_pose")])
def test_ransac_rescue_refines_each_kept_pose_without_ransac_and_picks_by_the_last_stage(monkeypatch, solver, ransac):
    """One PnPL RANSAC per start; the later gates refine each kept pose (no more RANSAC), and the best score at the
    last gate wins: the useless start's pose, kept or not, loses to the near one's."""
    import localization.query as Q

    T, ends, l2, pm = _scene(2)
    lq = LineQuery(ends)
    ransacs, refines = [], []
    pnpl, refine = getattr(Q, ransac), Q.refine_pnpl_pose
    monkeypatch.setattr(Q, ransac, lambda *a, **k: ransacs.append(1) or pnpl(*a, **k))
    monkeypatch.setattr(Q, "refine_pnpl_pose", lambda *a, **k: refines.append(1) or refine(*a, **k))
    rescue = LineRescueConfig(weak_inliers=12, solver=solver)  # the default gates: RANSAC at 30 px, then 15 and 8 px refinements
    trace = []
    r = rescue_pose(pm, l2, [_off(T, 60, 40), _off(T, 8, 3)], lq, CAM, replace(LocalizationConfig(), line_rescue=rescue),
                    trace)
    assert len(ransacs) == 2 and len(rescue.gates) == 3
    kept0 = [i for i, t in enumerate(trace) if t["stage"] == 0 and t["kept"]]
    assert len(refines) == 2 * len(kept0) and kept0  # two refinement stages per kept RANSAC pose
    last = {t["origin"]: t for t in trace}
    best = max((last[i] for i in kept0), key=lambda t: t["score"])
    assert best["stage"] == 2 and best["result"] is r
    assert pose_errors(T, r["cam_from_world"])[0] < 0.005
    # one stage only: RANSAC's own pose and score
    one = replace(rescue, gates=((30, 5),))
    r1 = rescue_pose(pm, l2, [_off(T, 8, 3)], lq, CAM, replace(LocalizationConfig(), line_rescue=one))
    assert len(ransacs) == 3 and len(refines) == 2 * len(kept0) and pose_errors(T, r1["cam_from_world"])[0] < 0.005


@pytest.mark.parametrize("solver", ["near", "ransac", "refine"])
def test_rescue_on_threads_gives_the_single_threads_pose_and_trace(solver):
    """The starts run side by side on ``threads``; the pose and the trace (stages, origins, scores, in the starts'
    order) are those of one thread."""
    T, ends, l2, pm = _scene(2)
    starts = [_off(T, 60, 40), _off(T, 8, 3), _off(T, -8, -3), _off(T, 25, 8)]
    out = {}
    for threads in (1, 2, 3):
        trace = []
        conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(weak_inliers=12, solver=solver, threads=threads))
        out[threads] = rescue_pose(pm, l2, starts, LineQuery(ends), CAM, conf, trace), trace
    r1, t1 = out[1]
    assert r1 is not None and pose_errors(T, r1["cam_from_world"])[0] < 0.005
    assert sum(t["stage"] == 0 for t in t1) == 4 and len(t1) > 4
    for r, t in (out[2], out[3]):
        assert np.allclose(r["cam_from_world"], r1["cam_from_world"], atol=1e-9)
        assert [(e["stage"], e["origin"], e["kept"], e["score"]) for e in t] == \
            [(e["stage"], e["origin"], e["kept"], e["score"]) for e in t1]
        assert all(np.allclose(e["start"], f["start"], atol=1e-9) for e, f in zip(t, t1))


def test_a_query_on_threads_gives_the_single_threads_record_and_trace():
    """Through localize_query (the point-only pose, the retrieved views and the hypotheses as starts): the same pose
    and starts on one thread as on two."""
    T, ends, l2, pm = _scene(2, n_pts=6)
    points = _Points(pm, _Model({"db1": _off(T, 60, 40), "db2": _off(T, 6, 2)}))
    out = []
    for threads in (1, 2):
        rescue = LineRescueConfig(weak_inliers=12, prior_views=2, threads=threads,
                                  hypotheses=replace(LineRescueConfig().hypotheses, box_margin=5.0))
        trace = []
        rec = localize_query("q", CAM, points, l2, LineQuery(ends), replace(LocalizationConfig(), line_rescue=rescue),
                             trace=trace)
        out.append((rec["point+line"], [t for t in trace if "stage" in t]))
    (a, ta), (b, tb) = out
    assert a["success"] and a["rescued"] and pose_errors(T, np.array(a["cam_from_world"]))[0] < 0.005
    assert np.allclose(a["cam_from_world"], b["cam_from_world"], atol=1e-9)
    assert a["n_line_inliers"] == b["n_line_inliers"]
    assert sum(t["stage"] == 0 for t in ta) >= 2  # the point-only pose and the far view (the rest lie near those)
    assert [(t["stage"], t["origin"], t["kept"], t["score"]) for t in ta] == \
        [(t["stage"], t["origin"], t["kept"], t["score"]) for t in tb]
    assert all(np.allclose(t["start"], u["start"], atol=1e-9) for t, u in zip(ta, tb))


@pytest.mark.parametrize("rounds", ["confirm", "local", "ransac"])
def test_a_rescued_pose_stands_and_the_lines_confirm_it(monkeypatch, rounds):
    """After the rescue, the narrowing rounds leave its pose as it is and only count the lines that hold it
    (``rounds="confirm"``); "local" narrows it by local refinements at the strong gates, "ransac" by RANSAC rounds."""
    import localization.query as Q

    T, ends, l2, pm = _scene(1)
    calls, rescued = [], []
    pnpl, near, local, rescue_pose_ = Q.pnpl_pose, Q.pnpl_near_start, Q.local_pnpl_pose, Q.rescue_pose
    monkeypatch.setattr(Q, "pnpl_pose", lambda *a, **k: calls.append("ransac") or pnpl(*a, **k))
    monkeypatch.setattr(Q, "pnpl_near_start", lambda *a, **k: calls.append("near") or near(*a, **k))
    monkeypatch.setattr(Q, "local_pnpl_pose", lambda *a, **k: calls.append("local") or local(*a, **k))
    monkeypatch.setattr(Q, "rescue_pose", lambda *a, **k: rescued.append(rescue_pose_(*a, **k)) or rescued[-1])
    rescue = LineRescueConfig(weak_inliers=12, prior_views=2, rounds=rounds,
                              hypotheses=replace(LineRescueConfig().hypotheses, keep=0))
    conf = replace(LocalizationConfig(), line_rescue=rescue)
    rec, detail = Q.localize_matches(pm, l2, CAM, LineQuery(ends), conf, priors=[_off(T, 60, 40), _off(T, 6, 2)],
                                     cam_from_world_gt=T)
    pl = rec["point+line"]
    assert pl["success"] and pl["rescued"] and pose_errors(T, np.array(pl["cam_from_world"]))[0] < 0.005
    after = calls[2:]  # after the rescue's RANSAC from each of the two starts
    assert calls[:2] == ["near", "near"]
    if rounds == "confirm":
        assert after == []
        np.testing.assert_array_equal(np.array(pl["cam_from_world"]), rescued[0]["cam_from_world"])
        # the line matches of the last strong gate at that pose, nearly all within the line threshold, all right
        m, inl = detail["line_matches"], detail["line_inliers"]
        assert pl["n_line_inliers"] == inl.sum() >= 0.9 * len(m["line_idx"]) >= 0.9 * rescue.min_final_lines
        assert pl["n_line_inliers_correct"] == pl["n_line_inliers"]
    elif rounds == "local":
        assert after == ["local"] * len(conf.strong_gates)
    else:
        assert after == ["ransac"] * len(conf.line_gates)


def test_unknown_rescue_solver_is_refused():
    T, ends, l2, pm = _scene(0)
    conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(solver="icp"))
    with pytest.raises(ValueError, match="icp"):
        rescue_pose(pm, l2, [T], LineQuery(ends), CAM, conf)


def test_coarse_scoring_pass_keeps_the_best_hypothesis_and_narrows_the_second_pass():
    from localization import hypotheses as H

    T, ends, l2, pm = _scene(3, n_lines=60, n_pts=6)
    p2d = pm.p2d[:5].copy()
    p2d[3:] += [[80, -40], [-60, 70]]
    sizes = []
    score = H.LineEvidence.score

    def spy(self, poses, lines3d):
        sizes.append((len(poses), len(lines3d)))
        return score(self, poses, lines3d)

    H.LineEvidence.score = spy
    try:
        one = H.line_verified_poses(p2d, pm.p3d[:5], l2, ends, CAM, H.HypothesisConfig(box_margin=5.0, coarse_lines=0))
        n_one = len(sizes)
        two = H.line_verified_poses(p2d, pm.p3d[:5], l2, ends, CAM,
                                    H.HypothesisConfig(box_margin=5.0, coarse_lines=20, coarse_keep=4))
    finally:
        H.LineEvidence.score = score
    assert n_one == 1 and sizes[1][1] == 20 and sizes[2] == (4, 60)
    assert pose_errors(T, one[0])[0] < 1e-6 and pose_errors(T, two[0])[0] < 1e-6


def test_a_narrowing_round_that_jumps_beyond_max_line_step_is_not_taken(monkeypatch):
    """The narrowing rounds refine a pose: a RANSAC solution far from the round's start is refused, and the query
    keeps the pose of the last round that stayed within the step (here the point-only pose)."""
    import localization.query as P

    T, ends, l2, pm = _scene(2, n_pts=30)
    points = _Points(pm, _Model({}))
    lq = LineQuery(ends)
    real = P.pnpl_pose
    calls = []

    def jumping(*a, **k):  # the first round's RANSAC lands 1 m away with every line "inlier"
        r = real(*a, **k)
        if not calls and r["success"]:
            r = {**r, "cam_from_world": _off(r["cam_from_world"], 100, 0)}
        calls.append(r)
        return r

    monkeypatch.setattr(P, "pnpl_pose", jumping)
    free = localize_query("q", CAM, points, l2, lq, LocalizationConfig(max_line_step=()))
    assert pose_errors(T, np.array(free["point+line"]["cam_from_world"]))[0] > 0.5  # the jump is taken, never undone
    calls.clear()
    guarded = localize_query("q", CAM, points, l2, lq, LocalizationConfig())  # the default: 0.3 m / 5 deg
    pl = guarded["point+line"]
    assert pl["success"] and not pl["used_lines"] and len(calls) == 1  # refused, and the rounds stop there
    assert pl["cam_from_world"] == guarded["point"]["cam_from_world"]
    assert pose_errors(T, np.array(pl["cam_from_world"]))[0] < 0.01


def test_a_rescue_no_narrowing_round_confirms_is_no_pose(monkeypatch):
    """A rescued start is a pose only once a narrowing round takes it with enough line inliers (otherwise they were
    nearly always wrong): otherwise the query fails with the reason, instead of returning the rescue's guess."""
    import localization.query as Q

    T, ends, l2, pm = _scene(3)
    guess = {"cam_from_world": _off(T, 40, 10), "inliers": np.ones(len(pm), bool), "n_inliers": len(pm),
             "n_line_inliers": 9, "success": True}
    monkeypatch.setattr(Q, "rescue_pose", lambda *a, **k: guess)
    unconfirmed = lambda pm, l2, T, *a, **k: (T, None, None, False, None)  # noqa: E731
    monkeypatch.setattr(Q, "refine_with_lines", unconfirmed)
    monkeypatch.setattr(Q, "confirm_with_lines", unconfirmed)
    rec, detail = Q.localize_matches(pm, l2, CAM, LineQuery(ends), LocalizationConfig())
    pl = rec["point+line"]
    assert not pl["success"] and pl["rescued"] and "not confirmed" in pl["reason"] and not detail["point_line_inliers"].any()
    def rounds_keeping(n_inliers):
        m = {"line_idx": np.arange(30), "lines2d": np.zeros((30, 2, 2)), "lines3d": np.zeros((30, 2, 3))}
        return lambda pm, l2, T, *a, **k: (T, m, np.arange(30) < n_inliers, True, None)

    # confirmed, but held by fewer line inliers than ``min_final_lines``: still no pose, with the count
    held = replace(LocalizationConfig(), line_rescue=LineRescueConfig(min_final_lines=20))
    monkeypatch.setattr(Q, "confirm_with_lines", rounds_keeping(19))
    pl = Q.localize_matches(pm, l2, CAM, LineQuery(ends), held)[0]["point+line"]
    assert not pl["success"] and pl["rescued"] and "19 line inliers < 20" in pl["reason"]
    monkeypatch.setattr(Q, "confirm_with_lines", rounds_keeping(20))
    assert Q.localize_matches(pm, l2, CAM, LineQuery(ends), held)[0]["point+line"]["success"]
    default = LocalizationConfig()  # 6, the rescue's own bar
    monkeypatch.setattr(Q, "confirm_with_lines", rounds_keeping(6))
    assert Q.localize_matches(pm, l2, CAM, LineQuery(ends), default)[0]["point+line"]["success"]
    monkeypatch.setattr(Q, "confirm_with_lines", rounds_keeping(5))
    assert not Q.localize_matches(pm, l2, CAM, LineQuery(ends), default)[0]["point+line"]["success"]
    off = replace(LocalizationConfig(), line_rescue=LineRescueConfig(min_final_lines=0))
    assert Q.localize_matches(pm, l2, CAM, LineQuery(ends), off)[0]["point+line"]["success"]


def test_a_rescued_pose_must_keep_a_share_of_the_querys_lines(monkeypatch):
    """In a view of hundreds of lines a wrong pose lays a dozen map lines on detections by chance: a rescued pose must
    keep ``min_final_share`` of the query's lines of ``min_length_px`` or more (and at least ``min_final_lines``)."""
    import localization.query as Q

    T, ends, l2, pm = _scene(3, n_lines=250)
    n_long = int((np.linalg.norm(l2[:, 2:] - l2[:, :2], axis=1) >= LineRescueConfig().min_length_px).sum())
    bar = int(np.ceil(0.08 * n_long))
    assert bar > LineRescueConfig().min_final_lines
    guess = {"cam_from_world": _off(T, 2, 1), "inliers": np.ones(len(pm), bool), "n_inliers": len(pm),
             "n_line_inliers": 40, "success": True}
    monkeypatch.setattr(Q, "rescue_pose", lambda *a, **k: guess)
    m = {"line_idx": np.arange(60), "lines2d": np.zeros((60, 2, 2)), "lines3d": np.zeros((60, 2, 3))}
    for kept, share, ok in ((bar, 0.08, True), (bar - 1, 0.08, False), (bar - 1, 0.0, True)):
        monkeypatch.setattr(Q, "confirm_with_lines", lambda *a, k=kept: (a[3], m, np.arange(60) < k, True, None))
        conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(min_final_share=share))
        pl = Q.localize_matches(pm, l2, CAM, LineQuery(ends), conf)[0]["point+line"]
        assert pl["success"] == ok and pl["rescued"]
        if not ok:
            assert f"{bar - 1} line inliers < {bar} in its last narrowing round (8% of the query's lines" in pl["reason"]
