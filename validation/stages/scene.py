"""The stages of a scene comparison: K renders per estimator on every rung of
an spp ladder, then what they measure against the reference.

* Metrics per rung (stats/metrics.py): relMSE, MSE, MAPE, bias, variance,
  efficiency 1 / (relMSE · seconds) per render.
* Unbiasedness: the batch-means test of all rungs pooled against the
  reference (stats/statistics.py) and the fireflies of the estimator's
  renders (stats/tails.py), continued on fresh batches where the rules of
  evidence cannot decide yet, and confirmed on one where they count a
  rejection (:func:`settle`, stages/sequential.py).
* Convergence: least-squares fit of log relMSE against log spp over the
  ladder (relMSE averaged over the K renders at each spp, minus the part the
  reference's own noise adds, mean var_ref/(r² + ε)); the slope's (1 − α)
  interval is Student-t with n − 2 degrees of freedom, and at least as wide
  as each rung's own uncertainty (the spread of its K renders' relMSE)
  makes it. Monte Carlo expects −1. An estimator with zero variance at
  every rung is exact and converges trivially (the cosine estimator in a
  furnace).

The verdicts are checks/scene.py's. Accuracy at equal time is the
speed-and-images stage's (speed.py): at these small sizes a render's time
is mostly its fixed cost.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from mcillum import files

from ..checks import convergence, evidence
from ..results import Convergence, EstimatorResult, RunStats, SceneResult, Unbiasedness
from ..run import stacks
from ..stats import metrics, statistics, tails
from . import sequential, sun_split
from .common import REFERENCE, compile_kernels, kept_file, reference_summary, scene_summary

ALPHA = statistics.ALPHA


def render_ladder(ctx) -> None:
    """K renders per estimator on every rung of the plan's spp ladder (kept)."""
    ctx.stacks = stacks.ladder(ctx, compile_kernels)


# ---------------------------------- Measure -------------------------------------

def measure(ctx) -> None:
    """Per estimator: metrics per rung, the pooled unbiasedness test with the
    fireflies of its renders (``ctx.evidence``; path's fireflies stand for the
    reference's tail) and the convergence fit."""
    ladder, ref = ctx.plan.ladder, ctx.reference
    rungs = {name: {spp: ctx.stacks[spp][name].images for spp in ladder}
             for name in ctx.integrators}
    events = {name: tails.tail_events(s.values(), ref.mean, s.keys())[0]
              for name, s in rungs.items()}
    path_events = events.get(REFERENCE)                     # the reference's tail
    for name in ctx.integrators:
        runs = [run_stats(ctx.stacks[spp][name], ref) for spp in ladder]
        found = ctx.evidence[name] = bias_evidence(rungs[name], ref, runs, events[name],
                                                   path_events)
        ctx.measured[name] = EstimatorResult(
            name=name, params=dict(ctx.integrators[name].params),
            compile_seconds=ctx.compile_seconds.get(name, float("nan")), runs=runs,
            unbiasedness=unbiasedness_record(found, max(ladder)),
            convergence=convergence_fit(runs))
    # path's own renders share every estimator's seeds, hence its pixel
    # samples: its rejections mark pixels the budget cannot judge (evidence.py)
    if REFERENCE in ctx.evidence:
        control = evidence.control_pixels(ctx.evidence[REFERENCE].comparison)
        for name, found in ctx.evidence.items():
            found.control, found.is_control = control, name == REFERENCE


def run_stats(stack, reference) -> RunStats:
    """Metrics of K renders of one estimator at one spp (see metrics.py)."""
    x = stack.images[..., :3].astype(np.float64)
    r = reference.mean[..., :3]
    per = metrics.per_render_relmse(x, r)
    rel = float(np.mean(per))
    b, se = metrics.bias(x, r, reference.image_mean_se)
    med = float(np.median(stack.seconds))
    pixels = x.shape[1] * x.shape[2]
    return RunStats(
        spp=stack.spp, renders=x.shape[0], relmse=rel, relmse_per_render=per.tolist(),
        mse=float(np.mean([metrics.mse(i, r) for i in x])),
        mape=float(np.mean([metrics.mape(i, r) for i in x])), bias=b, bias_se=se,
        variance_per_render=metrics.variance_per_render(x),
        nonfinite_fraction=metrics.nonfinite_fraction(stack.images), median_seconds=med,
        seconds=[float(s) for s in stack.seconds], samples_per_second=pixels * stack.spp / med,
        efficiency=1.0 / (rel * med) if rel > 0 else float("inf"),
        reference_relmse=metrics.reference_relmse(r, reference.variance_of_mean),
        firefly_fraction=tails.firefly_fraction(np.nan_to_num(x), r))


