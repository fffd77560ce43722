"""The budget axis: relMSE against wall time per render, from a tenth of a
second to a minute, at the display resolution (ctx.display), where the
profile's [display] gives ``axis`` (a budget in seconds per render each).

The speed stage (speed.py) reads efficiency at a tenth of a second; people
render for seconds to minutes, where an estimator that learns has paid for
its training and one that converges faster than N^-1/2 has pulled ahead.
Its stages, in order:

    render_axis    after the display reference, before the display scene is
                   let go: at each budget T, K timed renders per estimator,
                   interleaved (more below a second: ``renders_at``), at
                   the spp its cost model gives at the first budget and
                   the per-sample time it showed at the last one after;
                   a set whose median missed T beyond ON_BUDGET renders
                   again at the corrected spp (budgets.corrected; above
                   CHEAP seconds of renders only beyond EQUAL_TIME, once).
                   Measured at every budget: ``axis_measured`` (path, mis)
                   and every estimator that learns (never extrapolated). A
                   fixed-pdf estimator is measured up to ``axis_model_above``
                   and at the next budget, where the model c/(t − t0)
                   fitted below it is checked (stats/axis.py); agreeing, it
                   is drawn from the model above; not, it is measured on.
    measure_axis   relMSE of every point from the spread of its renders
                   (stats/axis.py: no reference can resolve a minute of
                   `path`; the reference only scales each pixel), efficiency
                   ÷ path at each budget, a ranking per budget, and where
                   an estimator's ratio crosses 1 → ctx.budget_axis.

The renders and their times are kept in the run directory
(``renders/<scene>/axis.npz``) under a key (scene content and seed set, as
``render_key`` holds them; estimators; the display plan): a re-run into a finished directory renders nothing, and
reports the first run's times.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os

import numpy as np

from mcillum import files

from mcillum.integrators.core import registry

from ..results import (AxisBudget, AxisCrossing, AxisModel, AxisPoint, BudgetAxis, Interval,
                       Try, layout, seconds_text)
from ..run import load, stacks
from ..run.stacks import Stack
from ..stats import axis, costs
from .budgets import CORRECTIONS, EQUAL_TIME, REFERENCE, corrected

#: Seconds of renders (K × the budget) below which a set that missed its
#: budget is corrected as the speed stage's are; above it, once, and only
#: beyond EQUAL_TIME: a correction at a minute costs K minutes, and a point
#: is charted at its measured time anyway.
CHEAP = 10.0
#: Below a second a budget gets up to this many seconds of renders, at most
#: MAX_RENDERS: a tighter spread for little time.
SMALL_SECONDS = 1.0
MAX_RENDERS = 8
CACHE_VERSION = 1


def renders_at(budget: float, k: int) -> int:
    """Renders at ``budget`` seconds: ``k``, more below SMALL_SECONDS."""
    return max(k, min(MAX_RENDERS, math.ceil(SMALL_SECONDS / budget)))


def planned_renders(estimators, display) -> int:
    """The axis's renders if every estimator rendered every budget once (no
    corrections; fewer where a model draws a point): the progress bar's."""
    return len(estimators) * sum(renders_at(t, display.axis_renders) for t in display.axis)


# --------------------------------- Renders ---------------------------------------

def render_axis(ctx) -> None:
    """K timed renders per estimator and budget of the axis (module doc)."""
    d = ctx.plan.display
    if not d.axis:
        return
    if _load_cache(ctx):
        return
    sub = ctx.display
    names = list(sub.integrators)
    always = {n for n in names if n in d.axis_measured or registry.facts(n).learns}
    check_at = next((t for t in d.axis if t > d.axis_model_above), None)
    r = sub.reference.mean[..., :3]
    ctx.axis_renders = {n: [] for n in names}
    models = ctx.axis_models = {}
    for j, budget in enumerate(d.axis):
        todo = {}
        for n in names:
            if n in models and models[n].agrees:
                continue                    # (drawn from its model)
            spp = _first_spp(ctx, n, budget)
            if spp is None:
                continue
            todo[n] = spp
        if not todo:
            continue
        k = renders_at(budget, d.axis_renders)
        for n, (stack, tries) in _on_budget(ctx, todo, budget, k, j).items():
            ctx.axis_renders[n].append((budget, stack, tries))
        if budget == check_at:
            for n in names:
                if n not in always and ctx.axis_renders[n]:
                    models[n] = _checked_model(ctx, n, r, d.axis_model_above, budget)
    _save_cache(ctx)


