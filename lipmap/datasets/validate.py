"""Check that the frames of a scene can be read before a long run starts, so one bad frame is found
in seconds, named, and either stops the run (mapping, by default) or is set aside (queries)."""
from __future__ import annotations

from dataclasses import replace

from tqdm import tqdm

from .. import logger
from ..errors import InputError


def check_view(view, need_depth: bool) -> str | None:
    """The problem with ``view`` (message naming the file), or None if its images are usable."""
    try:
        view.load_color()
        if need_depth:
            if view.depth_path is None:
                stem = view.color_path.name.split(".color.")[0]
                return f"{view.color_path.with_name(stem + '.depth.png')}: depth map is missing (mapping needs depth)"
            d = view.load_depth()
            if not (d > 0).any():
                return f"{view.depth_path}: depth map has no valid pixel (all 0 or 65535)"
    except InputError as e:
        return str(e)
    return None


def check_scene(scene, skip_bad_frames: bool = False, need_depth: bool = True):
    """Validate every frame; returns (scene with usable frames, {query name: problem}).

    A bad mapping frame raises InputError unless ``skip_bad_frames`` (then it is dropped with a
    warning). Bad queries are dropped from the returned scene and returned with their problem, so
    the caller can report them as failed while the other queries run.
    """
    mapping, bad_queries, skipped = [], {}, list(scene.meta.get("skipped_frames", []))
    for v in tqdm(scene.mapping, desc="check mapping frames", leave=False, disable=len(scene.mapping) < 20):
        problem = check_view(v, need_depth)
        if problem is None:
            mapping.append(v)
        elif skip_bad_frames:
            logger.warning("skipping bad mapping frame %s: %s", v.name, problem)
            skipped.append(problem)
        else:
            raise InputError(f"bad mapping frame {v.name}: {problem}", hint="use --skip-bad-frames to skip it")
    query = []
    for v in tqdm(scene.query, desc="check query frames", leave=False, disable=len(scene.query) < 20):
        problem = check_view(v, need_depth=False)
        if problem is None:
            query.append(v)
        else:
            logger.warning("query %s cannot be localized: %s", v.name, problem)
            bad_queries[v.name] = problem
    if not mapping:
        raise InputError(f"scene {scene.name} has no usable mapping frame", scene.root)
    return replace(scene, mapping=mapping, query=query, meta={**scene.meta, "skipped_frames": skipped}), bad_queries
