"""The stages of a failure case and of a point of a parameter sweep.

A case renders K seeds per estimator at one spp (after asking each whether it
refuses the scene), builds `path`'s reference, and measures how each
estimator's error spreads over the seeds (stats/tails.py) and its
batch-means test, replicated where the rules of evidence count a rejection.
On a map with a sun, the estimators whose test did not pass are tested again
on the map without its sun: the **sunless twin**, a context of its own that
the pipeline runs through :data:`~mcillum.validation.pipeline.SUNLESS`
(rendering is linear in the map, envmaps/sun.py). Those the real sun left
inconclusive and that passed without it are tested once more on the map
with its sun **widened** to a disc the samples hit (envmaps/sun.py:
``widen``), the **widened twin**, run the same way. A parameter sweep runs a
case's renders at every value and reports its rows along the parameter.
The verdicts are checks/cases.py's.
"""

from __future__ import annotations

import numpy as np

from mcillum import files
from mcillum.envmaps import sun
from mcillum.integrators import UnreachableContentError, registry

from ..checks import evidence
from ..plan import seeds
from ..results import (BatchTest, CaseReference, CaseResult, CaseRow, SunSplit, Sweep,
                       SweepRow, TailNumbers)
from ..run import jobs, references, renders, stacks
from ..stats import metrics, statistics, tails
from . import common, sequential
from .common import REFERENCE, compile_kernels, kept_file, scene_summary

ALPHA = statistics.ALPHA


# ---------------------------------- Refusals ------------------------------------

def probe_refusals(ctx) -> None:
    """Ask each estimator whether it refuses the scene.
    In the ``unreachable`` group a refusing estimator then renders with
    ``allow_unreachable=true``, so that the bias the user opts into is measured."""
    for name in ctx.estimators:
        error = None if name == REFERENCE else _refusal(ctx, name)
        if error is None:       # (a user's direct-light integrator may take no max_depth)
            ctx.integrators[name] = jobs.make_taking(name, ctx.params)
            continue
        ctx.refused[name] = error
        if ctx.plan.group == "unreachable":
            ctx.integrators[name] = jobs.make(name, {**ctx.params, "allow_unreachable": True})


def _refusal(ctx, name: str) -> UnreachableContentError | None:
    """The estimator's own scene check, as its render would run it first
    (nothing is rendered)."""
    integrator, _ = renders.make_taking(name, ctx.params)
    if not registry.is_estimator(integrator):
        return None
    try:
        integrator.check_scene(ctx.scene)
    except UnreachableContentError as err:
        return err
    return None


def _refusal_message(error: UnreachableContentError) -> str:
    return (f"integrator '{error.integrator}' cannot render this scene without bias: "
            + "; ".join(str(p) for p in error.problems))


# ----------------------------------- Renders ------------------------------------

def render_seeds(ctx) -> None:
    """K renders per estimator at the plan's spp (the case's seed stream; kept).
    A sweep's are timed (run/executors.py): its chart puts their seconds
    beside the error."""
    spp, k = ctx.plan.spp, ctx.plan.seeds
    name = ctx.streams["renders"]
    ctx.stacks = {spp: stacks.kept(ctx, kept_file(ctx, name), name, ctx.integrators,
                                   dict.fromkeys(ctx.integrators, spp), k,
                                   seeds.stream(name).take(k), compile_kernels, ctx.label,
                                   timed=bool(getattr(ctx.plan, "sweep", ())))}


# ------------------------------- Tail numbers -----------------------------------

def tail_numbers(ctx) -> None:
    """Per estimator: per-render relMSE percentiles, fireflies, NaN/Inf and
    negative values, spp to match `path` (:mod:`tails`)."""
    spp, k = ctx.plan.spp, ctx.plan.seeds
    found, r = ctx.stacks[spp], ctx.reference.mean[..., :3]
    path_rel = metrics.per_render_relmse(found[REFERENCE].images, r)
    for name in ctx.estimators:
        row = CaseRow(name=name, refused=name in ctx.refused)
        if name in ctx.refused:
            row.message = _refusal_message(ctx.refused[name])
        ctx.rows[name] = row
        if name not in found:
            continue
        x = found[name].images[..., :3].astype(np.float64)
        per = ctx.per_render[name] = metrics.per_render_relmse(x, r)
        bad = tails.bad_values(x)
        ratio = float(x.mean() / r.mean()) if r.mean() > 0 else None
        row.numbers = TailNumbers(
            relmse=tails.percentiles(per), firefly_fraction=tails.firefly_fraction(x, r),
            samples_per_pixel=k * spp, seeds=k,
            seconds_median=float(np.median(found[name].seconds)), image_mean_ratio=ratio,
            spp_to_match_path=None if row.refused else tails.spp_to_match(per, path_rel, spp),
            nonfinite_values=bad[0], negative_values=bad[1], tail_ratio=tails.tail_ratio(per))
        if row.refused and ratio is not None:   # the user's choice: what is missing
            row.numbers.missing_fraction = 1.0 - ratio


