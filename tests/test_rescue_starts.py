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


@pytest.mark.parametrize("solver", ["ransac", "refine"])
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
    assert stage0[1]["kept"] and stage0[1]["score"] > stage0[0]["score"]
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


def test_no_trace_no_change():
    T, ends, l2, pm = _scene(2)
    points = _Points(pm, _Model({"db1": _off(T, 6, 2)}))
    conf = replace(LocalizationConfig(), line_rescue=LineRescueConfig(weak_inliers=12, prior_views=1))
    a = localize_query("q", CAM, points, l2, LineQuery(ends), conf)
    b = localize_query("q", CAM, points, l2, LineQuery(ends), conf, trace=[])
    # (PoseLib repeats a call up to the last digits within one process, not bit for bit)
    np.testing.assert_allclose(a["point+line"]["cam_from_world"], b["point+line"]["cam_from_world"], atol=1e-6)
