"""The renders of a validation on a Ray cluster (``mcillum validate --executor ray``).

Workers are Ray actors (:class:`RenderWorker`): each imports ``mcillum``
(which points Dr.Jit at the bundled LLVM in its process), sets the run's
variant once and keeps what it loaded (:class:`~.jobs.Workshop`: scenes by
content key, integrators by name and properties). One worker per CPU of the
cluster (``num_cpus=1``), or per GPU for a cuda variant (``num_gpus=1``);
``--ray-workers`` chooses another number.

* Statistical renders go to every worker, two in flight per worker; results
  come back to the driver in the order of the jobs.
* Timed renders go to the first worker only, queued there in order (an
  actor runs its calls one at a time), while the rest of the run waits:
  nothing else renders meanwhile. Each render says on which node it ran.
* A worker that dies is restarted and its calls are run again
  (``max_restarts``/``max_task_retries`` -1): the seeds are in the jobs,
  so the images are the same. A render that raises fails the run with the
  worker's own exception, as a local run would, not a Ray traceback.
* Scene files travel once per scene (:func:`~.jobs.scene_files`, in Ray's
  object store): a worker fetches them only for a scene new to it, and
  renders from its own copy where its files differ (another machine).

Ray is an optional dependency (``pip install 'mcillum[ray]'``).
"""

from __future__ import annotations

import logging
import os
import platform

from mcillum.errors import UserError

from . import jobs as jobs_
from .executors import node_name

try:
    import ray
except ModuleNotFoundError as err:  # (only `--executor ray` imports this module)
    if err.name != "ray":
        raise
    raise UserError("--executor ray needs Ray, which is not installed: pip install "
                    "'mcillum[ray]' (or use --executor local)") from None

#: Calls in flight per worker: one rendering, one waiting (no idle gap).
DEPTH = 2
#: Jobs per call at most: a call costs ~2 ms of Ray's time, a small render
#: of the quick profile about as much (measured, 8² × 64 spp).
MAX_CHUNK = 16


