"""The speed-and-images stage: accuracy against time at the display resolution.

The small-image statistics (scene.py) decide whether an estimator is right;
this stage measures what it costs and shows what it looks like, at the
resolution of the scene's :class:`~mcillum.validation.plan.profiles.Display`,
in a sub-context of the scene's (``ctx.display``). Its stages, in order:

    display            the scene at the display resolution, same estimators
    time_costs         warm renders, estimators interleaved: ``repeats`` rounds
                       at 1 and 16 spp, the fastest of each → per estimator
                       t = a + b·spp, which places the budgets and predicts
                       each estimator's spp there
    render_budgets     (stages/budgets.py) budgets T = `path`'s model at
                       ``path_spp`` (scaled by one factor until every a ≤ 10 %
                       of the largest T, where efficiency is read, and every
                       estimator renders ≥ MIN_SPP spp there; a smaller T
                       renders those that fit MIN_SPP in it);
                       K renders per estimator and budget at
                       spp = max(1, round((T − a)/b)), interleaved, each timed;
                       an estimator whose median missed T by more than 10 %
                       renders its K again at the spp its measured times say,
                       at most three times (four on a loaded machine; for
                       an estimator that learns, not once adjacent spp
                       fell on both sides of T); every try is kept
    display_reference  `path` until its standard error is at most the profile's
                       ``display_reference_fraction`` (25 %) of `path`'s own RMSE
                       at the largest budget (run/references.py: adaptive,
                       cached by content): about 16× `path`'s spp there. Its
                       share of every relMSE is recorded (``reference_relmse``:
                       6 % of path's, with its standard error)
    measure_speed      per estimator t = a + b·spp with bootstrap intervals
                       (stats/costs.py) through every pilot render (the
                       budgets' own times are shown beside it);
                       relMSE with its interval per budget, wall times against
                       the budget, efficiency against `path` net of the
                       reference's share (stats/costs.py), a ranking with
                       ties, FLIP; an estimator whose relMSE is within 2× of
                       the share is flagged (its efficiency is a lower bound:
                       in the furnace the cosine estimator is exact), one
                       biased by design is marked so, and one whose
                       fireflies carry an error K renders cannot bound
                       (stats/tails.py: error_tail) is heavy-tailed, its
                       efficiency an upper bound; one whose median
                       (or path's) is still beyond ×EQUAL_TIME of its
                       budget after the corrections has its efficiency
                       withheld and is not ranked (:func:`off_budget`);
                       the cores other
                       processes used while the renders were timed
                       (run/load.py), and a note above LOADED
    save_display       images/<scene>/display/: the reference; per estimator
                       its first render at the largest budget with its FLIP map

Timings and renders are kept in the run directory (``renders/<scene>/speed.npz``,
results/layout.py; speed_cache.py) under a key (scene content, estimators,
settings): a re-run into a finished directory renders nothing; the timings
it reports are the first run's.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from mcillum import files
from mcillum.integrators.core import registry

from ..results import Budget, BudgetRun, Interval, Ratio, Speed, Try, layout
from ..run import load, probe, references, timing
from ..run.stacks import Stack
from ..stats import costs, metrics, tails
from . import budgets, common, speed_cache
from .budgets import EQUAL_TIME, LOADED, ON_BUDGET, REFERENCE, budget_spp, equal_time, load_se
from .budgets import job as _job

PILOT_SPP = (1, 16)
CACHE_VERSION = 4


# ----------------------------- The display scene --------------------------------

def display(ctx) -> None:
    """The scene at the display resolution with the estimators the scene
    comparison chose; its cached timings and renders if a run left them."""
    d = ctx.plan.display
    sub = ctx.derive(list(ctx.integrators), label=f"{ctx.id} {d.res}²",
                     plan=dataclasses.replace(ctx.plan, res=d.res))
    common.load(sub)
    sub.integrators = dict(ctx.integrators)           # (integrators hold no scene)
    ctx.display = sub
    speed_cache.load(ctx, [PILOT_SPP, CACHE_VERSION])


def time_costs(ctx) -> None:
    """A pilot cost model t = a + b·spp per estimator through the fastest of
    the profile's ``repeats`` renders at 1 and 16 spp (a ≈ t(1) − b): it
    places the budgets and predicts each estimator's spp there. The model
    reported, with intervals, is the line through every pilot render
    (:func:`measure_speed`).
    Rounds at spp near the smallest budget used to follow; the budgets'
    corrections made them redundant
    (docs/measurements.md#2026-12-03-quick-profile-cost-reference).
    Before the run's first timed render, the machine's probe (run/probe.py);
    a re-run whose timings are all kept takes none."""
    ctx.run.executor.timed_on()                         # (forget earlier stages')
    if ctx.run.machine_speed is None and (ctx.timings is None or not ctx.budget_stacks):
        # (the run's first timed renders: the machine's speed first, to
        # compare its timings and wall time with another machine's)
        ctx.run.machine_speed = probe.machine_speed()
    if ctx.timings is None:                             # (else from the cache)
        sub, d = ctx.display, ctx.plan.display
        ctx.timings = timing.timed(sub.run.executor, _job(sub),
                                   dict.fromkeys(sub.integrators, list(PILOT_SPP)),
                                   d.repeats, ctx.run.stream("speed_timing"), ctx.timing_load)
    ctx.costs = {n: costs.fit_cost({s: [min(t)] * 2 for s, t in spps.items()})
                 for n, spps in ctx.timings.items()}
    if ctx.budget_path_spp is None:
        ctx.budget_path_spp = budget_spp(ctx.costs, ctx.plan.display.path_spp)


# --------------------------------- Budgets ---------------------------------------

def render_budgets(ctx) -> None:
    """K timed renders per estimator at every budget, met by correction
    (stages/budgets.py), kept in the run directory; or the kept ones."""
    if budgets.render(ctx):
        speed_cache.save(ctx, [PILOT_SPP, CACHE_VERSION])


# -------------------------------- Reference --------------------------------------

def display_reference(ctx) -> None:
    """`path` at the display resolution, precise to the profile's fraction of
    the smallest RMSE at the largest budget."""
    sub = ctx.display
    own = ctx.budget_stacks[-1][REFERENCE]
    target = references.target_for([own.images], ctx.run.profile.display_reference_fraction)
    # (its pixels' variances are read on average: fewer, larger passes)
    sub.reference = references.ensure(sub, target,
                                      references.expected_spp(own.images, own.spp, target),
                                      references.AVERAGE_PASSES_WANTED)


# --------------------------------- Numbers ---------------------------------------

def measure_speed(ctx) -> None:
    sub, d = ctx.display, ctx.plan.display
    ref = sub.reference
    r = ref.mean[..., :3]
    share = costs.reference_share(r, ref.variance_of_mean, ref.passes)
    budgets = []
    last = len(ctx.budgets) - 1
    for j, ((budget, path_spp), by_name) in enumerate(zip(ctx.budgets, ctx.budget_stacks)):
        read = {n: _budget_run(ctx, n, u, budget, r, ctx.budget_tries[j][n], j == last)
                for n, u in by_name.items()}
        # (tail: the largest budget's when the loop ends, as the kinds read it)
        runs, tail = {n: b for n, (b, _) in read.items()}, {n: t for n, (_, t) in read.items()}
        budgets.append(Budget(seconds=budget, path_spp=path_spp, estimators=runs,
                              reference_relmse=share.value, reference_relmse_se=share.se))
    top = budgets[-1].estimators
    base = top[REFERENCE]
    # (the times of a loaded machine say less than their scatter shows)
    eff = {n: costs.efficiency(run.relmse_per_render, run.wall_seconds, share, load_se(run))
           for n, run in top.items()}
    ratios = off_budget(top, budgets[-1].seconds)
    for n in ratios:
        ctx.notes.append(f"{n}: efficiency ÷ path withheld: {ratios[n].reason}")
    for n, run in top.items():
        if n in ratios:
            continue
        ratio, ci = costs.ratio(eff[n], eff[REFERENCE],
                                min(len(run.relmse_per_render), len(base.relmse_per_render)))
        ratios[n] = Ratio(ratio=ratio, ci=ci, kind=_kind(n, run, share, tail[n]))
        if ratios[n].kind == "reference_limited":
            ctx.notes.append(f"{n}: its relMSE {run.relmse:.3g} is within "
                             f"{metrics.RESOLVED:g}× of the "
                             f"reference's own share {share.value:.3g}: the reference "
                             "limits it, and its efficiency is a lower bound")
        elif ratios[n].kind == "heavy_tailed":
            # (the interval's upper end holds: a mean over renders that
            # have not yet seen the rare errors reads the error low)
            ratios[n].ci = Interval(0.0, ci.high)
            eff[n] = dataclasses.replace(eff[n], ci=Interval(0.0, eff[n].ci.high))
    ctx.notes.extend(learner_notes(budgets))
    # (a withheld figure is not ranked: it was not read at equal time)
    ranking = costs.ranking({n: (e.value, e.ci) for n, e in eff.items()
                             if ratios[n].kind != "off_budget"})
    # the pilot's renders, every repeat: a line through the budgets' renders
    # too gave fixed costs of -8 to -14 ms [intervals below 0], since a sample
    # costs less at large spp than at 1-16
    # (docs/measurements.md#2026-12-03-quick-profile-cost-reference)
    models = {n: costs.fit_cost(ctx.timings[n]) for n in ctx.costs}
    others, cores, loaded = _load(ctx)
    flips = {n: metrics.flip(u.images[0], r) for n, u in ctx.budget_stacks[-1].items()}
    ctx.flip_maps = {n: f[0] for n, f in flips.items() if f is not None}
    ctx.speed = Speed(
        res=d.res, renders=d.renders, cost_model=models, budgets=budgets,
        efficiency_vs_path=ratios, ranking=ranking, reference=common.reference_summary(ref),
        mean_flip={n: (f[1] if f is not None else float("nan")) for n, f in flips.items()},
        notes=list(ctx.notes), timed_on=list(ctx.timed_on), others_cores=others,
        cores=cores, loaded=loaded)


def off_budget(runs: dict[str, BudgetRun], budget: float) -> dict[str, Ratio]:
    """The efficiency ratios to withhold at ``budget`` (seconds): {name:
    Ratio of NaN, kind "off_budget", its reason} for each estimator of
    ``runs`` whose median wall time missed the budget beyond
    budgets.EQUAL_TIME (after every correction, stages/budgets.py), and for
    every one where path's own did (each ratio divides by it)."""
    def miss(run: BudgetRun) -> str:
        median = float(np.median(run.wall_seconds))
        return (f"median {median * 1e3:.3g} ms at {run.spp} spp against a "
                f"{budget * 1e3:.3g} ms budget (×{median / budget:.2g}, beyond "
                f"×{EQUAL_TIME:g} either way)")

    base = runs.get(REFERENCE)
    path_off = base is not None and not equal_time(base.wall_seconds, budget)
    out = {}
    for n, run in runs.items():
        if path_off:
            why = f"path, which every ratio divides by, took {miss(base)}"
        elif not equal_time(run.wall_seconds, budget):
            why = miss(run)
        else:
            continue
        out[n] = Ratio(ratio=math.nan, ci=Interval(math.nan, math.nan), kind="off_budget",
                       reason=f"off budget: {why}: not an equal-time figure")
    return out


def learner_notes(found: list[Budget]) -> list[str]:
    """A note per estimator that learns (registry facts ``learns``) of its
    efficiency ÷ path at each of the budgets ``found``: its training is paid
    again in every render, so a larger budget amortises it and the figure
    rises with the budget (guided_path on the Cornell box: 0.72 at 24 spp,
    0.86 at 45, docs/measurements.md#2026-12-05-ms-floor-recording-lingering).
    Each is net of its own budget's reference share; the ranking reads the
    largest."""
    notes = []
    names = [n for n in found[-1].estimators if n != REFERENCE and registry.facts(n).learns]
    for name in names:
        parts = []
        for b in found:
            run, base = b.estimators.get(name), b.estimators.get(REFERENCE)
            if run is None or base is None:
                continue
            if name in off_budget({name: run, REFERENCE: base}, b.seconds):
                parts.append(f"withheld (off budget) at {b.seconds * 1e3:.0f} ms")
                continue
            share = costs.Share(b.reference_relmse, b.reference_relmse_se)
            ratio, ci = costs.ratio_interval(run.relmse_per_render, run.wall_seconds,
                                             base.relmse_per_render, base.wall_seconds, share,
                                             load_se(run), load_se(base))
            parts.append(f"{ratio:.3g} [{ci.low:.3g}, {ci.high:.3g}] at {b.seconds * 1e3:.0f} ms "
                         f"({run.spp} spp)")
        if len(parts) > 1:
            notes.append(f"{name} learns while it renders, and pays for its training in every "
                         f"render: efficiency ÷ path {', '.join(parts)}. A larger budget "
                         "amortises the training; the ranking reads the largest.")
    return notes


def _kind(name: str, run: BudgetRun, share: costs.Share, tail: tails.ErrorTail) -> str:
    """What the estimator's efficiency figure means (results.KINDS)."""
    if not registry.facts(name).unbiased:
        return "biased"
    # (before reference_limited: that figure's lower bound needs the very
    # upper end of the error that a heavy tail takes away)
    if tail.unbounded and name != REFERENCE:
        return "heavy_tailed"
    return "reference_limited" if run.relmse < metrics.RESOLVED * share.value else "unbiased"


def _load(ctx) -> tuple[float | None, int, bool]:
    """(cores other processes used on average during the timed renders,
    this machine's cores, whether that is above LOADED); notes it when so."""
    seconds = [t for t, _ in ctx.timing_load]
    others = [o for _, o in ctx.timing_load]
    for tries in ctx.budget_tries:
        for ts in tries.values():
            for t in ts:
                seconds.append(float(np.sum(t.wall_seconds)))
                others.append(None if t.others_cores is None
                              else t.others_cores * float(np.sum(t.wall_seconds)))
    used, cores = load.cores(others, seconds), os.cpu_count() or 1
    loaded = used is not None and used > LOADED
    if loaded:
        ctx.notes.append(
            f"the machine was loaded: other processes used {used:.2f} of its {cores} cores "
            "on average while these renders were timed; the times, and the efficiency "
            "figures, are those of a loaded machine (run again on a quiet one to compare)")
    return used, cores, loaded


def _budget_run(ctx, name: str, stack: Stack, budget: float, r: np.ndarray,
                tries: list[Try], top: bool) -> tuple[BudgetRun, tails.ErrorTail]:
    """One estimator's K renders at one budget, and their error's tail
    (stats/tails.py), noted where K renders cannot bound it."""
    per = metrics.per_render_relmse(stack.images, r).tolist()
    mean, ci = costs.relmse_interval(per)
    median = float(np.median(stack.seconds))
    on = abs(median - budget) <= ON_BUDGET * budget
    note = None
    if not on:
        one = costs.seconds_at(ctx.costs[name], 1)
        again = f" after {len(tries) - 1} corrections" if len(tries) > 1 else ""
        gap = budgets.unreachable(tries, budget)
        if stack.spp == 1 and one > budget:
            note = (f"1 spp already takes {one * 1e3:.1f} ms (cost model), more than the "
                    f"{budget * 1e3:.1f} ms budget")
        elif gap:
            at = {n: float(np.median([np.median(t.wall_seconds) for t in tries if t.spp == n]))
                  for n in gap}
            why = ("it adds a training pass between them" if registry.facts(name).learns
                   else "its times varied more than the spp could follow")
            note = (f"no whole spp met the {budget * 1e3:.1f} ms budget: {gap[0]} spp took "
                    f"{at[gap[0]] * 1e3:.1f} ms, {gap[1]} spp {at[gap[1]] * 1e3:.1f} ms{again}; "
                    f"{why}")
        else:
            note = (f"median {median * 1e3:.1f} ms at {stack.spp} spp against a "
                    f"{budget * 1e3:.1f} ms budget ({100 * (median / budget - 1):+.0f} %)"
                    f"{again}: its times varied more than the spp could follow")
        ctx.notes.append(f"{name} at {budget * 1e3:.1f} ms: {note}")
    tail = tails.error_tail(stack.images, r)
    if tail.unbounded:
        # (no upper end: the mean misses the rare errors the renders have
        # not seen yet; its lower end holds, stats/tails.py)
        ci = Interval(ci.low, math.inf)
        then = ""
        if top:         # (where efficiency is read)
            then = (", and its efficiency is an upper bound" if name != REFERENCE else
                    ", and every efficiency ratio, which divides by its efficiency, may "
                    "read low: their upper ends do not hold")
        ctx.notes.append(f"{name} at {budget * 1e3:.1f} ms: {tail.text()}: its K renders "
                         "cannot bound its mean error, so its relMSE has a lower bound "
                         f"only{then}")
    return BudgetRun(spp=stack.spp, wall_seconds=[float(s) for s in stack.seconds], relmse=mean,
                     relmse_ci=ci, relmse_per_render=per, on_budget=on, note=note,
                     tries=list(tries)), tail


# --------------------------------- Images ----------------------------------------

def save_display(ctx) -> None:
    """images/<scene>/display/: the reference; each estimator's first render at
    the largest budget with its FLIP map as layer ``flip``."""
    sub = ctx.display
    out = layout.made(layout.display_dir(ctx.run.out_dir, ctx.id))
    ref = sub.reference
    files.write_exr(f"{out}/reference.exr", ref.mean[..., :3].astype(np.float32),
                    {"spp": ref.spp, "passes": ref.passes})
    budget = ctx.budgets[-1][0]
    for n, stack in ctx.budget_stacks[-1].items():
        layers = {"flip": ctx.flip_maps[n][..., None]} if n in ctx.flip_maps else None
        files.write_exr(f"{out}/{n}.exr", stack.images[0].astype(np.float32),
                        {"integrator": n, "spp": stack.spp,
                         "seed": ctx.run.stream("speed", len(ctx.budgets) - 1).seed(0),
                         "render_seconds": float(stack.seconds[0]),
                         "budget_seconds": budget}, layers)


def release_display(ctx) -> None:
    """The display scene is rendered no more (common.release)."""
    common.release(ctx.display)
