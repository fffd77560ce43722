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
* A worker that dies is restarted and its calls are run again (up to
  :data:`RETRIES` times: a render that kills its worker every time stops
  the run, saying so): the seeds are in the jobs, so the images are the
  same. A render that raises fails the run with the innermost exception
  the worker saw (what a local run reports), not a Ray traceback.
* Scene files travel once per scene (:func:`~.jobs.scene_files`, in Ray's
  object store): a worker fetches them only for a scene new to it, and
  renders from its own copy where its files differ (another machine).

Ray is an optional dependency (``pip install 'mcillum[ray]'``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
import platform
import signal
from collections import OrderedDict

from mcillum import errors
from mcillum import plugins as mcillum_plugins
from mcillum.errors import UserError

from . import jobs as jobs_
from .executors import RAY_MISSING, Executor, node_name

try:
    import ray
except ModuleNotFoundError as err:  # (only `--executor ray` imports this module)
    if err.name != "ray":
        raise
    raise UserError(RAY_MISSING) from None

#: Calls in flight per worker: one rendering, one waiting (no idle gap).
DEPTH = 2
#: Restarts of a worker that died, and retries of the calls it was running.
RETRIES = 3
#: Scenes whose files stay in the object store (a validation renders one
#: scene after another; the full profile has some 70, each with its map).
FILES_KEPT = 4
#: Jobs per call at most: a call costs about as much of Ray's time as a
#: small render of the quick profile
#: (docs/measurements.md#2026-12-01-figures-moved-out-code).
MAX_CHUNK = 16


def chunk_size(jobs: int, workers: int, timed: bool) -> int:
    """Jobs per call: about four calls per worker, at most MAX_CHUNK (timed
    ones too: queued on one worker, they run one after another anyway)."""
    if timed:
        return MAX_CHUNK
    return max(1, min(MAX_CHUNK, -(-jobs // (4 * workers))))


class RenderWorker:
    """One Ray actor: a warm Mitsuba in the run's variant."""

    def __init__(self, variant: str, plugins=()):
        # (this module's imports loaded mcillum first: Dr.Jit has its LLVM)
        from . import renders
        renders.set_variant(variant)
        # a user's integrators, the driver's bytes (from its own file where
        # this node has the same, else a copy in this node's cache)
        self.plugins = {p.spec: mcillum_plugins.sha256_of(mcillum_plugins.ensure(p, variant))
                        for p in plugins}
        self.workshop = jobs_.Workshop()
        self.node = f"{node_name()} ({ray.util.get_node_ip_address()})"

    def versions(self) -> tuple[dict, str]:
        """(what decides the images here, this worker's node)."""
        return _versions(self.plugins), self.node

    def render(self, batch, files, timed: bool = True):
        """(the renders of ``batch`` in order, this worker's node); ``files``
        maps scene keys to ObjectRefs of their files (fetched only for a
        scene new to this worker: refs inside a dict are not fetched by Ray);
        an untimed batch is replayed where it can be (replays.py).
        Raises the innermost exception (Mitsuba wraps a plugin's, and a
        pickled exception loses its ``__cause__``)."""
        try:
            return [self.workshop.run(job, lambda job=job: ray.get(files[job.scene.key]), timed)
                    for job in batch], self.node
        except Exception as err:
            cause = errors.root_cause(err).with_traceback(None)
            try:                   # (one that cannot travel goes as its message)
                pickle.loads(pickle.dumps(cause))
            except Exception:  # noqa: BLE001
                cause = RuntimeError(errors.message(cause))
            raise cause from None


def _versions(plugins: dict | None = None) -> dict:
    """Versions, a hash of mcillum's own code (two checkouts of one
    version may differ; scene files travel with the jobs), and the hash of
    each user's plugin file imported (``plugins``: spec → sha256)."""
    import importlib

    import drjit as dr
    import mitsuba as mi
    h = hashlib.sha256()
    for package in ("mcillum", "mcillum.integrators", "mcillum.envmaps", "mcillum.validation"):
        folder = os.path.dirname(importlib.import_module(package).__file__)
        for root, dirs, names in os.walk(folder):
            dirs[:] = sorted(d for d in dirs if d != "__pycache__")
            for name in sorted(n for n in names if n.endswith(".py")):
                path = os.path.join(root, name)
                with open(path, "rb") as f:
                    h.update(f"{package}/{os.path.relpath(path, folder)}".encode()
                             + hashlib.sha256(f.read()).digest())
    return {"mitsuba": mi.__version__, "drjit": dr.__version__,
            "python": platform.python_version(), "mcillum code": h.hexdigest()[:16],
            **{f"plugin {spec}": sha[:16] for spec, sha in (plugins or {}).items()}}


class RayExecutor(Executor):
    """The executor of :mod:`.executors` on Ray (see the module doc)."""

    kind = "ray"

    def __init__(self, address: str | None, workers: int | None, variant: str, plugins=()):
        super().__init__()
        self.plugins = list(plugins)
        self.address = address
        self.nodes: list[str] = []
        self._files: OrderedDict[str, object] = OrderedDict()
        # ray.init replaces the SIGTERM handler with sys.exit: keep ours
        # (errors.sigterm_as_interrupt: exit 143, saying what was left)
        term = signal.getsignal(signal.SIGTERM)
        try:
            if address is None:    # a new instance on this machine, not one running here
                # (its notice that token authentication is on, the default, would
                # open every run's output; a warning that it is off still shows)
                log = logging.getLogger(
                    "ray._private.authentication.authentication_token_setup")
                log.addFilter(_token_notice)
                try:
                    ray.init(address="local", num_cpus=max(os.cpu_count() or 1, workers or 0),
                             include_dashboard=False, logging_level=logging.WARNING)
                finally:
                    log.removeFilter(_token_notice)
            else:
                ray.init(address=address, logging_level=logging.WARNING)
        finally:
            if term is not None:
                signal.signal(signal.SIGTERM, term)
        try:
            self._start_workers(workers, variant, variant.startswith("cuda"))
        except BaseException:
            ray.shutdown()
            raise

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
        actor = ray.remote(max_restarts=RETRIES, max_task_retries=RETRIES,
                           **options)(RenderWorker)
        self.workers = [actor.remote(variant, self.plugins) for _ in range(n)]
        self.parallelism = n
        mine = _versions({p.spec: p.sha256 for p in self.plugins})
        for theirs, node in _get([w.versions.remote() for w in self.workers]):
            differ = {k: (v, theirs.get(k)) for k, v in mine.items() if theirs.get(k) != v}
            if differ:
                raise UserError(f"Ray worker on {node} differs from this driver in "
                                + ", ".join(f"{k} ({b} there, {a} here)"
                                            for k, (a, b) in differ.items())
                                + ": install the same mcillum, Mitsuba, Dr.Jit and Python "
                                  "on every node")
            if node not in self.nodes:
                self.nodes.append(node)

    # ---------------------------------- Render ---------------------------------------

    def _files_of(self, batch) -> dict:
        """{scene key: ObjectRef of its files} of the scenes of ``batch``
        (the last few scenes' stay in the object store: a restarted worker
        may need them again)."""
        refs = {}
        for job in batch:
            key = job.scene.key
            if key not in self._files:
                self._files[key] = ray.put(jobs_.scene_files(job.scene))
            self._files.move_to_end(key)
            refs[key] = self._files[key]
        while len(self._files) > FILES_KEPT:
            self._files.popitem(last=False)
        return refs

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
                        ref = workers[w].render.remote(batch, self._files_of(batch),
                                                       timed)
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

    def record(self) -> dict:
        """Where the renders ran, as results.json's ``executor``."""
        return {"kind": self.kind, "address": self.address or "a local instance",
                "workers": self.parallelism, "nodes": sorted(self.nodes), "ray": ray.__version__,
                "note": f"statistical renders ran up to {self.parallelism} at a time (their "
                        "seconds include the other workers' load); timed ones one at a "
                        "time on one worker (speed.timed_on)"}

    def close(self) -> None:
        for w in getattr(self, "workers", []):
            ray.kill(w)
        ray.shutdown()


def _token_notice(record) -> bool:
    return "Token authentication is enabled" not in record.getMessage()


def _get(ref):
    """``ray.get``, raising what the worker raised (its message, its type),
    or a one-line error for a worker that died once more than RETRIES allow."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        cause = err.cause
        if isinstance(cause, BaseException):
            raise cause.with_traceback(None) from None
        raise
    except ray.exceptions.RayActorError as err:
        why = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"a Ray render worker stopped for good (restarted up to {RETRIES} "
                        f"times): {why}; a render that kills its worker, a node short of "
                        "memory, or a worker that cannot start (the run's variant on that "
                        "node): --executor local shows a render's own error") from None