# --------------------------------- Bias test ------------------------------------

def test_bias(ctx) -> None:
    """The batch-means test of each estimator's K renders against the
    reference, read by the rules of evidence and continued on fresh batches
    until it decides or its budget is spent (stages/sequential.py)."""
    found = ctx.stacks[ctx.plan.spp]
    if ctx.plan.group == "heavy_tail" and "envmap" in ctx.resolved and ctx.sun is None:
        ctx.sunless_map, ctx.sun = sun.without_sun(ctx.resolved["envmap"])
    for name, row in ctx.rows.items():
        n = row.numbers
        if n is None or row.refused or n.nonfinite_values or n.negative_values:
            continue
        n.test = settled_test(ctx, name, found[name].images)


def _reader(ctx, name: str):
    """``read(comparison, batches, look)``: the rules of evidence for this
    case's renders of ``name``, with path's fireflies (counted once per
    case) as the reference's tail. On a map with a sun, the sun is a tail
    the renders may not have seen yet, whatever else they caught: while
    the estimator's largest pdf expects fewer than SUN_HITS direct hits per
    pixel in the samples so far (N·Ω·max p; or it declares no largest pdf),
    no downward rejection counts (evidence.unseen_sun) and the test renders
    on. On the widened sun's map (``ctx.disc``) no downward pixel rejection
    counts (evidence.partly_hidden)."""
    found = ctx.stacks[ctx.plan.spp]
    path_events = (tails.tail_events([found[REFERENCE].images], ctx.reference.mean)[0]
                   if REFERENCE in found else None)
    decide = evidence.decider(ctx.reference.mean, path_events)
    directions = _directions(ctx, name)
    samples_emitters = _samples_emitters(name)

    def read(comparison, batches, look):
        d = decide(comparison, batches, look)
        if ctx.disc:
            return evidence.partly_hidden(d, comparison)
        if ctx.sun is None or samples_emitters:
            return d
        hits = expected_sun_hits(name, sequential.samples(batches) * directions,
                                 ctx.sun["solid_angle"])
        if hits is None or hits < evidence.SUN_HITS:
            evidence.unseen_sun(d, comparison, hits)
        return d
    return read


def settled_test(ctx, name: str, x: np.ndarray) -> BatchTest:
    """The sequential test (stages/sequential.py) of estimator ``name``'s
    renders ``x`` at the case's spp, as a :class:`BatchTest`."""
    seq = ctx.run.sequential
    settled, c = sequential.settle([(ctx.plan.spp, x)], ctx.reference.moments(),
                                   _reader(ctx, name), sequential.renderer(ctx, name),
                                   seq.case_epsilon, _growth(ctx),
                                   reference_spp=ctx.reference.spp)
    d = settled.decision
    return BatchTest(passed=c.passed, pass_fraction=c.pass_fraction, min_p=c.min_p,
                     pooled_p=[float(p) for p in c.pooled_p], alpha_pixel=c.alpha_pixel,
                     test=c.summary(), outcome=d.outcome, reason=d.reason,
                     tail_events=d.tail_events, samples_needed=d.samples_needed,
                     counted_up=d.counted_up, rejected_pixels=d.rejected_up + d.rejected_down,
                     replicated=settled.replicated,
                     replication_test=settled.replication or None, looks=settled.looks,
                     samples_per_pixel=settled.samples, relative_bias=d.relative_bias,
                     half_width=d.half_width)


# ------------------------------ The sunless twin --------------------------------

