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

from . import checks, metrics, statistics, tails
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
    ref_noise = metrics.reference_relmse(r, reference.variance_of_mean)
    return RunStats(
        unit.spp, x.shape[0], rel, per, float(np.mean([metrics.mse(i, r) for i in x])),
        float(np.mean([metrics.mape(i, r) for i in x])), b, se,
        metrics.variance_per_render(x), metrics.nonfinite_fraction(unit.images), med,
        [float(s) for s in unit.seconds], pixels * unit.spp / med,
        1.0 / (rel * med) if rel > 0 else float("inf"), ref_noise,
        tails.firefly_fraction(np.nan_to_num(x), r))


def decider(reference_mean: np.ndarray, spp: int, reference_events: np.ndarray | None):
    """``decide(comparison, renders)``: :func:`checks.bias_outcome` of a
    comparison of ``renders`` (K, H, W, C) at ``spp``, with their own
    fireflies as tail evidence (for replications and failure cases)."""
    def decide(comparison, renders):
        events, k, carried = tails.tail_events([renders], reference_mean)
        return checks.bias_outcome(comparison, events, k, spp * k, carried, reference_events)
    return decide


def unbiasedness(stacks: dict, reference, runs: list[RunStats], alpha: float, tail,
                 reference_events: np.ndarray | None = None, fresh=None) -> Unbiasedness:
    """The batch-means test of all rungs ``stacks`` ({spp: (K, H, W, C)}) pooled,
    each weighted by its samples, against the reference, read by
    :func:`checks.bias_outcome` (``tail``: tails.tail_events of the stacks,
    weighted by spp; ``reference_events``: fireflies per pixel in path's
    renders); not tested (failed) where a render holds NaN/Inf. A rejection
    that counts is tested again on ``fresh()`` renders (K more at the top
    spp; None: not replicated): if it does not come back, the outcome is
    inconclusive (an α-chance alarm, or a bias too small for K)."""
    top = max(stacks)
    if not all(r.nonfinite_fraction == 0 for r in runs):
        return Unbiasedness(top, False, 0.0, 0.0, alpha, 0.0, [],
                            "not tested: non-finite pixels", outcome="fail",
                            reason="non-finite pixels")
    pooled = statistics.Moments.pooled({spp: x[..., :3] for spp, x in stacks.items()})
    ref = reference.moments()
    c = statistics.compare(pooled, ref, alpha)
    events, n, carried = tail
    samples = int(sum(spp * x.shape[0] for spp, x in stacks.items()))
    d = checks.bias_outcome(c, events, n, samples, carried, reference_events)
    if d.outcome == "fail" and fresh is not None:
        y = fresh()[..., :3]
        replicated, pixels, _, excused = statistics.replicated_rejection(
            c, d, y, ref, alpha, decider(reference.mean, top, reference_events))
        k = y.shape[0]
        if not replicated:
            d.outcome = "inconclusive"
            d.reason += (f"; not replicated in {k} fresh renders at {top} spp"
                         + (" (they caught fireflies: a tail)" if excused else ""))
        else:
            d.reason += (f"; replicated in {k} fresh renders at {top} spp"
                         + (f" ({int(pixels.sum())} px)" if pixels.any() else " (image mean)"))
    return Unbiasedness(top, c.passed, c.pass_fraction, c.min_p, alpha, c.alpha_pixel,
                        [float(p) for p in c.pooled_p], c.summary(), samples,
                        d.outcome, d.reason, d.rejected_up, d.rejected_down,
                        int(events.sum()), d.samples_needed)


def loglog_fit(x, y, alpha: float = 0.05):
    """(slope, intercept, slope interval) of log y against log x."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    fit = stats.linregress(lx, ly)
    dof = len(lx) - 2
    half = stats.t.ppf(1 - alpha / 2, dof) * fit.stderr if dof > 0 else np.inf
    return fit.slope, fit.intercept, (fit.slope - half, fit.slope + half)


def convergence(runs: list[RunStats], alpha: float = 0.05,
                heavy: bool = False) -> Convergence:
    """Slope of log (relMSE − the reference's share) against log spp, with its
    (1 − α) interval, read by :func:`checks.convergence_outcome` (``heavy``:
    the estimator's renders hold fireflies). An estimator with zero variance
    at every spp is exact. With fewer than 3 usable rungs the interval is
    unbounded and nothing is claimed (inconclusive)."""
    if all(r.variance_per_render <= 1e-12 for r in runs):
        c = Convergence(float("nan"), float("nan"), float("nan"), True, True, True)
    else:
        ok = [(r.spp, r.relmse - r.reference_relmse) for r in runs
              if r.relmse - r.reference_relmse > 0]
        if len(ok) < 3:
            c = Convergence(float("nan"), float("-inf"), float("inf"), False, False, False)
        else:
            slope, _, (lo, hi) = loglog_fit(*zip(*ok), alpha)
            c = Convergence(float(slope), float(lo), float(hi), False,
                            bool(lo <= checks.EXPECTED_SLOPE <= hi), bool(hi < 0))
    c.outcome, c.message = checks.convergence_outcome(c, heavy)
    c.passed = c.outcome == "pass"
    return c
