"""From renders and a reference to numbers: metrics per spp, convergence
slopes and efficiency of the small-image statistics.

* Convergence: least-squares fit of log relMSE against log spp over the
  ladder (relMSE averaged over the K renders at each spp, minus the part the
  reference's own noise adds, mean var_ref/(r² + ε)); the slope's (1 − α)
  interval is Student-t with n − 2 degrees of freedom. Monte Carlo expects
  −1. An estimator with zero variance at every rung is exact and converges
  trivially (the cosine estimator in a furnace).
* Efficiency: 1 / (relMSE · seconds) per render (higher is better).
* Unbiasedness: the batch-means test (statistics.py) of all rungs pooled.

Accuracy at equal time is the speed-and-images stage's (speed.py, costs.py):
at these small sizes a render's time is mostly its fixed cost.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from . import metrics, statistics, tails
from .results import Convergence, RunStats, Unbiasedness


def run_stats(unit, reference) -> RunStats:
    """Metrics of K renders of one estimator at one spp (see metrics.py)."""
    x = unit.images[..., :3].astype(np.float64)
    r = reference.mean[..., :3]
    per = [metrics.relmse(img, r) for img in x]
    rel = float(np.mean(per))
    b, se = metrics.bias(x, r, reference.image_mean_se)
    med = float(np.median(unit.seconds))
    pixels = x.shape[1] * x.shape[2]
    ref_noise = float(np.mean(reference.variance_of_mean[..., :3] / (r ** 2 + metrics.EPSILON)))
    return RunStats(
        unit.spp, x.shape[0], rel, per, float(np.mean([metrics.mse(i, r) for i in x])),
        float(np.mean([metrics.mape(i, r) for i in x])), b, se,
        metrics.variance_per_render(x), metrics.nonfinite_fraction(unit.images), med,
        [float(s) for s in unit.seconds], pixels * unit.spp / med,
        1.0 / (rel * med) if rel > 0 else float("inf"), ref_noise,
        tails.firefly_fraction(np.nan_to_num(x), r))


def unbiasedness(stacks: dict, reference, runs: list[RunStats], alpha: float) -> Unbiasedness:
    """The batch-means test of all rungs ``stacks`` ({spp: (K, H, W, C)}) pooled,
    each weighted by its samples, against the reference; not tested (failed)
    where a render holds NaN/Inf."""
    top = max(stacks)
    if not all(r.nonfinite_fraction == 0 for r in runs):
        return Unbiasedness(top, False, 0.0, 0.0, alpha, 0.0, [],
                            "not tested: non-finite pixels")
    pooled = statistics.Moments.pooled({spp: x[..., :3] for spp, x in stacks.items()})
    c = statistics.compare(pooled, reference.moments(), alpha)
    return Unbiasedness(top, c.passed, c.pass_fraction, c.min_p, alpha, c.alpha_pixel,
                        [float(p) for p in c.pooled_p], c.summary(),
                        int(sum(spp * x.shape[0] for spp, x in stacks.items())))


def loglog_fit(x, y, alpha: float = 0.05):
    """(slope, intercept, slope interval) of log y against log x."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    fit = stats.linregress(lx, ly)
    dof = len(lx) - 2
    half = stats.t.ppf(1 - alpha / 2, dof) * fit.stderr if dof > 0 else np.inf
    return fit.slope, fit.intercept, (fit.slope - half, fit.slope + half)


def convergence(runs: list[RunStats], alpha: float = 0.05) -> Convergence:
    """Slope of log (relMSE − the reference's share) against log spp, with its
    (1 − α) interval; it converges when the interval lies below 0, or when
    the estimator has zero variance at every spp (exact). With fewer than 3
    usable rungs the interval is unbounded and nothing is claimed."""
    if all(r.variance_per_render <= 1e-12 for r in runs):
        return Convergence(float("nan"), float("nan"), float("nan"), True, True, True)
    ok = [(r.spp, r.relmse - r.reference_relmse) for r in runs
          if r.relmse - r.reference_relmse > 0]
    if len(ok) < 3:
        return Convergence(float("nan"), float("-inf"), float("inf"), False, True, False)
    slope, _, (lo, hi) = loglog_fit(*zip(*ok), alpha)
    return Convergence(float(slope), float(lo), float(hi), False, bool(lo <= -1.0 <= hi),
                       bool(hi < 0))
