"""The rescue's trace (localize_query(trace=...)) and benchmarks/rescue_starts.py's account of it."""
from dataclasses import replace

import numpy as np
import pytest

from conftest import benchmark_module
from test_line_rescue import CAM, _Model, _off, _Points, _scene

from lipmap.poses import pose_errors
from localization.linequery import LineQuery
from localization.config import LineRescueConfig, LocalizationConfig
from localization.query import localize_query


def _bench():
    return benchmark_module("rescue_starts.py")


@pytest.mark.parametrize("solver", ["near", "ransac", "refine"])
def test_trace_holds_every_start_and_the_outcome_is_checked_against_the_truth(solver):
    bench = _bench()
    T, ends, l2, pm = _scene(1)
    far, near = _off(T, 60, 40), _off(T, 6, 2)
    points = _Points(pm, _Model({"db1": far, "db2": near}))
    rescue = LineRescueConfig(weak_inliers=12, prior_views=2, solver=solver,
                              hypotheses=replace(LineRescueConfig().hypotheses, keep=0))  # the two retrieved starts only
    conf = replace(LocalizationConfig(), line_rescue=rescue)
    trace = []
    rec = localize_query("q", CAM, points, l2, LineQuery(ends), conf, trace=trace)
    np.testing.assert_array_equal(trace[0]["point_matches"].p2d, pm.p2d)  # the subset used (all three here)
    stage0 = [t for t in trace if t.get("stage") == 0]
    assert [t["start"].tolist() for t in stage0] == [far.tolist(), near.tolist()]
    # each start's last stage (its rescued pose) carries the score the choice is made on
    last = {t["origin"]: t for t in trace if "origin" in t}
    ends = [last[i] for i, t in enumerate(trace) if t.get("stage") == 0]
    assert ends[1]["kept"] and ends[1]["score"] > ends[0]["score"]
    assert all(t["stage"] == (len(rescue.gates) - 1 if solver != "refine" else len(rescue.refine_gates) - 1)
               for t in ends if t["kept"])
    o = bench.query_outcome(rec, trace, T, CAM, 6.0)
    assert o["right_points"] == 3 and o["starts"] == 2
    assert o["start_m"] == pytest.approx(pose_errors(T, near)[0]) and o["start_m"] < pose_errors(T, far)[0]
    assert o["best_pnpl_m"] < 0.005 and o["chosen_pnpl_m"] == o["best_pnpl_m"] and o["final_m"] < 0.005
    # a query the rescue does not see (strong points) has no outcome, and the shares count the others
    assert bench.query_outcome(rec, [{"point_matches": pm}], T, CAM, 6.0) is None
    s = bench.summarize([o, None, dict(o, right_points=2, final_m=0.2, start_m=0.5)])
    assert s["weak_queries"] == 2 and s["right_points_ge3"] == 50 and s["right_points_ge2"] == 100
    assert s["final_5cm"] == 50 and s["start_15cm"] == 50 and s["starts_per_query"] == 2
    assert bench.row("s", "lipmap", 10, s)[3:6] == ["2", "50 / 100 %", "0 / 50 %"]  # the near start is 7 cm off
    # the rescued poses that stood, split by their last round's line inliers
    assert o["final_lines"] == rec["point+line"]["n_line_inliers"] >= 20
    s = bench.summarize([o, dict(o, final_lines=8, final_m=0.3), dict(o, final_lines=12), dict(o, final_lines=-1)])
    assert (s["final_lines_few"], s["final_lines_few_5cm"], s["final_lines_many"]) == (2, 50, 1)
    assert bench.row("s", "lipmap", 10, s)[-1] == "2 (50 %) / 1 (100 %)"


def test_the_truth_as_a_start():
    """``priors`` of localize_query start the rescue before the retrieved images' poses: the benchmark's
    ``--truth-start`` puts the true pose there, and its outcome shows a start at 0 cm."""
    bench = _bench()
    T, ends, l2, pm = _scene(1)
    points = _Points(pm, _Model({"db1": _off(T, 60, 40)}))
    rescue = LineRescueConfig(weak_inliers=12, prior_views=1, hypotheses=replace(LineRescueConfig().hypotheses, keep=0))
    conf = replace(LocalizationConfig(), line_rescue=rescue)

    class _Scene:
        query = [type("V", (), {"name": "q", "camera": CAM, "cam_from_world": T})()]

    plain, truth = (bench.trace_scene(_Scene, points, LineQuery(ends), {"q": l2}, conf, [0], t)[0] for t in (False, True))
    assert plain["starts"] == 1 and plain["start_m"] > 0.3
    assert truth["starts"] == 2 and truth["start_m"] == 0 and truth["final_m"] < 0.005


def test_no_trace_no_change():
    T, ends, l2, pm = _scene(2)
    points = _Points(pm, _Model({"db1": _off(T, 6, 2)}))
    conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(weak_inliers=12, prior_views=1))
    a = localize_query("q", CAM, points, l2, LineQuery(ends), conf)
    b = localize_query("q", CAM, points, l2, LineQuery(ends), conf, trace=[])
    # (PoseLib repeats a call up to the last digits within one process, not bit for bit)
    np.testing.assert_allclose(a["point+line"]["cam_from_world"], b["point+line"]["cam_from_world"], atol=1e-6)
