"""The stages of a validation run: each is ``stage(context) -> None`` (the sweep's
last two also take its points).

A stage reads what earlier stages put on the :class:`~.context.Context` and
adds what it finds. :mod:`~mcillum.validation.pipeline` lists which stages a
scene comparison, a failure case and a point of a parameter sweep run, in
order. The stages gather evidence (renders, reference, numbers, tests); the
verdicts are the checks' (:mod:`~mcillum.validation.checks`).
"""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from mcillum import files
from mcillum.envmaps import sun
from mcillum.errors import root_cause
from mcillum.integrators import UnreachableContentError, registry

from . import analysis, checks, jobs, references, renders, scenes, seeds, statistics, sweeps, tails
from .results import (BatchTest, CaseReference, CaseResult, CaseRow, EstimatorResult,
                      ReferenceSummary, SceneResult, SunSplit, Sweep, SweepRow, TailNumbers)

REFERENCE = registry.REFERENCE
ALPHA = statistics.ALPHA


# ----------------------------- Scene and estimators ----------------------------

def load(ctx) -> None:
    """The scene with the plan's resolution and $-parameters; its cache key."""
    index = scenes.index()
    if ctx.scene_name not in index:
        raise ValueError(f"{ctx.id}: no scene '{ctx.scene_name}' in {scenes.SCENES_DIR}")
    ctx.info = index[ctx.scene_name]
    ctx.resolved = renders.resolve_defines(ctx.info.path, **{"res": ctx.res, **ctx.defines})
    ctx.scene = renders.load_resolved(ctx.info.path, ctx.resolved)
    ctx.params = {"max_depth": ctx.max_depth}
    ctx.scene_key = references.cache_key(ctx.info.path, ctx.resolved, ctx.params,
                                         ctx.run.variant)
    ctx.scene_spec = jobs.SceneSpec(os.path.abspath(ctx.info.path),
                                    tuple(sorted(ctx.resolved.items())), ctx.scene_key)


def choose_estimators(ctx) -> None:
    """The estimators asked for whose registry facts say they reach every
    kind of content the scene header declares (at the plan's max_depth)."""
    ctx.integrators = {n: jobs.make(n, ctx.params) for n in ctx.estimators
                       if registry.facts(n).renders(ctx.info.contains, ctx.max_depth)}


def probe_refusals(ctx) -> None:
    """Ask each estimator whether it refuses the scene.
    In the ``unreachable`` group a refusing estimator then renders with
    ``allow_unreachable=true``, so that the bias the user opts into is measured."""
    for name in ctx.estimators:
        error = None if name == REFERENCE else _refusal(ctx, name)
        if error is None:
            ctx.integrators[name] = jobs.make(name, ctx.params)
            continue
        ctx.refused[name] = error
        if ctx.plan.group == "unreachable":
            ctx.integrators[name] = jobs.make(name, {**ctx.params, "allow_unreachable": True})


def _refusal(ctx, name: str) -> UnreachableContentError | None:
    """The estimator's own scene check, as its render would run it first
    (nothing is rendered)."""
    integrator = renders.make_integrator(name, ctx.params)
    if not registry.is_estimator(integrator):
        return None
    try:
        integrator.check_scene(ctx.scene)
    except UnreachableContentError as err:
        return err
    return None


# ----------------------------------- Renders ------------------------------------

def _compile(ctx) -> None:
    """Each integrator's first render (its kernel compiles or loads from
    Dr.Jit's cache), timed apart; once per context, and only when something
    is rendered."""
    if ctx.compile_seconds:
        return
    seed = seeds.stream("compile").seed()
    batch = [ctx.job(integ, 1, seed) for integ in ctx.integrators.values()]
    ctx.compile_seconds = {n: out.seconds for n, out in
                           zip(ctx.integrators, ctx.render(batch, None, timed=True))}


def _file(ctx, what: str) -> str:
    """A file name for ``what`` that differs between contexts sharing an id
    (the points of a sweep, a case's sunless twin)."""
    tag = json.dumps(ctx.defines, sort_keys=True, default=str)
    return f"{what}-{hashlib.sha256(tag.encode()).hexdigest()[:8]}"