def bias_evidence(rungs: dict, reference, runs: list[RunStats], events: np.ndarray,
                  reference_events: np.ndarray | None) -> evidence.Evidence:
    """The batch-means test of all rungs ``rungs`` ({spp: (K, H, W, C)}) pooled,
    each weighted by its samples, against the reference, with the fireflies
    per pixel ``events`` (tails.tail_events of the rungs) and path's
    ``reference_events``; not tested (comparison None) where a render holds
    NaN/Inf."""
    samples = int(sum(spp * x.shape[0] for spp, x in rungs.items()))
    comparison = None
    if all(r.nonfinite_fraction == 0 for r in runs):
        pooled = statistics.Moments.pooled({spp: x[..., :3] for spp, x in rungs.items()})
        comparison = statistics.compare(pooled, reference.moments(), ALPHA)
    return evidence.Evidence(comparison=comparison, events=events, samples=samples,
                             reference_events=reference_events)


def unbiasedness_record(found: evidence.Evidence, top: int) -> Unbiasedness:
    """The numbers of the pooled test at top spp ``top``; its outcome is
    decided by checks/scene.py."""
    c = found.comparison
    if c is None:
        return Unbiasedness(spp=top, passed=False, pass_fraction=0.0, min_p=0.0, alpha=ALPHA,
                            alpha_pixel=0.0, pooled_p=[], summary="not tested: non-finite pixels")
    return Unbiasedness(spp=top, passed=c.passed, pass_fraction=c.pass_fraction, min_p=c.min_p,
                        alpha=ALPHA, alpha_pixel=c.alpha_pixel,
                        pooled_p=[float(p) for p in c.pooled_p], summary=c.summary(),
                        samples_per_pixel=found.samples)


def convergence_fit(runs: list[RunStats], alpha: float = 0.05, look: int = 0) -> Convergence:
    """Slope of log (relMSE − the reference's share) against log spp, with its
    (1 − α) interval and, as ``low_spent``, that interval's lower end at the
    level a fail at look ``look`` reads (sequential.level); its outcome is
    decided by checks/scene.py. An estimator with zero variance at every spp
    is exact. With fewer than 3 usable rungs the interval is unbounded and
    nothing is claimed. Rungs whose relMSE is within metrics.RESOLVED× the
    reference's share are left out."""
    if all(r.variance_per_render <= 1e-12 for r in runs):
        return Convergence(slope=float("nan"), low=float("nan"), high=float("nan"), exact=True,
                           consistent_with_mc=True, passed=True)
    # (a rung whose error is within RESOLVED× the reference's share is mostly
    # that share's one realisation, shared by all its renders: it bends the line)
    ok = [r for r in runs if r.relmse > metrics.RESOLVED * r.reference_relmse]
    if len(ok) < 3:
        return Convergence(slope=float("nan"), low=float("-inf"), high=float("inf"),
                           exact=False, consistent_with_mc=False, passed=False)
    # (each rung's mean relMSE varies as its renders' spread over K; one
    # render a rung gives no spread, and the residuals alone speak)
    var = [float(np.var(r.relmse_per_render, ddof=1)) / len(r.relmse_per_render)
           for r in ok] if all(len(r.relmse_per_render) > 1 for r in ok) else None
    x, y = [r.spp for r in ok], [r.relmse - r.reference_relmse for r in ok]
    slope, _, (lo, hi) = statistics.loglog_fit(x, y, alpha, y_var=var)
    spent = statistics.loglog_fit(x, y, sequential.level(alpha, look), y_var=var)[2][0]
    return Convergence(slope=float(slope), low=float(lo), high=float(hi), exact=False,
                       consistent_with_mc=bool(lo <= convergence.EXPECTED_SLOPE <= hi),
                       passed=bool(hi < 0), low_spent=float(spent),
                       renders=min(len(r.relmse_per_render) for r in runs))


def settle_convergence(ctx) -> None:
    """Each Monte Carlo estimator's convergence fit, continued where more
    renders per rung may decide it (convergence.more_renders_decide): look j
    adds to every rung as many fresh renders as it holds (its own seed
    block's next ones, as if the ladder's K were larger), and the fit is
    read again. A fail at look j reads its interval at sequential.level(α, j)
    (Σ_j α_j = α), so looking again does not inflate the false-fail rate. The
    budget is the scene's sequential one, × the ladder's renders per rung."""
    ref, k = ctx.reference, ctx.plan.renders
    most = int(k * ctx.run.growth(ctx.run.sequential.scene_budget))
    for name, est in ctx.measured.items():
        if evidence.by_design(name):
            continue
        runs, events = est.runs, ctx.evidence[name].events
        c = est.convergence
        c.tail_resolved, c.budget_renders = evidence.tail_resolved(events), most
        # (no early stop on a width the budget seems unable to narrow: on a
        # heavy tail the width read off few renders swings, and such fits
        # were decided: convergence.renders_to_decide)
        while (convergence.convergence_outcome(c, c.tail_resolved, len(runs))[0]
               == "inconclusive" and convergence.more_renders_decide(c)
               and 2 * c.renders <= most):
            look = c.looks + 1
            fresh = more_renders(ctx, name, c.renders, look)
            runs = [pooled(run, fresh[run.spp], ref) for run in runs]
            events = events + tails.tail_events(fresh.values(), ref.mean)[0]
            c = est.convergence = dataclasses.replace(
                convergence_fit(runs, look=look), looks=look, budget_renders=most,
                tail_resolved=evidence.tail_resolved(events))


