"""Equal-time budgets that are met (the speed stage's renders, stages/speed.py).

Each estimator renders K times at the spp its cost model gives for a budget
T (at a budget but the largest, only those that fit MIN_SPP samples in it:
:func:`fits`); at the second budget on, that spp is scaled by how far the
model was off at the budget before. A render set whose median wall time
misses T by more than ON_BUDGET renders again at the spp the measured times
say (:func:`corrected`), at most CORRECTIONS times, LOADED_CORRECTIONS where
other processes loaded the machine meanwhile (run/load.py), and, for an
estimator that learns, no more once tries at adjacent spp fell on both sides
of T (:func:`unreachable`: its time steps where it adds a training pass, and
no whole spp meets T); the try nearest T is measured, and every try is kept
(results.Try).
"""

from __future__ import annotations

import os

import numpy as np

from mcillum.integrators.core import registry

from ..results import Try
from ..run import load, stacks, timing
from ..stats import costs

REFERENCE = registry.REFERENCE
ON_BUDGET = 0.10           # a median wall time within ±10 % of its budget
#: A measured try whose median wall time lies beyond this factor of its
#: budget, either way, is no equal-time figure: its efficiency ÷ path is
#: withheld (:func:`equal_time`, stages/speed.py), and every ratio where
#: path's own is. Efficiency 1/(relMSE·t) holds across budgets only while
#: the fixed cost is small: at most 10 % of the largest budget
#: (costs.MAX_OVERHEAD), 15 % at budget/1.5, which moves the figure by
#: about 6 %, inside its interval; and a learner's step between adjacent
#: spp (30-45 %, :func:`unreachable`) leaves its nearest try within ×1.5.
#: Beyond it the figure reads the launch: cap_plane's emitter_sampling at
#: 2 spp in 10 ms against a 114 ms budget (a busy core) read 0.883
#: [0.489, 1.59] where the quiet run reads 15.8 [10.2, 24.7] (issue 66).
EQUAL_TIME = 1.5
#: Re-renders of an estimator that missed a budget: with 2, 2 of 63 render
#: sets missed by a few % after a first try 40 % slow on a quiet machine
#: (docs/measurements.md#2026-12-03-budgets-learner-step-makes).
CORRECTIONS = 3
LOADED_CORRECTIONS = 4     # ... where other processes loaded the machine meanwhile
#: Samples per pixel every estimator gets at the largest budget at least,
#: and every one rendered at a smaller budget (:func:`fits`).
MIN_SPP = 6
MAX_SCALE = 64             # budgets grow at most this much to outweigh the fixed cost
#: Samples per pixel an estimator that learns gets at the largest budget at
#: least: its training passes cost the same at any spp near it, so its
#: efficiency rises with its spp, and between runs whose budgets differ by a
#: few % it moved by more than its interval said. guided_path on the Cornell
#: box at 128²: 0.72 at 24 spp, 0.78 at 26, 0.84-0.87 at 44-45; two
#: quiet runs and a loaded one read 0.715 and 0.837
#: (docs/measurements.md#2026-12-05-ms-floor-recording-lingering).
MIN_LEARNER_SPP = 40
#: The smallest budget at least (seconds). With launches of 1-5 ms (they
#: were 13-33 ms when a 60 ms floor was set) six rounds of four renders at
#: 30 ms had medians within 1-9 % of each other here
#: (docs/measurements.md#2026-12-05-ms-floor-recording-lingering, "A 30 ms
#: floor").
MIN_BUDGET = 0.03
#: Other processes using more than this many cores on average during the
#: timed renders: the machine was loaded, and the report says so.
LOADED = 0.25


def budget_spp(models: dict, path_spp) -> list[int]:
    """`path`'s spp at each budget: the profile's ``path_spp`` scaled by one
    factor (1 to MAX_SCALE), its ratios kept, so that every estimator's fixed
    cost is at most 10 % of the largest budget, where efficiency is read,
    every estimator renders at least MIN_SPP samples there (one sample is
    then at most a sixth of it, and whole samples can come within ±10 % of
    it), an estimator that learns at least MIN_LEARNER_SPP, and the
    smallest is at least MIN_BUDGET. A smaller budget renders the
    estimators that fit MIN_SPP in it (:func:`fits`): held to MIN_SPP in
    the smallest, the N-direction estimators (a sample 100× path's) made
    nine of the full profile's sixteen budget pairs 4× larger for every
    estimator
    (docs/measurements.md#2026-12-05-n-direction-estimators-largest-budget). At
    the smaller budgets the fixed cost is a larger share, and the chart shows
    what it costs there: held to 10 % of the smallest, the quick profile's
    budgets were 2-4× larger
    (docs/measurements.md#2026-12-03-quick-profile-cost-reference)."""
    path = models[REFERENCE]
    per_spp = max(path.per_spp_s, 1e-12)

    def scale_for(seconds: float, spp: int) -> float:
        # (the factor on `spp` that makes path's time at it ``seconds``,
        # as costs.seconds_at reads path's model, which sets the budgets)
        return (seconds - max(path.fixed_s, 0.0)) / per_spp / spp

    worst = max(max(m.fixed_s, 0.0) for m in models.values())
    largest = scale_for(worst / costs.MAX_OVERHEAD, max(path_spp))
    # (path's spp defines the budgets: it renders them as they are)
    slowest = max((costs.seconds_at(m, MIN_SPP)
                   for n, m in models.items() if n != REFERENCE), default=0.0)
    fit = scale_for(slowest, max(path_spp))
    smallest = scale_for(MIN_BUDGET, min(path_spp))
    learner = max((costs.seconds_at(m, MIN_LEARNER_SPP)
                   for n, m in models.items() if registry.facts(n).learns), default=0.0)
    trained = scale_for(learner, max(path_spp))
    scale = min(max(1.0, largest, fit, smallest, trained), MAX_SCALE)
    first = int(np.ceil(scale * min(path_spp)))
    return [int(round(first * s / min(path_spp))) for s in path_spp]


