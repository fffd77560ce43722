"""The quadrature stage: what an estimator of N directions per shading point
(fibonacci_hemisphere, bayesian_hemisphere, bayesian_importance; registry
facts ``depths``) is measured on beyond the spp ladder, at the ladder's top
rung and resolution.

* **Equal rays.** The K renders of N directions × spp camera samples at the
  ladder's top rung against its baseline (facts ``equal_rays_baseline``:
  cosine_hemisphere, or emitter_sampling for one that samples the light) at
  N·spp spp: the ratio of their relMSE (each less the reference's own
  relative variance), with a 95 % interval from the spread of the per-render
  errors and the standard error of the reference's share (delta method on
  the log). The baseline's error at N·spp is its
  ladder renders' at spp over N where the scene's sampler is independent
  (the N·spp samples of a pixel are then N independent means of spp: the
  variance of their mean is 1/N of one's, exactly), measured where the
  reference's noise is smallest against it; with another sampler, or a
  baseline not on the ladder, K renders at N·spp. The seconds beside the
  ratio are medians of TIMED renders of each, interleaved and timed alone.
* **Bias against N** (estimators biased by design, facts ``unbiased``
  False): at N = 16, the default and 256, the bias per pixel b = m − r of
  the mean m of K renders (the default N's from the ladder, the others'
  :data:`BIAS_RENDERS`) (of the channel mean: the channels share their
  directions), summarised as the noise-corrected rms over pixels
  √(mean(b² − v/K − v_ref)) relative to the rms of the reference, ± its
  standard error. The check bias_shrinks reads its limit (checks/scene.py).
* **Settings** (estimators that choose them, ``chosen_settings``): what
  was chosen for the scene at this spp, how, and every candidate's
  held-out error (bayesian_hemisphere's ``auto``: integrators/quadrature/gp_settings.py).
* **Calibration of the posterior standard deviation** (estimators that
  write the ``posterior_std`` AOV), at the rung below the ladder's top
  (run/references.bars_rung: the reference resolves that rung's error bars
  at a quarter of the top's cost): per pixel, the RMSE of the K renders
  against the reference over the predicted std (rms over renders, the
  reference's variance added). Median and quartiles over pixels; **calibrated**
  if the median lies within :data:`~mcillum.validation.checks.convergence.CALIBRATED`
  (errors within 1.5× of what
  it predicts), **over-confident** above (errors larger than predicted),
  **under-confident** below.
"""

from __future__ import annotations

import math

import numpy as np

from mcillum.integrators.core import registry

from ..checks import convergence
from ..results import (BiasAtN, Calibration, EqualRays, GlossySettings, Quadrature,
                       SettingScore, Settings)
from ..run import jobs, references, stacks
from ..stats import costs, metrics
from . import common

#: Timed renders of each estimator and baseline for the equal-ray pair's seconds.
TIMED = 3
#: The N of the bias-against-N measurement (the default N is added).
BIAS_DIRECTIONS = (16, 256)
#: Renders per N other than the default (the plan's K, if fewer): the bias
#: check reads 2 % against standard errors of 0.01-0.2 % at K = 16 (full
#: profile), and N = 256 cost 11 s a scene there. Where a bias near 0 leaves
#: the check undecided at 8 (its se 0.4-0.75 % on lone_sphere_studio), the
#: plan's K are rendered.
BIAS_RENDERS = 8
#: Errors below this share of the reference count as exact (run/references).
EXACT = references.EXACT


def is_point_set(name: str) -> bool:
    """An estimator of N directions per shading point, mcillum's or a user's
    class derived from one (registry facts ``point_set``)."""
    return registry.facts(name).point_set


def planned_renders(names, k: int) -> int:
    """Renders this stage makes for ``names`` at K renders each (for the
    progress bar; estimators the scene refuses are counted too, a baseline
    rendered at N·spp is not)."""
    sets = [n for n in names if is_point_set(n)]
    baselines = {registry.facts(n).equal_rays_baseline for n in sets}
    return (TIMED * (len(sets) + len(baselines)) + min(k, BIAS_RENDERS) *
            sum(0 if registry.facts(n).unbiased else len(BIAS_DIRECTIONS) for n in sets))