def render_ladder(ctx) -> None:
    """K renders per estimator on every rung of the plan's spp ladder
    (kept: sweeps.py)."""
    ctx.units = sweeps.run(ctx, _compile)


def render_seeds(ctx) -> None:
    """K renders per estimator at the plan's spp (the case's seed stream; kept).
    A sweep's are timed (executors.py): its chart puts their seconds beside
    the error."""
    spp, k = ctx.plan.spp, ctx.plan.seeds
    name = ctx.streams["renders"]
    ctx.units = {spp: sweeps.kept(ctx, _file(ctx, name), name, ctx.integrators,
                                  dict.fromkeys(ctx.integrators, spp), k,
                                  seeds.stream(name).take(k), _compile, ctx.label,
                                  timed=bool(getattr(ctx.plan, "sweep", ())))}


def _fresh(ctx, name: str, spp: int | None = None, k: int | None = None) -> np.ndarray:
    """K new renders of one estimator at the case's spp (or ``spp``, ``k``:
    a scene's top rung), from the context's replication stream; kept."""
    spp, k = spp or ctx.plan.spp, k or ctx.plan.seeds
    stream = ctx.streams["replication"]
    return sweeps.kept(ctx, _file(ctx, f"{stream}-{name}"), stream,
                       {name: ctx.integrators[name]}, {name: spp}, k,
                       seeds.stream(stream).take(k), label=ctx.label)[name].images


# ---------------------------------- Reference -----------------------------------

def build_reference(ctx) -> None:
    """`path` until its standard error is a fraction of the smallest error it is
    compared against: the least noisy render stack of a scene comparison, or
    `path`'s own in a failure case (where the other stacks' tails would set no
    useful target)."""
    stacks = [u.images for by_name in ctx.units.values() for n, u in by_name.items()
              if not ctx.is_case or n == REFERENCE]
    target = references.target_for(stacks, ctx.run.profile.reference_fraction)
    ctx.reference = references.ensure(ctx, target)


# ------------------------------ Scene statistics --------------------------------

def measure(ctx) -> None:
    """Per estimator: metrics per rung, the pooled unbiasedness test,
    convergence (:mod:`analysis`), each read by the rules of checks.py
    (fireflies in an estimator's renders, or in path's for the reference); a
    rejection that counts is tested again on K fresh renders at the top rung."""
    ladder, ref = ctx.plan.ladder, ctx.reference
    stacks = {name: {spp: ctx.units[spp][name].images for spp in ladder}
              for name in ctx.integrators}
    tail = {name: tails.tail_events(s.values(), ref.mean, s.keys())
            for name, s in stacks.items()}
    path_events = tail[REFERENCE][0] if REFERENCE in tail else None   # the reference's tail
    for name in ctx.integrators:
        runs = [analysis.run_stats(ctx.units[spp][name], ref) for spp in ladder]
        ctx.measured[name] = EstimatorResult(
            name, ctx.params, ctx.compile_seconds.get(name, float("nan")), runs,
            analysis.unbiasedness(stacks[name], ref, runs, ALPHA, tail[name], path_events,
                                  lambda name=name: _fresh(ctx, name, ladder[-1],
                                                           ctx.plan.renders)),
            analysis.convergence(runs, heavy=bool(tail[name][0].any())))


def judge_scene(ctx) -> None:
    ctx.checks = checks.run(checks.SCENE, ctx, ctx.units, ctx.reference, by_estimator=True)


def save_images(ctx) -> None:
    """images/<scene>/: the reference and its variance; per estimator one
    render and the K-render mean at the top spp."""
    d, ref = ctx.images_dir, ctx.reference
    files.write_exr(f"{d}/reference.exr", ref.mean.astype(np.float32),
                    {"spp": ref.spp, "passes": ref.passes})
    files.write_exr(f"{d}/reference_variance.exr", ref.variance_of_mean.astype(np.float32),
                    {"passes": ref.passes})
    rung = len(ctx.plan.ladder) - 1
    top = ctx.plan.ladder[rung]
    for name in ctx.measured:
        images = ctx.units[top][name].images
        files.write_exr(f"{d}/{name}_spp{top}.exr", images[0],
                        {"integrator": name, "spp": top,
                         "seed": seeds.stream("ladder", rung).seed(0)})
        files.write_exr(f"{d}/{name}_spp{top}_mean.exr", images.mean(axis=0),
                        {"integrator": name, "spp": top, "renders": len(images)})