def _first_spp(ctx, name: str, budget: float) -> int | None:
    """The spp of ``name``'s first try at ``budget``: its cost model's at
    the first budget it renders, then the per-sample time its last
    measured budget showed (its training included); None, with a note,
    where one sample already takes beyond EQUAL_TIME × the budget."""
    model = ctx.costs[name]
    done = ctx.axis_renders[name]
    if done:
        _, stack, _ = done[-1]
        fixed = min(max(model.fixed_s, 0.0), 0.5 * float(np.median(stack.seconds)))
        per = (float(np.median(stack.seconds)) - fixed) / stack.spp
        spp = max(1, round((budget - fixed) / per)) if per > 0 else costs.spp_for(model, budget)
    else:
        spp = costs.spp_for(model, budget)
    if spp <= 1 and costs.seconds_at(model, 1) > EQUAL_TIME * budget:
        ctx.axis_notes.append(f"{name}: 1 spp takes {costs.seconds_at(model, 1):.3g} s (its "
                              f"cost model), beyond the {seconds_text(budget)} budget: not "
                              "rendered there")
        return None
    return spp


def _on_budget(ctx, todo: dict[str, int], budget: float, k: int, block: int) -> dict:
    """{name: (Stack, [Try])}: K renders of each of ``todo`` (name → spp)
    at ``budget``, corrected as the module doc says; the try whose median
    came nearest the budget is kept."""
    sub = ctx.display
    tries = {n: [] for n in todo}
    kept = {}
    cheap = k * budget <= CHEAP
    for attempt in range(1 + (CORRECTIONS if cheap else 1)):
        got = stacks.interleaved(
            sub, {n: sub.integrators[n] for n in todo}, todo, k,
            ctx.run.stream("budget_axis", block).take(k),
            f"{sub.label} axis {seconds_text(budget)}" + (f" (again: {len(todo)})"
                                                           if attempt else ""), timed=True)
        for n, stack in got.items():
            tries[n].append(Try(spp=stack.spp, wall_seconds=[float(x) for x in stack.seconds],
                                others_cores=load.cores(stack.others, stack.seconds)))
            if n not in kept or _miss(stack.seconds, budget) < _miss(kept[n].seconds, budget):
                kept[n] = stack
        todo = {n: nxt for n in got
                if (cheap or _miss(got[n].seconds, budget) > math.log(EQUAL_TIME))
                and (nxt := corrected(ctx.costs[n], tries[n], budget,
                                      registry.facts(n).learns)) is not None}
        if not todo:
            break
    return {n: (kept[n], tries[n]) for n in kept}


def _miss(seconds, budget: float) -> float:
    """How far a set's median time lies from ``budget``, on a log scale."""
    return abs(math.log(float(np.median(seconds)) / budget))


