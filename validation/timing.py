"""Honest timing: compile once, then alternate integrators over warm runs.

Machines are shared and noisy (±30% here), so integrators are compared as
ratios of medians within one process, with runs interleaved (A B C A B C …)
so that drift hits all of them equally. The first render of each integrator
compiles its kernel (or loads it from Dr.Jit's cache) and is reported apart.
"""

from __future__ import annotations

import statistics as pystats
from dataclasses import dataclass, field

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
    """Time each of ``integrators`` (name → instance) on ``scene`` at ``spp``.

    One untimed-for-ranking first render each, then ``runs`` interleaved warm
    rounds, each with a fresh seed.
    """
    if runs < 1:
        raise ValueError("need at least one warm run")
    out = {name: Timing(name, render(scene, integ, spp, seed=0).seconds)
           for name, integ in integrators.items()}
    for round_ in range(1, runs + 1):
        order = list(integrators.items())
        if round_ % 2 == 0:
            order.reverse()  # A B C, C B A, …: no integrator always runs first
        for name, integ in order:
            out[name].warm_seconds.append(render(scene, integ, spp, seed=round_).seconds)
    return out