def release(ctx) -> None:
    """Drop the loaded scene when nothing more is rendered from it: every
    live scene's shapes, BSDFs and emitters stay in Dr.Jit's instance
    registry, which every virtual call of a kernel dispatches over, and slow
    every later render in this process (measured: 1.3× with two alive), and
    so the timings of the speed stage and of a sweep's points."""
    ctx.scene = None


def scene_result(ctx) -> SceneResult:
    info = ctx.info
    return SceneResult(
        ctx.id, os.path.relpath(info.path, os.getcwd()), describe(ctx), ctx.res, ctx.max_depth,
        list(ctx.plan.ladder), ctx.plan.renders, reference_summary(ctx.reference),
        list(ctx.measured.values()), ctx.speed, list(ctx.quadrature.values()) or None)


def reference_summary(ref) -> ReferenceSummary:
    """What the results record of a reference (references.Reference)."""
    return ReferenceSummary(REFERENCE, ref.spp, ref.passes, ref.spp_per_pass, ref.seconds,
                            ref.cached_passes, ref.meta.get("rendered_passes", 0),
                            ref.meta.get("target_variance", 0.0),
                            float(ref.variance_of_mean.mean()), ref.capped, ref.key)


def describe(ctx) -> str:
    """The scene header's summary with the $-parameters it was rendered with
    (a map by the name it was given, not the checked file it became)."""
    return scenes.expand(ctx.info.path, ctx.info.summary, ctx.defines)


# ------------------------------- Failure cases ----------------------------------

def tail_numbers(ctx) -> None:
    """Per estimator: per-render relMSE percentiles, fireflies, NaN/Inf and
    negative values, spp to match `path` (:mod:`tails`)."""
    spp, k = ctx.plan.spp, ctx.plan.seeds
    units, r = ctx.units[spp], ctx.reference.mean[..., :3]
    path_rel = tails.per_render_relmse(units[REFERENCE].images, r)
    for name in ctx.estimators:
        row = CaseRow(name, refused=name in ctx.refused)
        if name in ctx.refused:
            row.message = _refusal_message(ctx.refused[name])
        ctx.rows[name] = row
        if name not in units:
            continue
        x = units[name].images[..., :3].astype(np.float64)
        per = ctx.per_render[name] = tails.per_render_relmse(x, r)
        bad = tails.bad_values(x)
        ratio = float(x.mean() / r.mean()) if r.mean() > 0 else None
        row.numbers = TailNumbers(
            tails.percentiles(per), tails.firefly_fraction(x, r), k * spp, k,
            float(np.median(units[name].seconds)), ratio,
            None if row.refused else tails.spp_to_match(per, path_rel, spp),
            nonfinite_values=bad[0], negative_values=bad[1], tail_ratio=tails.tail_ratio(per))
        if row.refused and ratio is not None:   # the user's choice: what is missing
            row.numbers.missing_fraction = 1.0 - ratio


def _refusal_message(error: UnreachableContentError) -> str:
    return (f"integrator '{error.integrator}' cannot render this scene without bias: "
            + "; ".join(str(p) for p in error.problems))


def test_bias(ctx) -> None:
    """The batch-means test of each estimator's K renders against the
    reference, read by the rules of checks.py; a rejection that counts is
    tested again on K fresh renders."""
    units = ctx.units[ctx.plan.spp]
    decide = _decider(ctx)
    for name, row in ctx.rows.items():
        n = row.numbers
        if n is None or row.refused or n.nonfinite_values or n.negative_values:
            continue
        n.test = _replicated_test(ctx, name, units[name].images, decide)