def _checked_model(ctx, name: str, r, fitted_to: float, check: float) -> AxisModel:
    """``name``'s model fitted to its points up to ``fitted_to`` seconds and
    checked against its point at ``check``; a note where it disagrees (the
    estimator is then measured on)."""
    points = [(b, _estimate(ctx, name, s, r)) for b, s, _ in ctx.axis_renders[name]]
    stack_at = {b: s for b, s, _ in ctx.axis_renders[name]}
    fitted = [(b, e) for b, e in points if b <= fitted_to]
    at_check = [e for b, e in points if b == check]
    if not fitted or not at_check:
        return AxisModel(c=math.nan, t0=math.nan, log_se=math.inf, fitted_to=fitted_to,
                         agrees=False)
    model = axis.fit([float(np.median(stack_at[b].seconds)) for b, _ in fitted],
                     [e.value for _, e in fitted], [e.log_se for _, e in fitted],
                     ctx.costs[name].fixed_s)
    seconds = float(np.median(stack_at[check].seconds))
    ok = axis.agrees(model, seconds, at_check[0])
    if not ok:
        ctx.axis_notes.append(
            f"{name}: its model c/(t − t0) through the budgets up to "
            f"{seconds_text(fitted_to)} predicted relMSE {model.relmse(seconds):.3g} at "
            f"{seconds_text(seconds)}, where {at_check[0].value:.3g} "
            f"[{at_check[0].ci.low:.3g}, {at_check[0].ci.high:.3g}] was measured: "
            "measured at every budget instead")
    return AxisModel(c=model.c, t0=model.t0, log_se=model.log_se, fitted_to=fitted_to,
                     checked_at=check, predicted=model.relmse(seconds), agrees=ok)


def _estimate(ctx, name: str, stack, r) -> axis.Estimate:
    """relMSE of one render from ``stack`` (stats/axis.py): the spread of
    its renders, with bias² against the reference for an estimator biased
    by design."""
    if registry.facts(name).unbiased:
        return axis.spread_relmse(stack.images, r)
    ref = ctx.display.reference
    return axis.error_relmse(stack.images, r, ref.variance_of_mean)


# ---------------------------------- Cache ----------------------------------------

def _cache_file(ctx) -> tuple[str, str]:
    sub = ctx.display
    key = hashlib.sha256(json.dumps(
        [sub.render_key, list(sub.integrators), dataclasses.asdict(ctx.plan.display),
         CACHE_VERSION]).encode()).hexdigest()[:24]
    return layout.kept_renders(ctx.run.out_dir, ctx.id, "axis"), key


def _load_cache(ctx) -> bool:
    """The kept renders, models and notes of an earlier run of this axis;
    False where there are none (absent, partial, another key)."""
    path, key = _cache_file(ctx)
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return False
            meta = json.loads(str(z["meta"]))
            renders = {n: [(b, Stack(n, spp, z[f"images_{n}_{i}"], list(seconds)),
                            [Try(**t) for t in tries])
                           for i, (b, spp, seconds, tries) in enumerate(points)]
                       for n, points in meta["renders"].items()}
    except Exception:  # absent, partial or from another version: render anew
        return False
    ctx.axis_renders = renders
    ctx.axis_models = {n: AxisModel(**m) for n, m in meta["models"].items()}
    ctx.axis_notes = list(meta["notes"])
    ctx.run.step(f"{ctx.id} budget axis: loaded", 0)
    return True


def _save_cache(ctx) -> None:
    path, key = _cache_file(ctx)
    arrays = {"key": key, "meta": json.dumps({
        "renders": {n: [[b, s.spp, [float(x) for x in s.seconds],
                         [dataclasses.asdict(t) for t in tries]] for b, s, tries in points]
                    for n, points in ctx.axis_renders.items()},
        "models": {n: dataclasses.asdict(m) for n, m in ctx.axis_models.items()},
        "notes": ctx.axis_notes})}
    for n, points in ctx.axis_renders.items():
        for i, (_, s, _) in enumerate(points):
            arrays[f"images_{n}_{i}"] = s.images
    os.makedirs(os.path.dirname(path), exist_ok=True)
    files.write_arrays(path, arrays)


# --------------------------------- Numbers ---------------------------------------

