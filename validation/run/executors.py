"""Where the renders of a validation run: in this process, or on a Ray cluster.

An executor takes a list of :class:`~.jobs.Job` and returns their renders
in the same order (:meth:`Local.render`). The seeds are in the jobs, so an
image does not depend on where it was rendered. Two kinds of work:

* **statistical renders** (ladders, references, failure seeds): any worker,
  as many at once as there are workers;
* **timed renders** (``timed=True``: the speed-and-images stage, the sweeps'
  and the equal-ray renders, whose wall times are reported): one at a time on
  one worker, with nothing else of the run rendering meanwhile. The pipeline
  waits for every batch before it starts the next, so nothing else is in
  flight then. :meth:`Local.timed_on` says on which node they ran.

``local`` is this process, one render at a time; ``ray`` is
:mod:`.ray_executor` (pipeline.start_executor chooses).
"""

from __future__ import annotations

import platform

from .jobs import Workshop

KINDS = ("local", "ray")


class Executor:
    """What every executor shares: the nodes that timed renders, and closing."""

    kind = ""
    parallelism = 1          # renders at once

    def __init__(self):
        self.timed_nodes: set[str] = set()

    def timed_on(self) -> list[str]:
        """The nodes that rendered timed jobs since the last call."""
        nodes, self.timed_nodes = sorted(self.timed_nodes), set()
        return nodes

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        try:
            self.close()
        except Exception:  # noqa: BLE001  (never hide why the run stopped)
            if exc[0] is None:
                raise


class Local(Executor):
    """Every render in this process, one after another."""

    kind = "local"

    def __init__(self):
        super().__init__()
        self.workshop = Workshop()

    def render(self, jobs, progress=None, timed: bool = False) -> list:
        """Render ``jobs`` in order; ``progress(job)`` after each."""
        out = []
        for job in jobs:
            out.append(self.workshop.run(job, timed=timed))
            if progress:
                progress(job)
        if timed and jobs:
            self.timed_nodes.add(node_name())
        return out

    def record(self) -> dict:
        """Where the renders ran, as results.json's ``executor``."""
        return {"kind": self.kind, "workers": 1, "nodes": [node_name()],
                "note": "one render at a time in this process"}


def node_name() -> str:
    """This machine, as the results name it."""
    return platform.node() or "localhost"


RAY_MISSING = ("--executor ray needs Ray, which is not installed: pip install "
               "'mcillum[ray]' (or use --executor local)")


def check_ray() -> None:
    """Raise a one-line UserError saying how to install Ray, if it is not."""
    import importlib.util

    from mcillum.errors import UserError
    try:
        found = importlib.util.find_spec("ray") is not None
    except (ValueError, AttributeError):    # (sys.modules["ray"] is None)
        found = False
    if not found:
        raise UserError(RAY_MISSING)