def equal_time(seconds, budget: float) -> bool:
    """Is the median of ``seconds`` (wall times) within EQUAL_TIME of
    ``budget``, either way: a figure read at equal time?"""
    median = float(np.median(seconds))
    return budget / EQUAL_TIME <= median <= EQUAL_TIME * budget


def fits(model, budget: float) -> bool:
    """Does the estimator of cost ``model`` render MIN_SPP samples within
    ``budget``, as its model predicts?"""
    return costs.seconds_at(model, MIN_SPP) <= budget


def render(ctx) -> bool:
    """K timed renders per estimator at every budget (or the cached ones):
    at the spp the cost model predicts (at the second budget on, as far off
    as it was at the budget before, :func:`_carried`), then, for an
    estimator whose median missed the budget by more than ON_BUDGET, again
    at the spp the measured times say (:func:`corrected`), at most
    CORRECTIONS times (LOADED_CORRECTIONS where other processes loaded the
    machine during the last try); the try whose median came nearest the
    budget is the one measured."""
    sub, d = ctx.display, ctx.plan.display
    path = ctx.costs[REFERENCE]
    ctx.budgets = [(costs.seconds_at(path, s), s) for s in ctx.budget_path_spp]
    _note_overhead(ctx)
    last = len(ctx.budgets) - 1
    spps = [{n: path_spp if n == REFERENCE else costs.spp_for(m, budget)
             for n, m in ctx.costs.items()
             if n == REFERENCE or j == last or fits(m, budget)}
            for j, (budget, path_spp) in enumerate(ctx.budgets)]
    for n in ctx.costs:
        left = [f"{b * 1e3:.0f}" for (b, _), spp in zip(ctx.budgets, spps) if n not in spp]
        if left:
            ctx.notes.append(f"{n}: {MIN_SPP} samples per pixel take more than "
                             f"{' and '.join(left)} ms, where whole samples cannot come "
                             "within ±10 % of the budget: not rendered there")
    if ctx.budget_stacks:                                # from the cache
        return False
    # (untimed, at each estimator's largest spp: without it the first round
    # at a budget ran 15-40 % slow for every estimator in one of two quick
    # runs, and the known ratio of test_validate read 3 % low, outside its
    # interval. A timed render that compiles anyway, as guided_path's at a
    # new spp, is rendered again: run/renders.timed_render)
    warmed = {n: max(s[n] for s in spps if n in s) for n in spps[-1]}
    timing.warm(sub.run.executor, job(sub), warmed, sub.run.stream("speed_timing").seed(0))
    for j, ((budget, _), spp) in enumerate(zip(ctx.budgets, spps)):
        stacks_j, tries = {}, {n: [] for n in spp}
        todo = {n: s if not j or n not in ctx.budget_tries[-1] else
                _carried(ctx.costs[n], ctx.budget_tries[-1][n], ctx.budgets[j - 1][0], budget)
                for n, s in spp.items()}
        for attempt in range(1 + LOADED_CORRECTIONS):
            got = stacks.interleaved(
                sub, {n: sub.integrators[n] for n in todo}, todo, d.renders,
                sub.run.stream("speed", j).take(d.renders),
                f"{sub.label} {budget * 1e3:.0f} ms" + (f" (again: {len(todo)})"
                                                        if attempt else ""), timed=True)
            for n, u in got.items():
                tries[n].append(Try(spp=u.spp, wall_seconds=[float(x) for x in u.seconds],
                                    others_cores=load.cores(u.others, u.seconds)))
                if _closest(tries[n], budget) == len(tries[n]) - 1:
                    stacks_j[n] = u         # (a correction that did worse is not kept)
            todo = {n: nxt for n in got
                    if (nxt := corrected(ctx.costs[n], tries[n], budget,
                                         registry.facts(n).learns)) is not None}
            loaded = any((t[-1].others_cores or 0.0) > LOADED for t in tries.values())
            if not todo or attempt >= (LOADED_CORRECTIONS if loaded else CORRECTIONS):
                break
        ctx.budget_stacks.append({n: stacks_j[n] for n in spp})
        ctx.budget_tries.append(tries)
    ctx.timed_on = sub.run.executor.timed_on()
    return True