def chunk_size(jobs: int, workers: int, timed: bool) -> int:
    """Jobs per call: about four calls per worker, at most MAX_CHUNK (timed
    ones too: queued on one worker, they run one after another anyway)."""
    if timed:
        return MAX_CHUNK
    return max(1, min(MAX_CHUNK, -(-jobs // (4 * workers))))


class RenderWorker:
    """One Ray actor: a warm Mitsuba in the run's variant."""

    def __init__(self, variant: str):
        import mcillum  # noqa: F401  (before Dr.Jit: its LLVM)
        from . import renders
        renders.set_variant(variant)
        self.workshop = jobs_.Workshop()
        self.node = f"{node_name()} ({ray.util.get_node_ip_address()})"

    def versions(self) -> dict:
        return _versions()

    def render(self, batch, files):
        """(the renders of ``batch`` in order, this worker's node); ``files``
        maps scene keys to ObjectRefs of their files (fetched only for a
        scene new to this worker: refs inside a dict are not fetched by Ray)."""
        return [self.workshop.run(job, lambda job=job: ray.get(files[job.scene.key]))
                for job in batch], self.node


def _versions() -> dict:
    import drjit as dr
    import mitsuba as mi
    from importlib import metadata
    try:
        own = metadata.version("mcillum")
    except metadata.PackageNotFoundError:
        own = "?"
    return {"mcillum": own, "mitsuba": mi.__version__, "drjit": dr.__version__,
            "python": platform.python_version()}


class RayExecutor:
    """The executor of :mod:`.executors` on Ray (see the module doc)."""

    kind = "ray"

    def __init__(self, address: str | None, workers: int | None, variant: str):
        self.address = address
        cuda = variant.startswith("cuda")
        if address is None:          # a local instance on this machine
            # (its notice that token authentication is on, the default, would
            # open every run's output; a warning that it is off still shows)
            log = logging.getLogger("ray._private.authentication.authentication_token_setup")
            log.addFilter(_token_notice)
            try:
                ray.init(num_cpus=max(os.cpu_count() or 1, workers or 0),
                         include_dashboard=False, logging_level=logging.WARNING)
            finally:
                log.removeFilter(_token_notice)
        else:
            ray.init(address=address, logging_level=logging.WARNING)
        try:
            self._start_workers(workers, variant, cuda)
        except BaseException:
            ray.shutdown()
            raise
        self._files: dict[str, object] = {}
        self.timed_nodes: set[str] = set()

    def _start_workers(self, workers, variant, cuda) -> None:
        resource = "GPU" if cuda else "CPU"
        have = int(ray.cluster_resources().get(resource, 0))
        n = workers or have
        if n < 1 or n > have:
            raise UserError(f"the Ray cluster has {have} {resource}s: "
                            + (f"{n} workers would wait for them forever; give "
                               f"--ray-workers {have} or fewer" if have else
                               f"a {variant} run needs at least one"))
        options = {"num_gpus": 1} if cuda else {"num_cpus": 1}
        actor = ray.remote(max_restarts=-1, max_task_retries=-1, **options)(RenderWorker)
        self.workers = [actor.remote(variant) for _ in range(n)]
        self.parallelism = n
        mine = _versions()
        for theirs in ray.get([w.versions.remote() for w in self.workers]):
            if theirs != mine:
                raise UserError(f"a Ray worker has {theirs}, this driver {mine}: install the "
                                "same mcillum, Mitsuba, Dr.Jit and Python on every node")

    # ---------------------------------- Render ---------------------------------------

    def _files_of(self, batch) -> dict:
        """{scene key: ObjectRef of its files} of the scenes of ``batch``."""
        for job in batch:
            if job.scene.key not in self._files:
                self._files[job.scene.key] = ray.put(jobs_.scene_files(job.scene))
        return {job.scene.key: self._files[job.scene.key] for job in batch}

    def render(self, jobs, progress=None, timed: bool = False) -> list:
        """Render ``jobs`` (see :class:`~.executors.Local`); ``progress(job)``
        as each finishes."""
        out = [None] * len(jobs)
        workers = self.workers[:1] if timed else self.workers
        size = chunk_size(len(jobs), len(workers), timed)
        queue = [list(range(i, min(i + size, len(jobs)))) for i in range(0, len(jobs), size)]
        depth = len(queue) if timed else DEPTH
        load = [0] * len(workers)
        pending: dict = {}
        try:
            while queue or pending:
                for w in range(len(workers)):
                    while queue and load[w] < depth:
                        chunk = queue.pop(0)
                        batch = [jobs[i] for i in chunk]
                        ref = workers[w].render.remote(batch, self._files_of(batch))
                        pending[ref] = (chunk, w)
                        load[w] += 1
                done, _ = ray.wait(list(pending), num_returns=1)
                chunk, w = pending.pop(done[0])
                load[w] -= 1
                renders, node = _get(done[0])
                for i, result in zip(chunk, renders):
                    result.meta["node"] = node
                    out[i] = result
                    if progress:
                        progress(jobs[i])
                if timed:
                    self.timed_nodes.add(node)
        except BaseException:
            for ref in pending:          # (the run stops: nobody waits for them)
                try:
                    ray.cancel(ref)
                except Exception:  # noqa: BLE001  (already finished, or a dead worker)
                    pass
            raise
        return out

    def timed_on(self) -> list[str]:
        nodes, self.timed_nodes = sorted(self.timed_nodes), set()
        return nodes

    def describe(self) -> dict:
        nodes = sorted({n["NodeManagerAddress"] for n in ray.nodes() if n.get("Alive")})
        return {"kind": self.kind, "address": self.address or "a local instance",
                "workers": self.parallelism, "nodes": nodes, "ray": ray.__version__,
                "note": f"statistical renders ran up to {self.parallelism} at a time (their "
                        "seconds include the other workers' load); timed ones one at a "
                        "time on one worker (speed.timed_on)"}

    def close(self) -> None:
        for w in getattr(self, "workers", []):
            ray.kill(w)
        ray.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _token_notice(record) -> bool:
    return "Token authentication is enabled" not in record.getMessage()


def _get(ref):
    """``ray.get``, raising what the worker raised (its message, its type)."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        cause = err.cause
        if isinstance(cause, BaseException):
            raise cause.with_traceback(None) from None
        raise
