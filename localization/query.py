"""One query's poses: the point-only pose, then the line stage (the line query and PnPL refinement in narrowing
gates, the rescue of weak queries from several starting poses). :func:`localize_matches` is the one implementation
behind the benchmark loop (:func:`localize_query`, :mod:`localization.pipeline`) and the per-query API
(:class:`localization.api.Localizer`).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Optional

import numpy as np

from lipmap import InputError
from lipmap import geometry as geo
from lipmap.poses import pose_errors

from .config import LocalizationConfig
from .estimate import estimate_pose_points, inliers_at, local_pnpl_pose, pnpl_pose, refine_pnpl_pose, subsample_matches
from .hypotheses import line_verified_poses
from .linequery import LineQuery, LineQueryConfig, correct_line_matches
from .near_ransac import pnpl_near_start
from .parallel import mapped


def make_line_query(linemap, conf: LocalizationConfig, where="line map") -> LineQuery:
    """The :class:`LineQuery` of ``linemap`` for ``conf``; a raycast query on a map without planes is refused here,
    once, rather than by every query alone (``where`` names the map in the error)."""
    lq = LineQuery.from_linemap(linemap)
    if conf.line_query.method == "raycast" and len(linemap) and (lq.caster is None or lq.edge_line is None):
        raise InputError(f"the raycast line query needs a line map with planes; this one was made by "
                         f"{linemap.metadata.get('method', '?')!r} and has none", where,
                         "use --line-query projection or --method lipmap")
    return lq


def localize_query(name, camera, points, lines2d, lq: LineQuery, conf: LocalizationConfig, cam_from_world_gt=None,
                   trace: Optional[list] = None, priors=()) -> dict:
    """Point-only and point+line poses of one query of a benchmark run, from its point source. Never raises:
    failures are recorded.

    The point matches come from ``points.matches_for(name)``, limited to ``conf.max_point_matches`` (a seeded draw),
    and the poses of its ``LineRescueConfig.prior_views`` best retrieved database images are starts of the rescue;
    the rest is :func:`localize_matches`. ``priors`` (poses (4, 4)) are starts of the rescue before those. ``trace``
    (a list) also receives the point matches as ``{"point_matches": pm}``.
    """
    rec = {"name": name, "point": {"success": False}, "point+line": {"success": False}}
    t0 = time.perf_counter()
    try:
        pm = points.matches_for(name)
    except InputError as e:
        rec["error"] = str(e)
        return rec
    idx = subsample_matches(len(pm), conf.max_point_matches, conf.seed if conf.match_seed is None else conf.match_seed, name)
    pm = pm.subset(idx)
    if trace is not None:
        trace.append({"point_matches": pm})
    rc = conf.line_rescue
    views = retrieved_poses(name, points, max(rc.prior_views, rc.hypotheses.lines_first.views))
    return localize_matches(pm, lines2d, camera, lq, conf, name, priors=[*priors, *views[:rc.prior_views]],
                            views=views[:rc.hypotheses.lines_first.views], cam_from_world_gt=cam_from_world_gt,
                            trace=trace, t0=t0)[0]


def retrieved_poses(name: str, points, k: int) -> list:
    """The poses (4, 4) of the ``k`` best database images retrieved for query ``name`` by a point source that knows
    them (``retrieved_for`` and a ``model``)."""
    retrieved = getattr(points, "retrieved_for", None)
    model = getattr(points, "model", None)
    if retrieved is None or model is None or k <= 0:
        return []
    return [model.cam_from_world(db) for db in retrieved(name)[:k] if db in model]


def localize_matches(pm, lines2d, camera, lq: LineQuery, conf: LocalizationConfig, name: str = "query",
                     priors=(), views=(), line_matches: Optional[dict] = None, cam_from_world_gt=None,
                     trace: Optional[list] = None, t0: Optional[float] = None) -> tuple:
    """Point-only and point+line poses of one query from its 2D-3D point matches and 2D lines. Never raises for a
    bad query: failures are recorded.

    The line stage starts from the point-only pose. A weak one (fewer than ``LineRescueConfig.weak_inliers``
    inliers, or none) goes through the rescue first, whose starts are that pose, ``priors`` and the line-verified
    P3P hypotheses; with the rescue off, the first of ``priors`` stands in for a missing point-only pose.

    Args:
        pm: :class:`~localization.points.PointMatches` (p2d COLMAP pixels, p3d world).
        lines2d: :math:`(L, 4)` query segments, COLMAP pixels.
        priors: starting poses :math:`(4, 4)` cam_from_world for a weak query's lines (a prior pose, the retrieved
            images' poses).
        views: poses :math:`(4, 4)` near the query's rotation (the retrieved images'), for the poses from lines of a
            query with too few point matches for P3P (:mod:`localization.linesfirst`); ``priors`` serve too.
        line_matches: 2D-3D line matches made elsewhere (:func:`given_line_matches`): the line query is skipped and
            one PnPL RANSAC over the points and these lines gives the point+line pose.
        cam_from_world_gt: with it, the line matches of the last refinement (and its PnPL line inliers) are checked
            (:func:`~localization.linequery.correct_line_matches`) - after the timing, so the check costs nothing.
        trace: a list receiving the line rescue's starts and their outcomes (:func:`rescue_pose`).
        t0: ``time.perf_counter()`` when the query started (default: now); its times count from there.

    Returns:
        (record, detail): the journal record (``point`` and ``point+line`` dicts) and the arrays behind it,
        ``point_inliers`` (N,) bool, ``point_line_inliers`` (N,) bool, ``line_matches`` (the line query's dict:
        ``lines2d`` (M, 2, 2), ``lines3d`` (M, 2, 3), ``query_idx`` (M,), ``line_idx`` (M,); None when no line round
        gave the pose) and ``line_inliers`` (M,) bool.
    """
    t0 = time.perf_counter() if t0 is None else t0
    rec = {"name": name, "point": {"success": False}, "point+line": {"success": False}}
    detail = {"point_inliers": np.zeros(len(pm), bool), "point_line_inliers": np.zeros(len(pm), bool),
              "line_matches": None, "line_inliers": np.zeros(0, bool)}
    est = estimate_pose_points(pm.p2d, pm.p3d, camera, replace(conf.point_pose, seed=conf.seed))
    t_point = (time.perf_counter() - t0) * 1000
    rec["point"] = {"success": bool(est["success"]), "n_matches": len(pm), "n_inliers": int(est["n_inliers"]),
                    "ms": t_point, "cam_from_world": _T(est["cam_from_world"] if est["success"] else None)}
    if not est["success"]:
        rec["point"]["reason"] = est.get("reason")
    detail["point_inliers"] = np.asarray(est["inliers"], bool)
    t1 = time.perf_counter()
    T = est["cam_from_world"] if est["success"] else None
    plconf = replace(conf.point_line_pose, seed=conf.seed)
    rescue = conf.line_rescue
    weak = T is None or est["n_inliers"] < rescue.weak_inliers
    priors = [np.asarray(P, dtype=float) for P in priors]
    rescued = False
    if line_matches is None and rescue.weak_inliers > 0 and weak:
        starts = ([np.asarray(est["cam_from_world"], dtype=float)]
                  if est.get("cam_from_world") is not None and np.all(np.isfinite(est["cam_from_world"])) else [])
        starts += priors
        if rescue.hypotheses.keep > 0:
            hc = rescue.hypotheses
            dirs = lq.dominant_directions(hc.n_map_lines, hc.min_support, hc.map_directions, hc.direction_tol_deg)
            starts += line_verified_poses(pm.p2d, pm.p3d, lines2d, lq.scoring_lines(hc.n_map_lines, hc.min_support),
                                          camera, hc, seed=conf.seed, directions=dirs,
                                          views=list(priors) + [np.asarray(V, dtype=float) for V in views])
        r = rescue_pose(pm, lines2d, starts, lq, camera, conf, trace)
        if r is not None:
            T, rescued = r["cam_from_world"], True
            plconf = replace(plconf, max_reproj_error=rescue.max_point_error)
            detail["point_line_inliers"] = np.asarray(r["inliers"], bool)
    elif weak and priors and (T is None or line_matches is not None):
        T = priors[0]
    # a start the points did not give (the rescue's, or a prior) is a pose only once a narrowing round confirms it:
    # on the held-out split with 3-10 matches, 1 of 92 unconfirmed rescues lay within 5 cm
    unconfirmed = rescued or (T is not None and not est["success"])
    t_rescue = (time.perf_counter() - t1) * 1000
    if T is None and line_matches is None:
        why = "no point-only pose, and the line rescue found none" if rescue.weak_inliers > 0 else "no point-only pose to start from"
        rec["point+line"] = {"success": False, "reason": why, "ms": t_point + (time.perf_counter() - t1) * 1000,
                             "line_stage_ms": (time.perf_counter() - t1) * 1000, "rescue_ms": t_rescue}
        return rec, detail
    if not rescued:
        detail["point_line_inliers"] = detail["point_inliers"]
    # the line inliers a rescued pose must keep in its last round: a right pose explains a share of the query's lines
    final_bar = max(rescue.min_final_lines, int(np.ceil(rescue.min_final_share * np.count_nonzero(
        geo.segment_lengths(np.asarray(lines2d, dtype=float).reshape(-1, 4)) >= rescue.min_length_px))))
    if line_matches is not None:
        T, m, inliers, used_lines, pl_inl = _pose_from_given_lines(pm, line_matches, T, camera, plconf)
    else:
        if rescued and rescue.rounds == "confirm":
            # the rescue's last stage refined the pose; tighter gates would move it farther from the truth more often
            T, m, inliers, used_lines, pl_inl = confirm_with_lines(pm, lines2d, T, camera, lq, conf, plconf)
        else:
            # a strong pose, or a rescued one with rounds="local", narrows without RANSAC, which only pulls it about
            local = (rescued and rescue.rounds == "local") or (
                not rescued and est["success"] and 0 < conf.strong_inliers <= est["n_inliers"])
            T, m, inliers, used_lines, pl_inl = refine_with_lines(pm, lines2d, T, camera, lq, conf, plconf, local)
        if rescued and est["success"] and (not used_lines or int(inliers.sum()) < final_bar):
            # a rescued pose no narrowing round confirms, or few lines hold, is a guess (below); the point-only pose
            # stands instead, narrowed as if no rescue ran
            rescued, unconfirmed, plconf = False, False, replace(conf.point_line_pose, seed=conf.seed)
            detail["point_line_inliers"] = detail["point_inliers"]
            T, m, inliers, used_lines, pl_inl = refine_with_lines(pm, lines2d, est["cam_from_world"], camera, lq, conf,
                                                                  plconf)
    if pl_inl is not None:
        detail["point_line_inliers"] = pl_inl
    t_line = (time.perf_counter() - t1) * 1000
    # a rescued pose held by few lines is a guess (on the held-out split nearly none with fewer than 20 line inliers
    # in the last round lay within 5 cm; docs/localization.md): without a point-only pose, the query fails
    n_held = int(inliers.sum()) if used_lines else 0
    weakly_held = rescued and used_lines and n_held < final_bar
    # so is a weak point-only pose that the rescue could not replace and as few lines hold: on the held-out split each
    # lay metres off (10 matches: 19 of 250; every match: 3 of 50), and a failure says so where a pose would not
    weak_guess = (line_matches is None and rescue.weak_inliers > 0 and rescue.min_final_lines > 0 and weak
                  and not rescued and est["success"] and n_held < rescue.min_final_lines)
    if T is None or (unconfirmed and not used_lines) or weakly_held or weak_guess:
        why = ("no pose from the point and line matches" if T is None else
               f"a weak point-only pose ({int(est['n_inliers'])} inliers < {rescue.weak_inliers}) that the line "
               f"rescue did not replace, held by {n_held} line inliers < {rescue.min_final_lines}" if weak_guess else
               f"the line rescue's pose kept {n_held} line inliers < {final_bar} in its last narrowing round "
               f"({rescue.min_final_share:.0%} of the query's lines, at least {rescue.min_final_lines})" if weakly_held else
               "the line rescue's pose was not confirmed by a narrowing round" if rescued else
               "the starting pose was not confirmed by a narrowing round")
        rec["point+line"] = {"success": False, "reason": why, "ms": t_point + t_line, "line_stage_ms": t_line,
                             "rescue_ms": t_rescue, "rescued": rescued}
        detail["point_line_inliers"] = np.zeros(len(pm), bool)
        return rec, detail
    n_lm = len(m["line_idx"]) if used_lines else 0
    rec["point+line"] = {"success": True, "used_lines": used_lines, "rescued": rescued, "n_line_matches": n_lm,
                         "n_line_inliers": int(inliers.sum()) if used_lines else 0,
                         "n_query_lines": int(len(lines2d)), "ms": t_point + t_line, "line_stage_ms": t_line,
                         "rescue_ms": t_rescue, "cam_from_world": _T(T)}
    if cam_from_world_gt is not None and used_lines:
        ok = correct_line_matches(m["lines2d"], m["lines3d"], cam_from_world_gt, camera)
        rec["point+line"]["n_line_matches_correct"] = int(ok.sum())
        rec["point+line"]["n_line_inliers_correct"] = int((ok & inliers).sum())
    if used_lines:
        detail["line_matches"] = m
        detail["line_inliers"] = np.asarray(inliers, bool)
    return rec, detail


def refine_with_lines(pm, lines2d, T, camera, lq: LineQuery, conf: LocalizationConfig, plconf,
                      strong: bool = False) -> tuple:
    """The narrowing rounds from pose ``T``: query the map's lines, refine with PnPL, repeat with narrower gates
    (:func:`line_query_schedule`); a round that fails or steps beyond ``conf.max_line_step`` ends them. A ``strong``
    query (``LocalizationConfig.strong_inliers``, or a rescued one) takes ``conf.strong_gates``, each round a local
    refinement.

    Returns:
        (pose, matches of the last round taken or None, their line inliers, whether a round was taken, the point
        inliers (N,) of that round or None).
    """
    m, inliers, used_lines, pl_inl = None, None, False, None
    visible = lq.visible_lines(T, camera, conf.line_query.occlusion_tol) if conf.line_query.method == "projection" else None
    for lconf in line_query_schedule(conf, strong):
        tried = lq.match(lines2d, T, camera, lconf, visible)
        if strong:
            r = local_pnpl_pose(pm.p2d, pm.p3d, tried["lines2d"], tried["lines3d"], camera, T, plconf)
        else:
            r = pnpl_pose(pm.p2d, pm.p3d, tried["lines2d"], tried["lines3d"], camera, initial=T, conf=plconf)
        if r["success"] and conf.max_line_step and not _within(r["cam_from_world"], T, *conf.max_line_step):
            r = {**r, "success": False}
        if not r["success"]:
            break
        T, m, inliers, used_lines = r["cam_from_world"], tried, r["line_inliers"], True
        pl_inl = np.asarray(r["inliers"], bool)
    return T, m, inliers, used_lines, pl_inl


def confirm_with_lines(pm, lines2d, T, camera, lq: LineQuery, conf: LocalizationConfig, plconf) -> tuple:
    """The lines that hold pose ``T`` without moving it: the line query at the last strong gate from ``T``, and the
    matches and points within ``plconf``'s thresholds there. For a rescued pose, which the rescue's last stage
    already refined.

    Returns:
        the tuple of :func:`refine_with_lines` with ``T`` itself; a round counts as taken when at least
        ``plconf.min_lines`` line matches were found.
    """
    lconf = line_query_schedule(conf, strong=True)[-1]
    visible = lq.visible_lines(T, camera, conf.line_query.occlusion_tol) if lconf.method == "projection" else None
    m = lq.match(lines2d, T, camera, lconf, visible)
    if len(m["line_idx"]) < plconf.min_lines:
        return T, None, None, False, None
    pt_inl, line_inl = inliers_at(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], T, camera, plconf.max_reproj_error,
                                   plconf.max_line_error)
    return T, m, line_inl, True, pt_inl


def given_line_matches(lines2d, lines3d, line_ids=None) -> dict:
    """2D-3D line matches made elsewhere, in the line query's layout.

    Args:
        lines2d: :math:`(M, 4)` or :math:`(M, 2, 2)` query segments (COLMAP pixels).
        lines3d: :math:`(M, 2, 3)` their 3D segments (world), or :math:`(K, 2, 3)` with ``line_ids``.
        line_ids: :math:`(M,)` index of each 2D segment's 3D line in ``lines3d`` (LIMAP's ``l3d_ids``); None: row i
            of ``lines3d`` is segment i's.

    Returns:
        dict with ``lines2d`` (M, 2, 2), ``lines3d`` (M, 2, 3), ``query_idx`` (M,) = 0..M-1, ``line_idx`` (M,): the ids
        (-1 without them).
    """
    l2 = np.asarray(lines2d, dtype=np.float64)
    l3 = np.asarray(lines3d, dtype=np.float64)
    if l2.size % 4 or l3.size % 6:
        raise InputError(f"line matches need (M, 4) or (M, 2, 2) 2D segments and (M, 2, 3) 3D segments, "
                         f"got {l2.shape} and {l3.shape}")
    l2, l3 = l2.reshape(-1, 2, 2), l3.reshape(-1, 2, 3)
    if line_ids is None:
        if len(l2) != len(l3):
            raise InputError(f"{len(l2)} 2D segments for {len(l3)} 3D segments (give line_ids to index the 3D lines)")
        ids = np.full(len(l2), -1, np.int64)
    else:
        ids = np.asarray(line_ids, dtype=np.int64).reshape(-1)
        if len(ids) != len(l2) or (len(ids) and (ids.min() < 0 or ids.max() >= len(l3))):
            raise InputError(f"line_ids must give one index in [0, {len(l3)}) per 2D segment ({len(l2)}), got "
                             f"{len(ids)} ids in [{ids.min() if len(ids) else '-'}, {ids.max() if len(ids) else '-'}]")
        l3 = l3[ids]
    return {"lines2d": l2, "lines3d": l3, "query_idx": np.arange(len(l2), dtype=np.int64), "line_idx": ids}


def _pose_from_given_lines(pm, m: dict, T, camera, plconf) -> tuple:
    """One PnPL RANSAC over the points and the given line matches (from ``T`` when there is one); the tuple of
    :func:`refine_with_lines`, whose pose is None when neither the points nor the lines give one."""
    r = pnpl_pose(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, initial=T, conf=plconf)
    if not r["success"]:
        return T, None, None, False, None
    return r["cam_from_world"], m, r["line_inliers"], True, np.asarray(r["inliers"], bool)


def rescue_pose(pm, lines2d, priors: list, lq: LineQuery, camera, conf: LocalizationConfig,
                trace: Optional[list] = None) -> Optional[dict]:
    """The best PnPL pose over ``priors`` with wide-gate line candidates (:class:`~localization.config.LineRescueConfig`),
    or None.

    With ``solver="near"`` each start's wide-gate candidates (``gates[0]``) go through a PnPL RANSAC about the start
    (:func:`~localization.near_ransac.pnpl_near_start`), with ``solver="ransac"`` through PoseLib's, which may land
    far from the start; each pose it keeps then goes through the later ``gates`` as robust refinements
    (:func:`refine_stages`), and the pose with the most point + line inliers at the last gate wins. A RANSAC per later
    stage only let minimal samples of near-parallel lines pull a right pose about, even one started at the true pose
    (docs/localization.md). With ``solver="refine"`` every start goes through ``refine_gates`` alone.
    ``trace`` (a list) receives one dict per start and stage: ``stage``, ``start`` and ``result`` (the solver's
    dict, None when a stage found too few lines), ``kept`` (whether it passed ``min_line_inliers``), ``score`` and
    ``origin`` (the index in ``trace`` of the stage-0 entry the pose comes from). The starts run side by side on
    ``LineRescueConfig.threads`` threads; the pose and the trace are the same on any number.
    """
    rc = conf.line_rescue
    priors = distinct_poses(priors, rc.same_pose_m, rc.same_pose_deg)
    lines2d = longest_lines(lines2d, rc.max_query_lines)
    trace = [] if trace is None else trace
    if rc.solver == "refine":
        firsts, later = [(None, T, None) for T in priors], rc.refine_gates
    elif rc.solver in ("ransac", "near"):
        plconf = replace(conf.point_line_pose, seed=conf.seed, max_iterations=rc.max_iterations,
                         max_reproj_error=rc.max_point_error,
                         min_iterations=min(conf.point_line_pose.min_iterations, rc.max_iterations))
        qconf, firsts, later = _rescue_query(conf, rc.gates[0]), [], rc.gates[1:]

        def first_stage(T0):
            m = lq.match(lines2d, T0, camera, qconf)
            if rc.solver == "near":
                return pnpl_near_start(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, T0, rc.near, plconf)
            return pnpl_pose(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, conf=plconf)

        for T0, r in zip(priors, mapped(first_stage, priors, rc.threads)):
            kept = r["success"] and r["n_line_inliers"] >= rc.min_line_inliers
            trace.append({"stage": 0, "start": T0, "result": r, "kept": kept,
                          "score": r["n_inliers"] + r["n_line_inliers"] if kept else -1, "origin": len(trace)})
            if kept:
                firsts.append((len(trace) - 1, r["cam_from_world"], r))
    else:
        raise ValueError(f"unknown line rescue solver {rc.solver!r} (ransac, near, refine)")
    if later:
        # each pose's stages trace into a list of their own, joined in the starts' order: the same trace on any thread
        def stages(first):
            own = []
            return refine_stages(pm, lines2d, first[1], lq, camera, conf, later, own, -1), own

        refined = mapped(stages, firsts, rc.threads)
    best, best_score = None, -1
    for k, (origin, T, r) in enumerate(firsts):
        if later:
            r, own = refined[k]
            origin = len(trace) if origin is None else origin
            trace.extend({**t, "origin": origin} for t in own)
            kept = r is not None and r["n_line_inliers"] >= rc.min_line_inliers
            score = r["n_inliers"] + r["n_line_inliers"] if kept else -1
            trace[-1].update(kept=kept, score=score)
        else:
            score = r["n_inliers"] + r["n_line_inliers"]
        if score > best_score:
            best, best_score = r, score
    return best


def refine_stages(pm, lines2d, T, lq: LineQuery, camera, conf: LocalizationConfig, gates, trace: list,
                  origin: int) -> Optional[dict]:
    """A pose through the rescue's refinement stages: per gate (px, deg[, candidates]) the nearest map lines from the
    current pose, then a robust refinement (Cauchy, scale ``refine_scale`` x the gate) of the points and those lines,
    without RANSAC. The map lines the first pose sees (the plane occlusion test) serve every stage: they move it by
    centimetres. Returns the last stage's :func:`~localization.estimate.refine_pnpl_pose` dict, or None when a stage
    finds too few lines or no pose; each stage is appended to ``trace`` (stage numbers after the RANSAC's)."""
    rc = conf.line_rescue
    vis, r = lq.visible_lines(T, camera, conf.line_query.occlusion_tol), None
    first = 0 if rc.solver == "refine" else 1
    for k, gate in enumerate(gates):
        m = lq.match(lines2d, T, camera, _rescue_query(conf, gate), vis)
        r = None
        if len(m["line_idx"]) >= conf.point_line_pose.min_lines:
            r = refine_pnpl_pose(pm.p2d, pm.p3d, m["lines2d"], m["lines3d"], camera, T,
                                 point_scale=rc.max_point_error / 2, line_scale=rc.refine_scale * gate[0],
                                 max_reproj_error=rc.max_point_error, max_line_error=conf.point_line_pose.max_line_error)
        trace.append({"stage": first + k, "start": T, "result": r, "kept": False, "score": -1, "origin": origin})
        if r is None or not r["success"]:
            return None
        T = r["cam_from_world"]
    return r


def longest_lines(lines2d: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` longest of the segments ``lines2d`` (N, 4), in their order (all when ``k`` is 0 or N <= k)."""
    lines2d = np.asarray(lines2d, dtype=float).reshape(-1, 4)
    if k <= 0 or len(lines2d) <= k:
        return lines2d
    return lines2d[np.sort(np.argsort(-geo.segment_lengths(lines2d), kind="stable")[:k])]


def _rescue_query(conf: LocalizationConfig, gate) -> LineQueryConfig:
    """The line query of one rescue stage, ``gate`` = (px, deg[, candidates])."""
    rc = conf.line_rescue
    px, deg, *k = gate
    return replace(conf.line_query, method="projection", max_dist_px=float(px), max_angle_deg=float(deg),
                   max_candidates=int(k[0]) if k else rc.candidates, min_margin=0.0, one_to_one=False,
                   min_length_px=max(rc.min_length_px, conf.line_query.min_length_px))


def _within(U: np.ndarray, T: np.ndarray, max_m: float, max_deg: float) -> bool:
    dt, dr = pose_errors(U, T)
    return dt <= max_m and dr <= max_deg


def distinct_poses(poses: list, max_m: float, max_deg: float) -> list:
    """``poses`` without those within ``max_m`` and ``max_deg`` of an earlier one (the same start twice costs a RANSAC
    and finds the same lines)."""
    out = []
    for T in poses:
        if not any(_within(U, T, max_m, max_deg) for U in out):
            out.append(T)
    return out


def line_query_schedule(conf: LocalizationConfig, strong: bool = False) -> list:
    """The :class:`LineQueryConfig` of each query-and-refine iteration (of a strong query's, with ``strong``)."""
    gates = conf.strong_gates if strong else conf.line_gates
    if gates:
        return [replace(conf.line_query, max_dist_px=float(d), max_angle_deg=float(a)) for d, a in gates]
    return [conf.line_query] * max(1, conf.line_iters)


def _T(T):
    return None if T is None else np.asarray(T).tolist()
