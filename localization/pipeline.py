"""Per-scene localization benchmark: map (if needed), 2D-3D points, point-only pose, line query,
point+line pose, evaluation. Every step caches its artifact, stamped with the settings that made it;
per-query results go to a journal so an interrupted run resumes where it stopped.

    OUT/<dataset>/<scene>/
        map-<method>-<preset>-<digest>/         the line map of one mapping variant (lipmap.mapping.pipeline):
                                                linemap.h5, lines2d.h5, linemap.ply, renders
        planes-<preset>-<digest>/               planes.h5, planes.ply: one plane optimization, shared by the map
                                                variants that differ only after it (lipmap.mapping.joint)
        points-<preset>-<digest>/               SIFT features, pairs, matches, sfm model (built-in points)
        lines2d_query-<digest>.h5               2D lines of the queries (the mapping's detector)
        queries-<digest>.jsonl                  per-query journal of one configuration (resume)
        results_point.txt, results_point_line.txt   hloc format (name qw qx qy qz tx ty tz), latest run
        results.json                            per-query errors, inliers, timings; summary; which map
                                                and points the run used
    OUT/<dataset>/results.json, summary.md      all scenes, paper table beside ours
"""
from __future__ import annotations

import functools
import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
from tqdm import tqdm

from lipmap import InputError, logger
from lipmap.artifacts import digest, source_digest, views_key
from lipmap.imageio import write_text_atomic

from . import evaluate as ev
from . import points as pts
from .config import LocalizationConfig, check_config
from .hloc_outputs import HlocOutputs, as_hloc_outputs
from .linequery import LineQuery
from .query import localize_query, make_line_query


# hloc-format results of each method (name qw qx qy qz tx ty tz, cam_from_world)
RESULT_FILES = {"point": "results_point.txt", "point+line": "results_point_line.txt"}


def _read_journal(path: Path) -> dict:
    done = {}
    if not path.exists():
        return done
    for line in path.read_text().splitlines():
        try:
            r = json.loads(line)
            done[r["name"]] = r
        except (json.JSONDecodeError, KeyError):
            continue  # a line cut by an interrupted write: that query is redone
    return done


class _Journal:
    def __init__(self, path: Path):
        self.f = open(path, "a")

    def write(self, rec: dict):
        self.f.write(json.dumps(rec) + "\n")
        self.f.flush()
        os.fsync(self.f.fileno())

    def close(self):
        self.f.close()


@dataclass
class SceneJob:
    """One scene's localization once :func:`prepare_scene` has made its artifacts: everything a worker needs to
    localize some of its queries from the files under ``out_dir`` (:func:`localize_chunk`), and the driver to
    journal them and write the results (:func:`journal_records`, :func:`finish_scene`). Small and picklable."""

    scene: object  # lipmap.scene.Scene with the frames that passed check_scene
    out_dir: Path
    conf: LocalizationConfig
    hloc_dir: Optional[HlocOutputs]
    map_info: dict
    qlines_h5: Path
    journal_path: Path
    bad_queries: dict  # query name -> problem (reported as failed)
    gt: dict  # cam_from_world of every query, bad ones included
    skipped: dict  # query name -> why its ground truth is invalid
    timings: dict
    sources: dict

    def open_points(self):
        """The point source, reopened from its artifacts (nothing is rebuilt)."""
        return open_points(self.scene, self.out_dir, self.conf, self.hloc_dir)

    def open_line_query(self) -> LineQuery:
        """The line query on the line map, reloaded from ``linemap.h5``."""
        from lipmap.linemap import LineMap

        return make_line_query(LineMap.load(self.out_dir / self.map_info["path"]), self.conf, self.map_info["path"])


def localize_scene(scene, out_dir, conf: LocalizationConfig, hloc_dir=None, lines_source=None, overwrite=False,
                   skip_bad_frames: bool = False, checkpoint: Optional[Callable[[str], None]] = None,
                   linemap=None) -> dict:
    """Run the whole per-scene pipeline and write the scene's results; returns the scene summary.

    Each variant of an artifact lives where its settings put it: the line map in
    ``map-<method>-<preset>-<digest>/``, the point map in ``points-<preset>-<digest>/``, the queries' journal
    in ``queries-<digest>.jsonl`` (the digest covers the settings, the map and the points), so runs with other
    settings into the same ``out_dir`` never reuse each other's artifacts. The results files describe the
    latest run and name the map and points they used.

    Bad frames are found first (lipmap.datasets.validate): a bad mapping frame stops the run with a
    message naming it unless ``skip_bad_frames``; a bad query is reported as failed and the others run.
    ``checkpoint(event)`` is called after each artifact ("lines2d", "planes", "linemap", "mapped") and
    after each query's journal entry ("query"): progress for benchmarks, fault injection for tests.
    """
    job, points, lq = prepare_scene(scene, out_dir, conf, hloc_dir, lines_source, overwrite, skip_bad_frames, checkpoint,
                                    linemap)
    done = resume_scene(job, overwrite)
    todo = pending_queries(job, done)
    journal_records(job, done, localize_views(tqdm(todo, desc=f"localize {job.scene.name}"), points, job.qlines_h5, lq, conf),
                    checkpoint)
    return finish_scene(job, done)