def measure_axis(ctx) -> None:
    """The axis's records (module doc) → ``ctx.budget_axis``."""
    d = ctx.plan.display
    if not d.axis or not ctx.axis_renders:
        return
    r = ctx.display.reference.mean[..., :3]
    curves, models = {}, {}
    for name, measured in ctx.axis_renders.items():
        points = {b: _measured_point(ctx, name, b, s, r) for b, s, _ in measured}
        model = _model(ctx, name)
        if model is not None:
            models[name] = model
            fitted = axis.Model(model.c, model.t0, model.log_se)
            for b in d.axis:
                if b > (model.checked_at or math.inf) and b not in points:
                    value = fitted.relmse(b)
                    half = axis.Z * model.log_se
                    points[b] = AxisPoint(budget=b, measured=False, seconds=b, relmse=value,
                                          relmse_ci=Interval(value * math.exp(-half),
                                                             value * math.exp(half)),
                                          log_se=model.log_se)
        if points:
            curves[name] = [points[b] for b in sorted(points)]
    rankings, crossings = _compare(curves, d.axis)
    ctx.budget_axis = BudgetAxis(res=d.res, renders=d.axis_renders, budgets=list(d.axis),
                                 curves=curves, models=models, rankings=rankings,
                                 crossings=crossings,
                                 notes=list(ctx.axis_notes) + _crossing_notes(crossings,
                                                                             rankings))


def _measured_point(ctx, name: str, budget: float, stack, r) -> AxisPoint:
    e = _estimate(ctx, name, stack, r)
    return AxisPoint(budget=budget, measured=True, seconds=float(np.median(stack.seconds)),
                     relmse=e.value, relmse_ci=e.ci,
                     log_se=float(math.hypot(e.log_se, axis.log_se_of_times(stack.seconds))),
                     spp=stack.spp, wall_seconds=[float(x) for x in stack.seconds])


def _model(ctx, name: str) -> AxisModel | None:
    """The model render_axis checked for a fixed-pdf estimator, where it
    agreed; None for one measured throughout."""
    model = ctx.axis_models.get(name)
    return model if model is not None and model.agrees else None


def _compare(curves: dict, budgets) -> tuple[list[AxisBudget], list[AxisCrossing]]:
    """Efficiency ÷ path written into each point, a ranking per budget,
    and every estimator's crossings of path's efficiency."""
    base = {p.budget: p for p in curves.get(REFERENCE, [])}
    rankings = []
    for b in budgets:
        here = {n: p for n, ps in curves.items() for p in ps if p.budget == b}
        if len(here) < 2:
            continue
        effs = {}
        for n, p in here.items():
            value = 1.0 / (p.relmse * p.seconds) if p.relmse > 0 else math.inf
            half = axis.Z * p.log_se
            effs[n] = (value, Interval(value * math.exp(-half), value * math.exp(half)))
            if b in base and n != REFERENCE and p.relmse > 0 and base[b].relmse > 0:
                p.efficiency_vs_path, p.efficiency_vs_path_ci = axis.ratio(
                    p.relmse, p.seconds, p.log_se,
                    base[b].relmse, base[b].seconds, base[b].log_se)
        rankings.append(AxisBudget(seconds=b, ranking=costs.ranking(effs)))
    crossings = []
    for n, ps in curves.items():
        if n == REFERENCE:
            continue
        ratios = [(p.efficiency_vs_path, math.hypot(p.log_se, base[p.budget].log_se))
                  if p.efficiency_vs_path is not None else None for p in ps]
        for c in axis.crossings(n, [p.budget for p in ps], ratios):
            verb = "overtakes" if c.overtakes else "falls behind"
            sides = (f"behind at {seconds_text(c.behind_at)}, ahead at "
                     f"{seconds_text(c.ahead_at)}")
            crossings.append(AxisCrossing(
                estimator=n, seconds=c.seconds, overtakes=c.overtakes, behind_at=c.behind_at,
                ahead_at=c.ahead_at,
                text=f"{n} {verb} path at about {seconds_text(c.seconds)} ({sides}, 99 %)"))
    return rankings, crossings


def _crossing_notes(crossings: list[AxisCrossing], rankings: list[AxisBudget]) -> list[str]:
    """The crossings, and who leads at each budget, in sentences."""
    lead = []
    for b in rankings:
        first = [p for p in b.ranking if p.rank == 1]
        ties = f" (tied: {', '.join(p.estimator for p in first[1:])})" if len(first) > 1 else ""
        lead.append(f"{seconds_text(b.seconds)}: {first[0].estimator}{ties}")
    notes = [c.text for c in crossings]
    if lead:
        notes.append("most efficient at each budget: " + "; ".join(lead))
    return notes