def sunless_twin(ctx) -> None:
    """``ctx.sunless``: the case on its map without the sun, for the
    estimators whose test did not pass (inconclusive: a rejection a tail can
    explain; or biased), with `path`, on seed streams of its own; None
    unless this is a heavy-tail case on a map."""
    tested = [n for n, row in ctx.rows.items() if row.numbers and row.numbers.test
              and row.numbers.test.outcome != "pass"]
    if not tested or ctx.plan.group != "heavy_tail" or "envmap" not in ctx.resolved:
        return
    ctx.sunless = ctx.derive([*tested, REFERENCE], label=f"{ctx.id} sunless",
                             streams={"renders": "sunless", "sequential": "sunless_sequential"},
                             envmap=ctx.sunless_map)


def split_sun(ctx) -> None:
    """Each estimator of the sunless twin tested there by the same rules (a
    bias there is a bias, whatever the sun does), with the sun's facts and
    the number of direct hits it expects in the samples its test reached,
    N·Ω·max p."""
    sub = ctx.sunless
    if sub is None:
        return
    sunless_mean = float(sub.reference.mean[..., :3].mean())
    image_mean = float(ctx.reference.mean[..., :3].mean())
    for name in sub.estimators[:-1]:        # those tested (the last is path, the reference)
        test = settled_test(sub, name, sub.stacks[ctx.plan.spp][name].images)
        samples = ctx.rows[name].numbers.test.samples_per_pixel
        ctx.rows[name].numbers.sun = SunSplit(
            sun=ctx.sun, sunless_passed=test.outcome != "fail",
            sunless_test=test.test, sunless_reference_mean=sunless_mean,
            expected_sun_hits_per_pixel=expected_sun_hits(
                name, samples * _directions(ctx, name), ctx.sun["solid_angle"]),
            sun_share_of_image=1.0 - sunless_mean / image_mean, sunless_outcome=test.outcome,
            sunless_reason=test.reason)


# ----------------------------- The widened sun ---------------------------------

def widened_twin(ctx) -> None:
    """``ctx.widened``: the case on its map with the sun widened
    (envmaps/sun.py, :func:`~mcillum.envmaps.sun.widen`), for the estimators
    whose test on the real map the budget left inconclusive, that passed
    without the sun, and that do not sample the emitters (an estimator that
    does finds the sun by construction); with `path`, on seed streams of its
    own; None unless there are such estimators."""
    tested = [n for n, row in ctx.rows.items()
              if row.numbers and row.numbers.test and row.numbers.test.outcome == "inconclusive"
              and row.numbers.sun is not None and row.numbers.sun.sunless_outcome == "pass"
              and not _samples_emitters(n)]
    if not tested or not ctx.sun or not ctx.sun["texels"]:     # (no sun to widen)
        return
    widened_map, facts = sun.widened(ctx.resolved["envmap"])
    ctx.widened = ctx.derive([*tested, REFERENCE], label=f"{ctx.id} widened sun",
                             streams={"renders": "widened",
                                      "sequential": "widened_sequential"},
                             envmap=widened_map)
    ctx.widened.disc = True
    for name in tested:
        ctx.rows[name].numbers.sun.widened = facts


def widened_reference(ctx) -> None:
    """`path`'s reference of the widened twin (common.build_reference), then
    rendered on until its spp no longer caps the test's budget
    (sequential.REFERENCE_LEAD): the disc is hit often enough for the budget
    to decide, and a reference of the usual precision stopped sun_sky's at
    half of it (image mean ±4.5 % at 131 072 samples per pixel)."""
    common.build_reference(ctx)
    ref = ctx.reference
    needed = sequential.budget(ctx.plan.spp * ctx.plan.seeds, _growth(ctx)) \
        / sequential.REFERENCE_LEAD
    if ref.spp < needed:
        variance = float(ref.variance_of_mean.mean())     # (as references.ensure reads it)
        ctx.reference = references.ensure(ctx, variance * ref.spp / needed)


def split_widened(ctx) -> None:
    """Each estimator of the widened twin tested there by the same rules of
    evidence, but for the pixels that see the disc only through a sliver
    (evidence.partly_hidden): the disc is hit often over the image, so its
    image mean decides."""
    sub = ctx.widened
    if sub is None:
        return
    for name in sub.estimators[:-1]:        # those tested (the last is path, the reference)
        test = settled_test(sub, name, sub.stacks[ctx.plan.spp][name].images)
        split = ctx.rows[name].numbers.sun
        split.widened_outcome, split.widened_reason = test.outcome, test.reason
        split.widened_test = test.test