def prepare_scene(scene, out_dir, conf: LocalizationConfig, hloc_dir=None, lines_source=None, overwrite=False,
                  skip_bad_frames: bool = False, checkpoint: Optional[Callable[[str], None]] = None, linemap=None):
    """Check the frames, then make (or reuse) the scene's line map, point source and query lines.

    Returns (:class:`SceneJob`, point source, :class:`LineQuery`): the job names the artifacts on disk; the other
    two are the objects already in memory, which a worker elsewhere reopens with ``job.open_points()`` and
    ``job.open_line_query()``.
    """
    from lipmap.datasets.validate import check_scene

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not scene.query:
        raise InputError(f"scene {scene.name} has no query views", scene.root / "TestSplit.txt")
    checkpoint = checkpoint or (lambda event: None)
    all_queries = list(scene.query)
    scene, bad_queries = check_scene(scene, skip_bad_frames)
    t0 = time.time()
    linemap, map_info = scene_linemap(scene, out_dir, conf, lines_source, overwrite, checkpoint, linemap)
    t_map = time.time() - t0
    checkpoint("mapped")
    lq = make_line_query(linemap, conf, map_info["path"])
    points = open_points(scene, out_dir, conf, hloc_dir, overwrite)
    qlines_h5 = query_lines_file(scene, out_dir, conf, overwrite)
    journal_path = out_dir / f"queries-{_journal_digest(scene, conf, map_info, points, qlines_h5)}.jsonl"
    sources = {"map": map_info, "points": {"folder": _rel(points.folder, out_dir), "digest": points.stamp.digest,
                                           **getattr(points, "info", {})},
               "journal": journal_path.name}
    job = SceneJob(scene, out_dir, conf, as_hloc_outputs(hloc_dir), map_info, qlines_h5, journal_path,
                   bad_queries, gt={v.name: v.cam_from_world for v in all_queries},
                   skipped={v.name: v.meta["gt_error"] for v in all_queries if v.meta.get("gt_error")},
                   timings={"map_s": t_map, **points.timings}, sources=sources)
    return job, points, lq


def open_points(scene, out_dir: Path, conf: LocalizationConfig, hloc_dir=None, overwrite: bool = False):
    """The scene's point source (:func:`localization.points.open_points`) with the settings of ``conf``."""
    return pts.open_points(scene, out_dir, conf.points, conf.retrieval, conf.num_retrieved, conf.seed, hloc_dir, overwrite)


def finish_scene(job: SceneJob, done: dict) -> dict:
    """Write the scene's results files from the records of its queries; returns the scene's results."""
    return write_scene_results(job.scene, job.out_dir, done, job.conf, job.map_info["n_lines"], job.timings, job.gt,
                               job.skipped, job.sources)


def _rel(path: Path, base: Path) -> str:
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return str(path)


def scene_linemap(scene, out_dir: Path, conf: LocalizationConfig, lines_source=None, overwrite: bool = False,
                  checkpoint: Optional[Callable[[str], None]] = None, linemap=None):
    """The line map of this configuration, built or reused in its own variant folder, or the map ``linemap`` (a
    ``linemap.h5`` already built, e.g. by :func:`lipmap.mapping.pipeline.map_scene`); returns (LineMap, info)."""
    from lipmap.linemap import LineMap

    if linemap is not None:
        return given_linemap(scene, Path(linemap), out_dir)
    from lipmap.mapping.pipeline import get_conf as map_conf
    from lipmap.mapping.pipeline import map_scene, map_variant_dir, mapping_stamp

    mconf = replace(map_conf(conf.mapping), seed=conf.seed)
    map_dir = map_variant_dir(out_dir, scene, mconf, conf.map_method, lines_source)
    # the planes in a folder of their own: map variants that differ only after the plane optimization share them
    path = map_scene(scene, map_dir, mconf, conf.map_method, lines_source, overwrite, checkpoint=checkpoint,
                     planes_root=out_dir)
    linemap = LineMap.load(path)
    info = {"method": conf.map_method, "preset": mconf.preset, "path": _rel(path, out_dir), "n_lines": len(linemap),
            "digest": mapping_stamp(scene, mconf, conf.map_method, lines_source).digest}
    if not len(linemap):
        logger.warning("%s: the line map has no lines; point+line poses will be the point-only poses", path)
    return linemap, info