def more_renders(ctx, name: str, have: int, look: int) -> dict[int, np.ndarray]:
    """{spp: (have, H, W, 3)}: ``have`` more renders of estimator ``name`` on
    every rung, seeds ``have`` … 2·have − 1 of the rung's block (kept)."""
    out = {}
    for rung, spp in enumerate(ctx.plan.ladder):
        seeds_ = ctx.run.stream("ladder", rung).take(2 * have)[have:]
        out[spp] = stacks.kept(ctx, kept_file(ctx, f"spp{spp}-{name}-look{look}"),
                               f"rung {rung} look {look}", {name: ctx.integrators[name]},
                               {name: spp}, have, seeds_, label=ctx.label)[name].images[..., :3]
    return out


def pooled(run: RunStats, fresh: np.ndarray, reference) -> RunStats:
    """``run`` with the relMSE of the ``fresh`` renders (K, H, W, 3) of its
    rung added to its renders' (the rest of its metrics stay the ladder's)."""
    per = run.relmse_per_render + metrics.per_render_relmse(
        fresh.astype(np.float64), reference.mean[..., :3]).tolist()
    return dataclasses.replace(run, relmse_per_render=per, relmse=float(np.mean(per)),
                               renders=len(per))


def settle(ctx) -> None:
    """Each estimator's unbiasedness test continued on fresh batches until it
    decides or its budget is spent (stages/sequential.py): look 0 is the
    ladder, read with path's own rejections as the control; a rejection that
    counts is confirmed on the next batch, beside path's renders of its seeds.
    An estimator biased by design keeps its first look's reading. On a map
    with a sun, a test the sun split will decide stops where its budget
    cannot (sequential.BEYOND_BUDGET)."""
    ref, seq = ctx.reference, ctx.run.sequential
    sun_split.find_sun(ctx)
    for name, found in ctx.evidence.items():
        if found.comparison is None:
            continue
        first = [(spp, ctx.stacks[spp][name].images) for spp in ctx.plan.ladder]
        read = evidence.decider(ref.mean, found.reference_events, found.control,
                                found.is_control)
        # one biased by design has no unbiased check (checks/scene.py): its
        # first look is its record, and no batch is rendered for it
        designed = evidence.by_design(name)
        found.settled, c = sequential.settle(first, ref.moments(), read,
                                             sequential.renderer(ctx, name),
                                             seq.scene_epsilon,
                                             ctx.run.growth(seq.scene_budget),
                                             looks=1 if designed else sequential.LOOKS,
                                             reference_spp=ref.spp,
                                             control=sequential.control_renderer(ctx, name),
                                             confirm=not designed,
                                             split_follows=sun_split.split_follows(ctx, name))
        found.settled.summary = c.summary()


# ---------------------------------- Images --------------------------------------

def save_images(ctx) -> None:
    """images/<scene>/: the reference and its variance; per estimator one
    render and the K-render mean at the top spp, the mean with the pooled
    test's smallest p per pixel over channels (layer ``p``; NaN: not tested)
    and its Šidák level (``alpha_pixel``), which the report's viewer shows."""
    d, ref = ctx.images_dir, ctx.reference
    files.write_exr(f"{d}/reference.exr", ref.mean.astype(np.float32),
                    {"spp": ref.spp, "passes": ref.passes})
    files.write_exr(f"{d}/reference_variance.exr", ref.variance_of_mean.astype(np.float32),
                    {"passes": ref.passes})
    rung = len(ctx.plan.ladder) - 1
    top = ctx.plan.ladder[rung]
    for name in ctx.measured:
        images = ctx.stacks[top][name].images
        files.write_exr(f"{d}/{name}_spp{top}.exr", images[0],
                        {"integrator": name, "spp": top,
                         "seed": ctx.run.stream("ladder", rung).seed(0)})
        found = ctx.evidence.get(name)
        test = None if found is None else found.comparison
        files.write_exr(f"{d}/{name}_spp{top}_mean.exr", images.mean(axis=0),
                        {"integrator": name, "spp": top, "renders": len(images)}
                        | ({} if test is None else {"alpha_pixel": float(test.alpha_pixel)}),
                        None if test is None else
                        {"p": np.asarray(test.pixel_p, np.float32)[..., None]})


def scene_result(ctx) -> SceneResult:
    """The scene comparison's record."""
    return SceneResult(
        name=ctx.id, path=os.path.relpath(ctx.info.path, os.getcwd()),
        summary=scene_summary(ctx), res=ctx.res, max_depth=ctx.max_depth,
        ladder=list(ctx.plan.ladder), renders=ctx.plan.renders,
        reference=reference_summary(ctx.reference), estimators=list(ctx.measured.values()),
        speed=ctx.speed, budget_axis=ctx.budget_axis, quadrature=list(ctx.quadrature.values()) or None,
        learning=list(ctx.learning.values()) or None,
        notes=list(ctx.scene_notes) or None)