def measure(ctx) -> None:
    """Per point-set estimator of the scene: ``ctx.quadrature[name]``."""
    ctx.quadrature = {}
    names = [n for n in ctx.integrators if is_point_set(n)]
    if not names:
        return
    spp, k = ctx.plan.ladder[-1], ctx.plan.renders
    ref = ctx.reference
    groups = _pairs(ctx, names, spp)
    seconds = _timings(ctx, groups, spp)
    # (baseline, N·spp) → the stack its error is read from: one per scene
    baselines = {pair: _baseline(ctx, *pair, spp, k, len(names) + names.index(members[0]))
                 for pair, members in groups.items()}
    for name in names:
        n = ctx.integrators[name].made.directions
        # the ladder's top rung: what K fresh renders at spp would be
        own = ctx.stacks[spp][name]
        # (the Monte Carlo estimator its registry facts name)
        against = registry.facts(name).equal_rays_baseline
        rays = (_equal_rays(own, baselines[against, n * spp], against, ref, n, spp,
                            seconds[name], seconds[against, n * spp])
                if (against, n * spp) in baselines else None)
        bias, calibration = None, None
        if not registry.facts(name).unbiased:
            bias = _bias_against_n(ctx, name, own, ref, k, 2 * len(names))
        bars = ctx.stacks[references.bars_rung(ctx.plan.ladder)][name]
        if "posterior_std" in bars.aovs:
            calibration = _calibration(bars, ref)
        ctx.quadrature[name] = Quadrature(name=name, directions=n, spp=spp, renders=k,
                                          equal_rays=rays, bias=bias, calibration=calibration,
                                          settings=_settings(ctx, name, spp))


def _pairs(ctx, names, spp) -> dict:
    """(baseline, N·spp) → the point-set estimators compared with it, for
    those whose facts name a registered baseline."""
    groups: dict = {}
    for name in names:
        against = registry.facts(name).equal_rays_baseline
        if against in registry.names():
            n = ctx.integrators[name].made.directions
            groups.setdefault((against, n * spp), []).append(name)
    return groups


def _timings(ctx, groups: dict, spp) -> dict:
    """Median seconds of TIMED renders: per point-set estimator at ``spp``
    (by name) and per baseline at N·spp (by (baseline, N·spp)), each
    baseline of ``groups`` (:func:`_pairs`) timed once with the estimators
    compared with it, interleaved and timed alone (executors.py)."""
    out = {}
    for g, ((against, rays), members) in enumerate(groups.items()):
        made = {m: ctx.integrators[m] for m in members}
        made[against] = ctx.integrators.get(against) or jobs.make(against, dict(ctx.params))
        found = stacks.kept(ctx, f"quadrature{g}-timing-{against}", f"timing {rays}", made,
                            {**{m: spp for m in members}, against: rays}, TIMED,
                            ctx.run.stream("quadrature", g).take(TIMED), label=ctx.label,
                            timed=True)
        out.update({m: float(np.median(found[m].seconds)) for m in members})
        out[against, rays] = float(np.median(found[against].seconds))
    return out


def _baseline(ctx, against: str, rays: int, spp: int, k: int, block: int) -> stacks.Stack:
    """The stack the baseline's error at ``rays`` = N·spp is read from: its
    ladder renders at ``spp`` where the scene's sampler draws independent
    samples (:func:`_equal_rays` scales their error by 1/N), else K renders
    at N·spp from block ``block`` of the quadrature stream."""
    rung = ctx.stacks[spp]
    sampler = ctx.scene.sensors()[0].sampler().class_name()
    if against in rung and sampler == "IndependentSampler":
        return rung[against]
    return _renders(ctx, against, {}, rays, k, block)


def _settings(ctx, name, spp) -> Settings | None:
    """How the estimator chose its settings for the scene at the stage's spp
    (asked of the driver's own instance: renders may have run elsewhere)."""
    chosen = getattr(ctx.integrators[name].made, "chosen_settings", None)
    found = chosen(ctx.scene, spp) if chosen is not None else None
    if found is None:
        return None
    rows = [SettingScore(**row) for row in found.pop("candidates")]
    glossy = found.pop("glossy", None)
    return Settings(**found, candidates=rows or None,
                    glossy=GlossySettings(**glossy) if glossy else None)


def _renders(ctx, name, params, spp, k, block, timed=False) -> stacks.Stack:
    """K renders from block ``block`` of the quadrature seed stream."""
    return common.stream_renders(ctx, "quadrature", name, params, spp, k, block, timed)