def given_linemap(scene, path: Path, out_dir: Path):
    """A line map built elsewhere, checked against the scene (same world frame: the pose source); (LineMap, info)."""
    from lipmap.artifacts import digest as _digest
    from lipmap.artifacts import read_stamp
    from lipmap.linemap import LineMap

    if not path.is_file():
        raise InputError("line map file is missing", path)
    stamp = read_stamp(path)
    made = (stamp.settings.get("scene") or {}) if stamp is not None else {}
    if made.get("pose_source") not in (None, scene.pose_source):
        raise InputError(f"the line map was made with --pose-source {made['pose_source']}, and this run localizes "
                         f"with {scene.pose_source}: their poses live in different world frames", path,
                         f"evaluate with --pose-source {made['pose_source']}, or map again")
    if made.get("scene") not in (None, scene.name):
        logger.warning("%s was made for scene %s, not %s", path, made["scene"], scene.name)
    lm = LineMap.load(path)
    st = path.stat()
    info = {"method": lm.metadata.get("method", "given"), "preset": lm.metadata.get("preset"), "path": _rel(path, out_dir),
            "n_lines": len(lm), "given": True,
            "digest": stamp.digest if stamp is not None else _digest([str(path.resolve()), st.st_size, st.st_mtime_ns])}
    logger.info("Localizing %s against the line map %s (%d lines).", scene.name, path, len(lm))
    return lm, info


def query_lines_file(scene, out_dir: Path, conf: LocalizationConfig, overwrite: bool = False) -> Path:
    """2D lines of the queries, with the mapping's detector, in a file named by the detector's settings."""
    from lipmap.lines2d import detect_lines, get_conf as lines_conf, lines_stamp
    from lipmap.mapping.pipeline import get_conf as map_conf

    lconf = lines_conf(map_conf(conf.mapping).lines)
    stamp = lines_stamp(lconf.name, asdict(lconf))
    return detect_lines(scene.query, out_dir / f"lines2d_query-{stamp.digest[:8]}.h5", lconf, overwrite=overwrite)


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """Digest of the source of the ``lipmap`` and ``localization`` packages (every ``.py`` file, path and bytes)."""
    import lipmap

    return source_digest([Path(lipmap.__file__).parent, Path(__file__).parent])


def _journal_digest(scene, conf: LocalizationConfig, map_info: dict, points, qlines_h5: Path) -> str:
    # A journal resumes an interrupted run of the same code: after a change to the code its records (poses and
    # timings) would be the old code's, so another code starts another journal.
    return digest({"conf": asdict(conf), "map": map_info["digest"], "points": points.stamp.digest,
                   "query_lines": qlines_h5.name, "queries": views_key(scene.query), "code": code_digest()}, 10)


def resume_scene(job: SceneJob, overwrite: bool = False) -> dict:
    """Queries already localized by this configuration (from its journal), plus the bad ones as failures."""
    if overwrite and job.journal_path.exists():
        job.journal_path.unlink()
    done = _read_journal(job.journal_path)
    if done:
        logger.info("Resuming %s: %d of %d queries already localized (%s).", job.scene.name, len(done),
                    len(job.scene.query), job.journal_path.name)
    for name, problem in job.bad_queries.items():
        done[name] = {"name": name, "point": {"success": False}, "point+line": {"success": False}, "error": problem}
    return done


def pending_queries(job: SceneJob, done: dict) -> list:
    """The query views not in ``done``, in the scene's order."""
    return [v for v in job.scene.query if v.name not in done]


