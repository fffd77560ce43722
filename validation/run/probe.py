"""How fast this machine renders: one fixed workload, timed before a run's
first timed render (stages/speed.time_costs).

A run's wall time says as much about its machine as about its work: the
same full profile took 1.19× longer on one day's development VM than on the
day before, with nothing else running
(docs/measurements.md#2026-12-06-five-speed-stages-machine). So every run that
times renders first times Mitsuba's `path` on the bundled Cornell box at a
fixed film and spp, in this process, and records it beside its wall time; two
runs' wall times compare after dividing each by its own probe.
"""

from __future__ import annotations

import numpy as np

from mcillum.integrators.core import registry

from ..plan import scenes, seeds
from .executors import Local
from .jobs import Job, make
from .renders import load_scene
from .timing import timed

SCENE, RES, SPP, MAX_DEPTH = "cornell_box", 128, 64, 8
#: Timed renders after the untimed one: the median of 7 moved by 1-2 %
#: between runs on a quiet machine
#: (docs/measurements.md#2026-12-06-five-speed-stages-machine).
ROUNDS = 7


def workload() -> str:
    """What the probe renders, in words."""
    return f"{registry.REFERENCE} on {SCENE} at {RES}² × {SPP} spp, max_depth {MAX_DEPTH}"


def machine_speed() -> dict:
    """{"workload", "seconds" (median), "low", "high" (fastest, slowest)}
    of ROUNDS timed renders of :func:`workload` in this process, after an
    untimed one (the variant set already: run/renders.set_variant)."""
    scene = load_scene(scenes.path(SCENE), res=RES)
    integrator = make(registry.REFERENCE, {"max_depth": MAX_DEPTH})

    def job(name, spp, seed):
        return Job(None, integrator, spp, seed, live=scene)

    seconds = timed(Local(), job, {registry.REFERENCE: [SPP]}, ROUNDS,
                    seeds.stream("bench"))[registry.REFERENCE][SPP]
    return {"workload": workload(), "seconds": float(np.median(seconds)),
            "low": float(min(seconds)), "high": float(max(seconds))}
