"""The stages of a failure case and of a point of a parameter sweep.

A case renders K seeds per estimator at one spp (after asking each whether it
refuses the scene), builds `path`'s reference, and measures how each
estimator's error spreads over the seeds (stats/tails.py) and its
batch-means test, continued where the rules of evidence cannot decide yet
(stages/sun_split.py: ``settled_test``). On a map with a sun, what the real
sun leaves undecided is decided on the map without it and with it widened:
the sun split (stages/sun_split.py). A parameter sweep runs a case's
renders at every value and reports its rows along the parameter. The
verdicts are checks/cases.py's.
"""

from __future__ import annotations

import numpy as np

from mcillum import files
from mcillum.integrators import UnreachableContentError
from mcillum.integrators.core import registry

from ..results import CaseReference, CaseResult, CaseRow, Sweep, SweepRow, TailNumbers
from ..run import jobs, renders, stacks
from ..stats import metrics, statistics, tails
from . import common, sun_split
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
        # (kept without its traceback: its frames hold this context and its
        # scene, which then lived, in a cycle, until Python's collector came)
        return err.with_traceback(None)
    return None


def _refusal_message(error: UnreachableContentError) -> str:
    return (f"integrator '{error.integrator}' cannot render this scene without bias: "
            + "; ".join(str(p) for p in error.problems))


# ----------------------------------- Renders ------------------------------------

def render_seeds(ctx) -> None:
    """K renders per estimator at the context's one spp (common.first_look;
    its seed stream; kept).
    A sweep's are timed (run/executors.py): its chart puts their seconds
    beside the error."""
    spp, k = common.first_look(ctx)
    name = ctx.streams["renders"]
    ctx.stacks = {spp: stacks.kept(ctx, kept_file(ctx, name), name, ctx.integrators,
                                   dict.fromkeys(ctx.integrators, spp), k,
                                   ctx.run.stream(name).take(k), compile_kernels, ctx.label,
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
    if ctx.plan.group == "heavy_tail":
        # (before the tests: a test the split follows stops on the real sun;
        # a map without one is not split, and no unseen sun excuses a deficit)
        sun_split.find_sun(ctx)
    for name, row in ctx.rows.items():
        n = row.numbers
        if n is None or row.refused or n.nonfinite_values or n.negative_values:
            continue
        n.test = sun_split.settled_test(ctx, name, found[name].images)


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