def _decider(ctx):
    """The rules of checks.py for this case's renders, with path's fireflies
    (counted once per case) as the reference's tail."""
    units = ctx.units[ctx.plan.spp]
    path_events = (tails.tail_events([units[REFERENCE].images], ctx.reference.mean)[0]
                   if REFERENCE in units else None)
    return analysis.decider(ctx.reference.mean, ctx.plan.spp, path_events)


def _replicated_test(ctx, name: str, x: np.ndarray, decide) -> BatchTest:
    return statistics.replicated_compare(
        x[..., :3], ctx.reference.moments(), lambda: _fresh(ctx, name)[..., :3], ALPHA,
        decide)


def split_sun(ctx) -> None:
    """Heavy-tail cases on a map with a sun: estimators whose test was
    inconclusive (a rejection a tail can explain) or biased are tested again
    on the map without its sun (rendering is linear in the map,
    envmaps/sun.py), by the same rules: a bias there is a bias, whatever the
    sun does. With the sun's facts and the number of direct hits each
    estimator expects, N·Ω·max p."""
    tested = [n for n, row in ctx.rows.items() if row.numbers and row.numbers.test
              and row.numbers.test.outcome != "pass"]
    if not tested or ctx.plan.group != "heavy_tail" or "envmap" not in ctx.resolved:
        return
    sunless_path, facts = sun.without_sun(ctx.resolved["envmap"])
    sub = ctx.derive([*tested, REFERENCE], label=f"{ctx.id} sunless",
                     streams={"renders": "sunless", "replication": "sunless_replication"},
                     envmap=sunless_path)
    for stage in (load, choose_estimators, render_seeds, build_reference):
        stage(sub)
    samples = ctx.plan.seeds * ctx.plan.spp
    sunless_mean = float(sub.reference.mean[..., :3].mean())
    image_mean = float(ctx.reference.mean[..., :3].mean())
    decide = _decider(sub)
    for name in tested:
        test = _replicated_test(sub, name, sub.units[ctx.plan.spp][name].images, decide)
        ctx.rows[name].numbers.sun = SunSplit(
            facts, not (test.outcome == "fail" and test.replicated), test.test,
            sunless_mean, expected_sun_hits(
                name, samples * getattr(ctx.integrators[name].made, "directions", 1),
                facts["solid_angle"]),
            1.0 - sunless_mean / image_mean, test.outcome, test.reason)


def expected_sun_hits(name: str, samples: int, solid_angle: float) -> float | None:
    """Direct hits on a sun of ``solid_angle`` that estimator ``name`` expects
    in ``samples`` directions traced from a pixel (camera samples × the
    directions per sample of a point-set estimator), at most N·Ω·max p
    (None: unbounded, its registry facts give no largest pdf)."""
    pdf = registry.facts(name).max_direction_pdf
    return None if pdf is None else samples * solid_angle * pdf


def judge_case(ctx) -> None:
    pixels = int(np.prod(ctx.reference.mean.shape[:2]))
    for row in ctx.rows.values():
        row.verdict = checks.case_verdict(row, pixels)
    ctx.checks = checks.run(checks.CASE, ctx, ctx.units, ctx.reference)


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
    for name, unit in ctx.units[ctx.plan.spp].items():
        ctx.rows[name].images = _evidence(ctx, name, unit.images, ctx.per_render[name])


def case_result(ctx) -> CaseResult:
    """A failure case's result: its rows and reference, or for a sweep its
    rows along the parameter (each point had its own reference)."""
    p = ctx.plan
    swept = bool(p.sweep)
    return CaseResult(
        p.id, p.group, p.label or p.scene, p.scene, dict(p.defines), p.res, p.spp, p.seeds,
        p.max_depth, describe(ctx), ctx.sweep_rows if swept else list(ctx.rows.values()),
        reference=None if swept else CaseReference(ctx.reference.spp, ctx.reference.capped),
        sweep=Sweep(p.sweep[0], list(p.sweep[1])) if swept else None)


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
            name, rel, secs, rel[-1] / rel[0] if rel[0] > 0 else None, bad,
            points[-1].rows[name].images, "fine" if bad == 0 else "non-finite/negative"))


def judge_sweep(ctx) -> None:
    ctx.checks = checks.run(checks.SWEEP, ctx, None, None)
