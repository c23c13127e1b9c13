"""benchmarks/perf/bench_line_stage.py times the parts of the line stage without counting a part twice."""
from dataclasses import replace

import pytest

from conftest import benchmark_module
from test_line_rescue import CAM, _scene

from localization.linequery import LineQuery
from localization.config import LineRescueConfig, LocalizationConfig
from localization.query import localize_query


def _bench():
    return benchmark_module("perf/bench_line_stage.py")


class _Points:
    def __init__(self, pm):
        self.pm = pm

    def matches_for(self, name):
        return self.pm


@pytest.mark.parametrize("solver", ["near", "ransac", "refine"])
def test_parts_add_up_to_at_most_the_line_stage(solver):
    import localization.query as P

    bench = _bench()
    T, ends, l2, pm = _scene(2, n_pts=6)
    lq = LineQuery(ends)
    # on one thread: on several, the starts' parts overlap one another and sum to more than the stage
    rescue = LineRescueConfig(weak_inliers=12, solver=solver, gates=((30, 5, 1), (15, 3, 1)), threads=1,
                              hypotheses=replace(LineRescueConfig().hypotheses, box_margin=5.0))
    conf = replace(LocalizationConfig(), line_rescue=rescue)
    originals = (P.rescue_pose, P.pnpl_pose, lq.match, lq.visible_lines)
    timer = bench.PartTimer(lq)
    try:
        rec = localize_query("q", CAM, _Points(pm), l2, lq, conf)
        parts = timer.take()
    finally:
        timer.restore()
    assert (P.rescue_pose, P.pnpl_pose, lq.match, lq.visible_lines) == originals
    pl = rec["point+line"]
    assert pl["rescued"]
    # a rescued pose's narrowing round only confirms it: a line query, no PnPL
    assert {"hypotheses", "rescue query", "rescue PnPL", "visibility", "narrow query"} == set(parts)
    assert all(v > 0 for v in parts.values())
    assert sum(parts.values()) <= pl["line_stage_ms"]  # a visibility test inside a query is not counted twice