def corrected(model, tries: list[Try], budget: float, learns: bool = False) -> int | None:
    """The spp of the next try of an estimator whose last try's median wall
    time missed ``budget`` by more than ON_BUDGET; None where it did not, or
    where no other spp would do better (1 spp is already too slow, or, for
    an estimator that ``learns``, :func:`unreachable` found its step). The
    line through the model's fixed cost (spp 0, a) fitted to every render
    of every try so far, its step at most ×2 either way: on a loaded
    machine one try's median swung by 30-50 %, and a secant through the
    last one or two chased that noise (34 spp, then 1). Where the line
    rounds back to the last try's spp, the next whole sample toward the
    budget is tried."""
    last = tries[-1]
    median = float(np.median(last.wall_seconds))
    if abs(median - budget) <= ON_BUDGET * budget or (learns and unreachable(tries, budget)):
        return None
    fixed = min(max(model.fixed_s, 0.0), 0.5 * min(float(np.median(t.wall_seconds))
                                                  for t in tries))
    spp = np.concatenate([np.full(len(t.wall_seconds), t.spp, float) for t in tries])
    seconds = np.concatenate([np.asarray(t.wall_seconds, float) for t in tries])
    slope = float(np.sum((seconds - fixed) * spp) / np.sum(spp ** 2))
    if slope <= 0:
        return None
    step = min(max((budget - fixed) / slope / last.spp, 0.5), 2.0)
    nxt = max(1, int(round(last.spp * step)))
    if nxt == last.spp:
        # (the line rounds back to the spp that just missed: a slow first
        # try steepens it; bayesian_importance at 256², 603 ms: 6 spp took
        # 827 ms, then 4 spp 503 ms twice, where 5 spp was within 10 %)
        nxt = last.spp + 1 if median < budget else last.spp - 1
    return None if nxt < 1 else nxt


def unreachable(tries: list[Try], budget: float) -> tuple[int, int] | None:
    """(n, n + 1) where every try at n spp took less than ``budget`` by more
    than ON_BUDGET and every try at n + 1 more by more than it: no whole spp
    meets the budget, since the estimator's time jumps between the two
    (guided_path adds a training pass at some spp: at 128², training on ¼
    of its samples, its 12 spp took 30-45 % longer than its 11,
    docs/measurements.md#2026-12-03-budgets-learner-step-makes). None
    otherwise. A smooth estimator's one sample is a few % of a budget, so only
    a load swing makes such a pair for it (path under load: 8 spp 70 ms, 9 spp
    95 ms against 78 ms), and only a learner's stops the corrections
    (:func:`corrected`)."""
    lo, hi = (1 - ON_BUDGET) * budget, (1 + ON_BUDGET) * budget
    medians: dict[int, list[float]] = {}
    for t in tries:
        medians.setdefault(t.spp, []).append(float(np.median(t.wall_seconds)))
    for n, below in sorted(medians.items()):
        above = medians.get(n + 1)
        if above and max(below) < lo and min(above) > hi:
            return n, n + 1
    return None


def load_se(run) -> float:
    """What the load of other processes during a BudgetRun's measured try
    adds to its times' log-scale standard error (costs.load_log_se)."""
    measured = [t for t in run.tries if t.wall_seconds == run.wall_seconds] or run.tries
    return costs.load_log_se(measured[-1].others_cores if measured else None,
                             os.cpu_count() or 1)


def _carried(model, before: list[Try], before_budget: float, budget: float) -> int:
    """The first try's spp at ``budget``, after a smaller ``before_budget``
    whose ``before`` tries were measured: the model's spp for the time
    ``budget`` takes if the model is as far off as it was at the try nearest
    that budget (a factor within ×2 either way). On a quiet machine the
    renders at a scene's largest budget took 25-35 % longer than the model,
    fitted at small spp, said, for every estimator: each rendered twice."""
    near = before[_closest(before, before_budget)]
    predicted = costs.seconds_at(model, near.spp)
    off = float(np.median(near.wall_seconds)) / predicted if predicted > 0 else 1.0
    return costs.spp_for(model, budget / min(max(off, 0.5), 2.0))


def _closest(tries: list[Try], budget: float) -> int:
    """The index of the try whose median is nearest ``budget``."""
    return min(range(len(tries)),
               key=lambda i: abs(float(np.median(tries[i].wall_seconds)) - budget))


def job(sub):
    """``job(name, spp, seed)`` of the display scene (timing.py)."""
    return lambda name, spp, seed: sub.job(sub.integrators[name], spp, seed)


def _note_overhead(ctx) -> None:
    largest = ctx.budgets[-1][0]
    for n, m in ctx.costs.items():
        share = costs.overhead_share(m, largest)
        if share > costs.MAX_OVERHEAD:
            ctx.notes.append(
                f"{n}: its fixed cost {m.fixed_s * 1e3:.1f} ms is {100 * share:.0f} % of the "
                f"largest budget ({largest * 1e3:.1f} ms), where efficiency is read, over "
                "the 10 % the stage aims for: its efficiency is partly launch overhead")