def localize_views(views, points, qlines_h5: Path, lq: LineQuery, conf: LocalizationConfig):
    """Yield the record of each view, in order (:func:`localize_query`); a failing query never stops the others."""
    from lipmap.lines2d import load_lines

    for v in views:
        try:
            lines2d = load_lines(qlines_h5, v.name)
        except Exception as e:  # noqa: BLE001 - a bad query must not stop the others
            lines2d = np.zeros((0, 4))
            logger.warning("No lines for query %s: %s", v.name, e)
        try:
            rec = localize_query(v.name, v.camera, points, lines2d, lq, conf, v.cam_from_world)
        except Exception as e:  # noqa: BLE001
            logger.warning("Query %s failed: %s", v.name, e)
            rec = {"name": v.name, "point": {"success": False}, "point+line": {"success": False}, "error": repr(e)}
        yield rec


def localize_chunk(job: SceneJob, names: list) -> list:
    """Records of the queries ``names`` of a prepared scene, reopening its artifacts from disk: the unit of work
    that a worker process or machine runs (localization.scaleout)."""
    views = {v.name: v for v in job.scene.query}
    return list(localize_views([views[n] for n in names], job.open_points(), job.qlines_h5, job.open_line_query(), job.conf))


def journal_records(job: SceneJob, done: dict, records, checkpoint: Optional[Callable[[str], None]] = None) -> None:
    """Append each record to the scene's journal (fsync'd, so a killed run resumes after it) and to ``done``,
    in the order given; ``checkpoint("query")`` after each."""
    journal = _Journal(job.journal_path)
    try:
        for rec in records:
            journal.write(rec)
            done[rec["name"]] = rec
            if checkpoint:
                checkpoint("query")
    finally:
        journal.close()


def line_match_stats(recs) -> dict:
    """Per-scene line-correspondence figures, checked with the ground-truth pose: medians of matches and
    correct matches per query, and the precision of the matches and of the PnPL line inliers."""
    pl = [r["point+line"] for r in recs if "n_line_matches_correct" in r.get("point+line", {})]
    if not pl:
        return {}
    tot = {k: sum(p.get(k, 0) for p in pl) for k in ("n_line_matches", "n_line_matches_correct", "n_line_inliers",
                                                       "n_line_inliers_correct")}
    return {
        "median_line_matches": float(np.median([p["n_line_matches"] for p in pl])),
        "median_line_matches_correct": float(np.median([p["n_line_matches_correct"] for p in pl])),
        "line_match_precision": round(tot["n_line_matches_correct"] / tot["n_line_matches"], 4) if tot["n_line_matches"] else None,
        "line_inlier_precision": round(tot["n_line_inliers_correct"] / tot["n_line_inliers"], 4) if tot["n_line_inliers"] else None,
    }


def write_scene_results(scene, out_dir: Path, recs: dict, conf: LocalizationConfig, n_map_lines: int, timings, gt=None,
                        skipped=None, sources: Optional[dict] = None) -> dict:
    from .hloc_io import write_results

    gt = scene.query_gt if gt is None else gt
    summary, per_query = {}, {}
    for key, fname in RESULT_FILES.items():
        est = {n: (np.array(r[key]["cam_from_world"]) if r[key].get("success") else None) for n, r in recs.items()}
        write_results(out_dir / fname, {n: T for n, T in est.items() if T is not None})
        errs = ev.query_errors(est, gt)
        ms = [r[key]["ms"] for r in recs.values() if r[key].get("ms") is not None]
        summary[key] = ev.summarize(errs, ms)
        for n, (t, r) in errs.items():
            per_query.setdefault(n, {})[key] = {"t_cm": round(t * 100, ev.DECIMALS) if math.isfinite(t) else None,
                                                 "R_deg": round(r, ev.DECIMALS) if math.isfinite(r) else None,
                                                 **{k: v for k, v in recs.get(n, {}).get(key, {}).items() if k != "cam_from_world"}}
    line_ms = [r["point+line"]["line_stage_ms"] for r in recs.values() if "line_stage_ms" in r["point+line"]]
    summary["point+line"]["median_ms_line_stage"] = float(np.median(line_ms)) if line_ms else None
    summary["point+line"]["median_line_inliers"] = float(np.median([r["point+line"].get("n_line_inliers", 0) for r in recs.values()]))
    summary["point+line"].update(line_match_stats(recs.values()))
    out = {
        "scene": scene.name,
        "dataset": scene.dataset,
        "pose_source": scene.pose_source,
        "pgt_files": (scene.meta or {}).get("pgt_files", []),
        "n_map_lines": n_map_lines,
        **(sources or {}),
        "config": json.loads(json.dumps(asdict(conf), default=str)),
        "timings": timings,
        "summary": summary,
        "queries": per_query,
        "errors": {n: r["error"] for n, r in recs.items() if "error" in r},
        "skipped_invalid_gt": skipped or {},
        "skipped_mapping_frames": scene.meta.get("skipped_frames", []),
    }
    write_text_atomic(out_dir / "results.json", json.dumps(out, indent=1, default=float))
    return out


