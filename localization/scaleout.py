"""Scale-out of the localization benchmark on a Ray cluster (`lipmap-loc eval --ray [ADDRESS]`).

Each scene's artifacts (line map, points, query lines) are made by one Ray task
(:func:`localization.pipeline.prepare_scene`); its queries are then localized by tasks of ``chunk`` queries
each (:func:`localization.pipeline.localize_chunk`), which reopen those artifacts from disk. The driver
appends the returned records to the scene's journal in query order and writes the results exactly as a
local run does (:func:`localization.pipeline.finish_scene`), so results.json is the same as a local run's
apart from wall-clock timings, and an interrupted run resumes from the journal either way.

The cluster's workers must see OUT (and the dataset root) at the same paths as the driver - a shared
filesystem - and run the same Python environment. Ray is an optional dependency (``pip install
"lipmap[ray]"``), imported only here and only when asked for.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from lipmap import InputError, logger

from .hloc_outputs import as_hloc_outputs
from .config import LocalizationConfig
from .pipeline import (finish_scene, journal_records, localize_chunk, pending_queries, prepare_scene,
                       resume_scene)

INSTALL_HINT = 'pip install "lipmap[ray]"'


def import_ray():
    """The ``ray`` module, or an InputError saying how to install it."""
    try:
        import ray
    except ImportError as e:
        raise InputError(f"--ray needs Ray, which is not installed here ({e})", hint=INSTALL_HINT) from None
    return ray


def _prepare(scene, out_dir: Path, conf: LocalizationConfig, hloc_dir, overwrite: bool, skip_bad_frames: bool,
             linemap=None):
    """Ray task: a scene's artifacts; returns its :class:`~localization.pipeline.SceneJob` (the objects stay behind)."""
    return prepare_scene(scene, out_dir, conf, hloc_dir, overwrite=overwrite, skip_bad_frames=skip_bad_frames,
                         linemap=linemap)[0]


@dataclass
class RayRunner:
    """A scene runner for :func:`localization.pipeline.run_eval` that spreads the work over Ray.

    ``address``: None starts a local Ray instance (or attaches to the one this machine runs), "auto" or
    "ray://host:port" / "host:port" connects to a cluster. ``num_cpus``: CPUs of a local instance.
    ``chunk``: queries per task. When this process is connected to Ray already, that connection is used.
    """

    address: Optional[str] = None
    num_cpus: Optional[int] = None
    chunk: int = 50

    def __post_init__(self):
        if self.chunk < 1:
            raise InputError(f"--ray-chunk must be >= 1 query, got {self.chunk}")
        if self.num_cpus is not None and self.num_cpus < 1:
            raise InputError(f"--ray-cpus must be >= 1, got {self.num_cpus}")
        if self.num_cpus is not None and self.address:
            raise InputError("--ray-cpus sets up a local Ray instance; a cluster at an address has its own CPUs")

    def _connect(self, ray) -> bool:
        """Connect unless connected already; True when this call connected (and the runner disconnects)."""
        if ray.is_initialized():
            return False
        try:
            if self.address:
                ray.init(address=self.address)
            else:
                ray.init(num_cpus=self.num_cpus, include_dashboard=False)
        except (ConnectionError, ValueError, RuntimeError) as e:
            raise InputError(f"cannot start or reach Ray at {self.address or 'this machine'}: {e}",
                             hint="start a cluster with `ray start --head`, or give --ray with no address") from None
        logger.info("Ray: %s CPUs in the cluster.", ray.cluster_resources().get("CPU"))
        return True

    def __call__(self, scenes, conf: LocalizationConfig, hloc_dir=None, overwrite=False, skip_bad_frames: bool = False,
                 checkpoint: Optional[Callable[[str], None]] = None, linemaps: Optional[dict] = None):
        """Yield each scene's results in order, like :func:`localization.pipeline.localize_scenes`.

        ``checkpoint`` sees "mapped" when a scene's artifacts are ready and "query" after each journal entry (the
        events inside the mapping happen on the workers)."""
        ray = import_ray()
        connected = self._connect(ray)
        try:
            # a query's rescue runs on LineRescueConfig.threads threads: its task holds as many CPUs
            prepare, chunk_task = ray.remote(_prepare), ray.remote(num_cpus=conf.line_rescue.threads)(localize_chunk)
            # every scene's mapping is submitted at once; its queries as soon as its artifacts are there
            hloc_dir = as_hloc_outputs(hloc_dir)  # absolute paths: the workers start elsewhere
            prepared = [prepare.remote(scene, Path(out_dir).resolve(), conf, hloc_dir, overwrite, skip_bad_frames,
                                       (linemaps or {}).get(scene.name))
                        for scene, out_dir in scenes]
            submitted = []
            for ref in prepared:
                job = ray.get(ref)
                if checkpoint:
                    checkpoint("mapped")
                done = resume_scene(job, overwrite)
                names = [v.name for v in pending_queries(job, done)]
                job_ref = ray.put(job)
                chunks = [chunk_task.remote(job_ref, names[i:i + self.chunk]) for i in range(0, len(names), self.chunk)]
                logger.info("%s: %d queries in %d Ray tasks.", job.scene.name, len(names), len(chunks))
                submitted.append((job, done, chunks))
            for job, done, chunks in submitted:
                # chunk by chunk in query order: a killed run leaves a journal whose queries are not asked again
                journal_records(job, done, (rec for ref in chunks for rec in ray.get(ref)), checkpoint)
                yield finish_scene(job, done)
        finally:
            if connected:
                ray.shutdown()
