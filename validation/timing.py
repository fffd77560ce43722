"""`mcillum bench`: time integrators against each other on one scene.

Machines are shared and noisy (±30 % here), so integrators are compared as
ratios of medians within one process, their warm runs interleaved by
:func:`sweeps.interleaved` so that drift hits all of them alike. The first
render of each integrator compiles its kernel (or loads it from Dr.Jit's
cache) and is reported apart.
"""

from __future__ import annotations

import json
import os
import platform
import statistics as pystats
from dataclasses import asdict, dataclass, field

import drjit as dr
import mitsuba as mi

from mcillum import files

from . import seeds, sweeps
from .renders import render


@dataclass
class Timing:
    """Wall-clock seconds of one integrator: first (compile) and warm runs."""

    name: str
    first_seconds: float
    warm_seconds: list[float] = field(default_factory=list)

    @property
    def median(self) -> float:
        return pystats.median(self.warm_seconds)


def alternate(scene, integrators: dict, spp: int, runs: int = 5) -> dict[str, Timing]:
    """Time each of ``integrators`` (name → instance) on ``scene`` at ``spp``:
    one first render each, then ``runs`` interleaved warm rounds, each with a
    fresh seed (stream "bench")."""
    if runs < 1:
        raise ValueError("need at least one warm run")
    stream = seeds.stream("bench")
    out = {name: Timing(name, render(scene, integ, spp, seed=stream.seed(0)).seconds)
           for name, integ in integrators.items()}
    warm = sweeps.interleaved(scene, integrators, dict.fromkeys(integrators, spp), runs,
                              stream.take(runs + 1)[1:])
    for name, unit in warm.items():
        out[name].warm_seconds = list(unit.seconds)
    return out


@dataclass
class BenchRow:
    integrator: str
    first_seconds: float
    warm_seconds: list[float]
    median_seconds: float
    ratio_to_first: float
    samples_per_second: float


def bench(scene, integrators: dict, spp: int, runs: int) -> list[BenchRow]:
    """:func:`alternate`, as rows with ratios to the first integrator."""
    times = alternate(scene, integrators, spp, runs)
    names = list(integrators)
    base = times[names[0]].median
    w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
    return [BenchRow(n, times[n].first_seconds, times[n].warm_seconds, times[n].median,
                     times[n].median / base, w * h * spp / times[n].median) for n in names]


def write_json(path: str, scene_path: str, scene, defines: dict, params: dict, spp: int,
               variant: str, rows: list[BenchRow]) -> None:
    """The bench results and where they were measured, as JSON (atomically)."""
    w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
    report = {"scene": os.path.abspath(scene_path), "defines": defines, "params": params,
              "spp": spp, "resolution": [w, h], "variant": variant,
              "mitsuba_version": mi.__version__, "drjit_version": dr.__version__,
              "machine": platform.platform(), "cpus": os.cpu_count(),
              "results": [asdict(r) for r in rows]}
    files.write_text(path, json.dumps(report, indent=2) + "\n")