def _equal_rays(own, baseline, against: str, ref, n, spp, seconds: float,
                baseline_seconds: float) -> EqualRays:
    a = metrics.net_relmse(own.images, ref.mean, ref.variance_of_mean)
    # a baseline read at fewer samples: its net relMSE falls as 1/spp (module doc)
    scale = baseline.spp / (n * spp)
    b = metrics.net_relmse(baseline.images, ref.mean, ref.variance_of_mean) * scale
    ratio = float(a.mean() / b.mean()) if b.mean() > 0 else float("nan")
    # delta method on log(ā / b̄): var ≈ var(ā)/ā² + var(b̄)/b̄², each mean's
    # variance its renders' spread over K and the reference share's own (the
    # share subtracted is an estimate: it matters where the error is near it)
    share = costs.reference_share(ref.mean, ref.variance_of_mean, ref.passes).se
    ka, kb = len(a), len(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = math.sqrt((a.var(ddof=1) / ka + share ** 2) / a.mean() ** 2 +
                      (b.var(ddof=1) / kb + (share * scale) ** 2) / b.mean() ** 2)
    low, high = (ratio * math.exp(-1.96 * s), ratio * math.exp(1.96 * s)) \
        if np.isfinite(s) and ratio > 0 else (float("nan"), float("nan"))
    return EqualRays(baseline=against, baseline_spp=n * spp, relmse=float(a.mean()),
                     baseline_relmse=float(b.mean()), ratio=ratio, ratio_low=low, ratio_high=high,
                     seconds=seconds, baseline_seconds=baseline_seconds,
                     baseline_read_at=baseline.spp)


def _bias_against_n(ctx, name, own, ref, k: int, block: int) -> list[BiasAtN]:
    """The bias rows of ``name``, by N: the default N's from ``own`` (the
    ladder's top rung), each other N of BIAS_DIRECTIONS from
    :data:`BIAS_RENDERS` renders (seed blocks from ``block`` on), or from the
    plan's K where those leave the limit (checks/scene.bias_shrinks)
    undecided."""
    n, spp = ctx.integrators[name].made.directions, own.spp

    def rows(renders: int) -> list[BiasAtN]:
        found = [_bias(own, ref, n)]
        for b, m in enumerate(BIAS_DIRECTIONS):
            if m != n:
                other = _renders(ctx, name, {"directions": m}, spp, renders, block + b)
                found.append(_bias(other, ref, m))
        return sorted(found, key=lambda row: row.directions)

    found = rows(min(k, BIAS_RENDERS))
    # (near a bias of 0 the standard error of the rms is wide: render more)
    if BIAS_RENDERS < k and convergence.bias_limit_outcome(found[0], found[-1])[0] == \
            "inconclusive":
        found = rows(k)
    return found


def _bias(stack, ref, n) -> BiasAtN:
    # per pixel, the mean over channels: R, G and B come from the same
    # directions, so they are not independent evidence
    x = stack.images[..., :3].astype(np.float64).mean(axis=-1)
    k = len(x)
    m, v = x.mean(axis=0), x.var(axis=0, ddof=1) / k
    r = np.asarray(ref.mean, np.float64)[..., :3].mean(axis=-1)
    # (the mean of the channel variances: at least the channel mean's, so conservative)
    v_ref = np.asarray(ref.variance_of_mean, np.float64)[..., :3].mean(axis=-1)
    b = m - r
    noise = v + v_ref
    per_pixel = b ** 2 - noise                       # unbiased for the squared bias
    squared = float(per_pixel.mean())
    # se of that mean: Var(b̂²) ≈ 2 σ⁴ + 4 b² σ² per pixel-channel, σ² = noise
    se_squared = float(np.sqrt(np.sum(2 * noise ** 2 + 4 * np.maximum(per_pixel, 0) * noise))
                       / per_pixel.size)
    scale = float(np.sqrt(np.mean(r ** 2)))
    rms = math.sqrt(max(squared, 0.0))
    # se of √(B) by the delta method, se(B)/(2√B), where B is well above its
    # own se; nearer 0 that grows without bound (0.01 % ± 2.5 % on the quick
    # furnace, seed set 102), and √(B + se(B)) − √B ≤ √se(B) bounds it
    bound = math.sqrt(se_squared)
    se = min(se_squared / (2 * rms), bound) if rms > 0 else bound
    signed = float((b.mean()) / np.mean(r)) if np.mean(r) > 0 else float("nan")
    return BiasAtN(directions=n, rms_bias=rms / scale, rms_bias_se=se / scale, mean_bias=signed,
                   renders=k)


def _calibration(stack, ref) -> Calibration:
    x = stack.images[..., :3].astype(np.float64)
    std = stack.aovs["posterior_std"][..., :3].astype(np.float64)
    r = np.asarray(ref.mean, np.float64)[..., :3]
    v_ref = np.asarray(ref.variance_of_mean, np.float64)[..., :3]
    # the reference's own error is in every measured error: it joins the
    # prediction (a per-pixel subtraction would leave it where it is larger
    # than its variance, and call an exact quadrature over-confident)
    measured = np.sqrt(((x - r) ** 2).mean(axis=0))
    predicted = np.sqrt((std ** 2).mean(axis=0) + v_ref)
    # pixels where both are at float precision (exact) say nothing; a 0
    # prediction with an error is infinitely over-confident
    floor = EXACT * np.abs(r)
    keep = (predicted > floor) | (measured > floor)
    with np.errstate(divide="ignore"):
        ratio = np.where(predicted > 0, measured / np.where(predicted > 0, predicted, 1), np.inf)
    ratio = ratio[keep]
    if ratio.size == 0:
        return Calibration(median=float("nan"), q25=float("nan"), q75=float("nan"), pixels=0,
                           spp=stack.spp, verdict="exact (no error and none predicted)")
    q25, median, q75 = (float(q) for q in np.quantile(ratio, [0.25, 0.5, 0.75]))
    return Calibration(median=median, q25=q25, q75=q75, pixels=int(ratio.size), spp=stack.spp,
                       verdict=convergence.calibration_verdict(median))
