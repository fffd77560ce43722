"""Timed warm renders, and `mcillum bench`: what each integrator costs on one
scene, as the cost model t = a + b·spp (stats/costs.py).

Machines are shared and noisy, so integrators are compared in one process,
their renders interleaved (the order rotated every round,
:func:`stacks.rotation`) so that drift hits all of them alike, and each spp
timed only after an untimed render at it: the first render of a kernel
compiles it (or loads it from Dr.Jit's cache). A timed render that compiled
anyway is rendered again (renders.timed_render).
"""

from __future__ import annotations

import json
import os
import platform
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mcillum import files

from ..plan import seeds
from ..results import CostModel, to_json
from ..stats import costs
from .executors import Local
from .jobs import Job
from .stacks import rotation


def warm(executor, job, spp: dict[str, int], seed: int) -> dict[str, float]:
    """One untimed-for-the-model render of each integrator at ``spp[name]``
    (``job(name, spp, seed)`` makes its :class:`~.jobs.Job`); returns its
    seconds (the first of a process includes compilation: the render that
    renders.timed_render set aside, if any)."""
    names = list(spp)
    outs = executor.render([job(n, spp[n], seed) for n in names], timed=True)
    return {n: out.first_seconds for n, out in zip(names, outs)}


def timed(executor, job, plan: dict[str, list[int]], rounds: int,
          stream, spans: list | None = None) -> dict[str, dict[int, list[float]]]:
    """{name: {spp: [seconds]}}: after an untimed render at every spp of the
    plan (largest first), ``rounds`` rounds, the integrators rotated every
    round, each rendering at every spp of ``plan[name]`` (round i with seed i
    of ``stream``); one timed batch of the executor. Without the warm-up at
    each spp, a cold kernel cache makes one timed render several times the
    others' and inflates the fitted fixed cost
    (docs/measurements.md#2026-12-01-figures-moved-out-code).
    ``spans``, if given, receives (seconds, CPU seconds of other processes)
    of every timed render (run/load.py)."""
    batch, slots = [], []
    for j in range(max(len(s) for s in plan.values())):
        for n, spps in plan.items():
            if j < len(spps):
                batch.append(job(n, sorted(spps, reverse=True)[j], stream.seed(0)))
                slots.append(None)
    names = list(plan)
    for i in range(rounds):
        for n in rotation(names, i):
            for s in plan[n]:
                batch.append(job(n, s, stream.seed(i)))
                slots.append((n, s))
    out = {n: {s: [] for s in spps} for n, spps in plan.items()}
    for slot, result in zip(slots, executor.render(batch, timed=True)):
        if slot is not None:
            out[slot[0]][slot[1]].append(result.seconds)
            if spans is not None:
                spans.append((result.seconds, result.others_seconds))
    return out


# ------------------------------- mcillum bench ----------------------------------

@dataclass(kw_only=True)
class BenchRow:
    integrator: str
    first_seconds: float            # the first render: compile or cache load, and 1 spp
    cost_model: CostModel
    median_seconds: float           # warm renders at --spp
    ratio_to_first: float           # b ÷ the first integrator's b
    samples_per_second: float       # pixels / b


def bench(scene, integrators: dict, spp: int, runs: int) -> list[BenchRow]:
    """Time each integrator (name → :class:`~.jobs.Integrator`) at ``spp`` // 4
    and ``spp`` (``runs`` interleaved rounds) in this process, fit
    t = a + b·spp, and compare the b (seconds per spp) to the first
    integrator's."""
    if runs < 1:
        raise ValueError("need at least one warm run")
    stream = seeds.stream("bench")
    executor = Local()

    def job(name, n, seed):                 # (this process only: no scene spec)
        return Job(None, integrators[name], n, seed, live=scene)

    first = warm(executor, job, dict.fromkeys(integrators, 1), stream.seed(0))
    low = max(1, spp // 4)
    plan = {n: sorted({low, max(spp, low + 1)}) for n in integrators}
    times = timed(executor, job, plan, runs, stream)
    models = {n: costs.fit_cost(t) for n, t in times.items()}
    names = list(integrators)
    w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
    base = models[names[0]].per_spp_s
    return [BenchRow(integrator=n, first_seconds=first[n], cost_model=models[n],
                     median_seconds=float(np.median(times[n][plan[n][-1]])),
                     ratio_to_first=models[n].per_spp_s / base if base > 0 else float("nan"),
                     samples_per_second=(w * h / models[n].per_spp_s
                                         if models[n].per_spp_s > 0 else float("inf")))
            for n in names]


def bench_line(row: BenchRow, first: str) -> str:
    """One line of `mcillum bench`: a and b with their 95 % intervals."""
    m = row.cost_model
    return (f"{row.integrator:>22}: a = {m.fixed_s * 1e3:.2f} ms "
            f"[{m.fixed_s_ci.low * 1e3:.2f}, {m.fixed_s_ci.high * 1e3:.2f}], "
            f"b = {m.per_spp_s * 1e3:.3f} ms/spp "
            f"[{m.per_spp_s_ci.low * 1e3:.3f}, {m.per_spp_s_ci.high * 1e3:.3f}]; "
            f"median {row.median_seconds:.4f} s at {max(int(s) for s in m.timings)} spp "
            f"(first render {row.first_seconds:.3f} s); b is {row.ratio_to_first:.2f}x "
            f"{first}'s; {row.samples_per_second / 1e6:.2f} Msamples/s")


def write_json(path: str, scene_path: str, scene, defines: dict, params: dict, spp: int,
               variant: str, rows: list[BenchRow]) -> None:
    """The bench results and where they were measured, as JSON (atomically)."""
    w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
    report = {"scene": os.path.abspath(scene_path), "defines": defines, "params": params,
              "spp": spp, "resolution": [w, h], "variant": variant,
              "mitsuba_version": mi.__version__, "drjit_version": dr.__version__,
              "machine": platform.platform(), "cpus": os.cpu_count(),
              "model": "t = fixed_s + per_spp_s * spp (95 % bootstrap intervals)",
              "results": [to_json(r) for r in rows]}
    files.write_text(path, json.dumps(report, indent=2) + "\n")