def localize_scenes(scenes, conf: LocalizationConfig, hloc_dir=None, overwrite=False, skip_bad_frames: bool = False,
                    checkpoint: Optional[Callable[[str], None]] = None, linemaps: Optional[dict] = None):
    """The local scene runner of :func:`run_eval`: ``scenes`` yields (scene, out_dir); yields each scene's results,
    in order. localization.scaleout.RayRunner is the other one (same arguments, same results)."""
    for scene, out_dir in scenes:
        yield localize_scene(scene, out_dir, conf, hloc_dir, overwrite=overwrite, skip_bad_frames=skip_bad_frames,
                             checkpoint=checkpoint, linemap=(linemaps or {}).get(scene.name))


def run_eval(dataset: str, root, scenes, out, conf: LocalizationConfig, hloc_dir=None, pose_source="posetxt",
             register_depth=True, overwrite=False, mapping_step: int = 1, skip_bad_frames: bool = False,
             checkpoint: Optional[Callable[[str], None]] = None, runner: Optional[Callable] = None,
             pgt_dir=None, linemap=None) -> Path:
    """Localize every scene and write OUT/<dataset>/results.json and summary.md; returns the results path.

    ``runner`` localizes the scenes (default :func:`localize_scenes`, here, one after the other); e.g.
    ``localization.scaleout.RayRunner`` spreads them and their queries over a Ray cluster.
    ``linemap``: line maps already built (``linemap.h5``), used instead of mapping here: a path (``{scene}`` in it
    becomes each scene's name) or ``{scene: path}``.
    """
    from lipmap.datasets import load_scene

    check_config(conf)  # before any mapping: a bad number would otherwise fail every query one by one
    # absolute paths: a runner's workers may start elsewhere, and the paths in messages are the same either way
    root, out = Path(root).resolve(), Path(out).resolve() / dataset
    hloc_dir = as_hloc_outputs(hloc_dir)
    all_res = {"dataset": dataset, "root": str(root), "pose_source": pose_source, "config": json.loads(json.dumps(asdict(conf), default=str)),
               "scenes": {}, "scene_details": {}}

    def loaded():
        for name in scenes:
            scene = load_scene(dataset, root, name, pose_source=pose_source, register_depth=register_depth,
                               mapping_step=mapping_step, skip_bad_frames=skip_bad_frames, pgt_dir=pgt_dir)
            logger.info("Scene %s: %d mapping, %d query views (poses: %s).", name, len(scene.mapping), len(scene.query), pose_source)
            yield scene, out / name

    if linemap is not None and not isinstance(linemap, dict):
        linemap = {name: str(linemap).replace("{scene}", name) for name in scenes}
    linemap = {k: Path(v).resolve() for k, v in (linemap or {}).items()}
    results = (runner or localize_scenes)(loaded(), conf, hloc_dir=hloc_dir, overwrite=overwrite,
                                          skip_bad_frames=skip_bad_frames, checkpoint=checkpoint, linemaps=linemap)
    for name, res in zip(scenes, results, strict=True):  # a runner yields the scenes' results in their order
        all_res["scenes"][name] = res["summary"]
        all_res["scene_details"][name] = {"n_map_lines": res["n_map_lines"], "map": res["map"], "timings": res["timings"]}
        s = res["summary"]
        logger.info("%s point-only: %s | point+line: %s", name, ev.format_summary(s["point"]), ev.format_summary(s["point+line"]))
    path = out / "results.json"
    write_text_atomic(path, json.dumps(all_res, indent=1, default=float))
    notes = [f"Mapping: {conf.map_method} ({conf.mapping} preset); points: "
             + ("hloc files" if hloc_dir else f"built-in {conf.points} + {conf.retrieval} top-{conf.num_retrieved}")
             + (f"; point matches limited to {conf.max_point_matches} per query (seed {conf.seed if conf.match_seed is None else conf.match_seed})" if conf.max_point_matches is not None else ""),
             f"Line query: {conf.line_query.method}, "
             + (f"map lines seen in at least {conf.line_query.min_support} mapping image(s) by the track test"
                if conf.line_query.min_support else "every map line")]
    write_text_atomic(out / "summary.md", ev.summary_markdown(all_res, dataset, pose_source, notes))
    return path