def _growth(ctx) -> float:
    """A case's test budget as a multiple of its first look's samples."""
    return ctx.run.growth(ctx.run.sequential.case_budget)


def _samples_emitters(name: str) -> bool:
    """Does estimator ``name`` sample the emitters (it reaches point lights)?
    Then it finds the sun by construction: it has no unseen sun to plead,
    and no widened sun is needed to decide it."""
    return "delta_emitter" in registry.facts(name).reachable


def _directions(ctx, name: str) -> int:
    """Directions per camera sample of estimator ``name`` (N for a point set)."""
    return getattr(ctx.integrators[name].made, "directions", 1)


def expected_sun_hits(name: str, samples: int, solid_angle: float) -> float | None:
    """Direct hits on a sun of ``solid_angle`` that estimator ``name`` expects
    in ``samples`` directions traced from a pixel (camera samples × the
    directions per sample of a point-set estimator), at most N·Ω·max p
    (None: unbounded, its registry facts give no largest pdf)."""
    pdf = registry.facts(name).max_direction_pdf
    return None if pdf is None else samples * solid_angle * pdf


# ---------------------------------- Evidence ------------------------------------

def _evidence(ctx, name: str, images: np.ndarray, per: np.ndarray) -> dict:
    """The median-error and worst-error renders of one estimator, as EXR."""
    order = np.argsort(per)
    out = {}
    for label, k in (("median", order[len(order) // 2]), ("worst", order[-1])):
        out[label] = f"{name}_{label}.exr"
        files.write_exr(f"{ctx.images_dir}/{out[label]}", images[k][..., :3],
                        {"integrator": name, "seed_index": int(k), "relmse": float(per[k])})
    return out


def save_evidence(ctx) -> None:
    """failures/<case>/: the reference, and each rendering estimator's
    median- and worst-error seed (by the per-render relMSE of tail_numbers)."""
    r = ctx.reference.mean[..., :3]
    meta = {"spp": ctx.reference.spp}
    if ctx.plan.sweep:                      # a point of a sweep: at which value
        param = ctx.plan.sweep[0]
        meta[param] = ctx.defines[param]
    files.write_exr(f"{ctx.images_dir}/reference.exr", r.astype(np.float32), meta)
    for name, stack in ctx.stacks[ctx.plan.spp].items():
        ctx.rows[name].images = _evidence(ctx, name, stack.images, ctx.per_render[name])


def case_result(ctx) -> CaseResult:
    """A failure case's record: its rows and reference, or for a sweep its
    rows along the parameter (each point had its own reference)."""
    p = ctx.plan
    swept = bool(p.sweep)
    return CaseResult(
        id=p.id, group=p.group, label=p.label or p.scene, scene=p.scene,
        defines=dict(p.defines), res=p.res, spp=p.spp, seeds=p.seeds, max_depth=p.max_depth,
        summary=scene_summary(ctx),
        estimators=ctx.sweep_rows if swept else list(ctx.rows.values()),
        reference=None if swept else CaseReference(spp=ctx.reference.spp,
                                                   capped=ctx.reference.capped),
        sweep=sweep_record(p) if swept else None)


def sweep_record(plan) -> Sweep:
    """The record of a plan's parameter sweep."""
    return Sweep(param=plan.sweep[0], values=list(plan.sweep[1]))


# ------------------------------- Parameter sweeps -------------------------------

def sweep_rows(ctx, points: list) -> None:
    """Per estimator, relMSE (mean over seeds) and median seconds at every
    point of the sweep; evidence images at the last (narrowest) point."""
    save_evidence(points[-1])
    ctx.info = points[-1].info
    for name in points[-1].integrators:
        rel = [p.rows[name].numbers.relmse.mean for p in points]
        secs = [p.rows[name].numbers.seconds_median for p in points]
        bad = sum(p.rows[name].numbers.nonfinite_values + p.rows[name].numbers.negative_values
                  for p in points)
        ctx.sweep_rows.append(SweepRow(
            name=name, relmse=rel, seconds=secs,
            growth=rel[-1] / rel[0] if rel[0] > 0 else None, nonfinite_values=bad,
            images=points[-1].rows[name].images,
            verdict="fine" if bad == 0 else "non-finite/negative"))
