"""From renders and a reference to numbers: metrics per spp, convergence
slopes, efficiency and the equal-time comparison.

* Convergence: least-squares fit of log relMSE against log spp over the
  ladder (relMSE averaged over the K renders at each spp, minus the part the
  reference's own noise adds, mean var_ref/(r² + ε)); the slope's (1 − α)
  interval is Student-t with n − 2 degrees of freedom. Monte Carlo expects
  −1. An estimator with zero variance at every rung is exact and converges
  trivially (the cosine estimator in a furnace).
* Efficiency: 1 / (relMSE · seconds) per render (higher is better).
* Equal time: per estimator, fit log relMSE = a + b·log t over the ladder
  (t = median seconds per render); at a common budget T (the geometric mean
  of the estimators' median times at their middle rung) the fit predicts each
  estimator's relMSE and so a ranking; a render of each estimator at the spp
  its measured ladder says fits in T (:func:`spp_for_budget`) checks it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from . import metrics


@dataclass
class RunStats:
    spp: int
    renders: int
    relmse: float
    relmse_per_render: list[float]
    mse: float
    mape: float
    bias: float
    bias_se: float
    variance_per_render: float
    nonfinite_fraction: float
    median_seconds: float
    seconds: list[float]
    samples_per_second: float
    efficiency: float
    reference_relmse: float        # what the reference's own noise adds to relmse


def run_stats(unit, reference) -> RunStats:
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
        1.0 / (rel * med) if rel > 0 else float("inf"), ref_noise)


@dataclass
class Slope:
    slope: float
    low: float
    high: float
    exact: bool = False

    @property
    def converges(self) -> bool:
        """Exact, or the error clearly falls with spp (interval below 0)."""
        return self.exact or self.high < 0

    @property
    def consistent_with_mc(self) -> bool:
        return self.exact or self.low <= -1.0 <= self.high


def loglog_fit(x, y, alpha: float = 0.05):
    """(slope, intercept, slope interval) of log y against log x."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    fit = stats.linregress(lx, ly)
    dof = len(lx) - 2
    half = stats.t.ppf(1 - alpha / 2, dof) * fit.stderr if dof > 0 else np.inf
    return fit.slope, fit.intercept, (fit.slope - half, fit.slope + half)


def convergence(runs: list[RunStats], alpha: float = 0.05) -> Slope:
    if all(r.variance_per_render <= 1e-12 for r in runs):
        return Slope(float("nan"), float("nan"), float("nan"), exact=True)
    ok = [(r.spp, r.relmse - r.reference_relmse) for r in runs
          if r.relmse - r.reference_relmse > 0]
    if len(ok) < 3:
        return Slope(float("nan"), float("-inf"), float("inf"))
    slope, _, (lo, hi) = loglog_fit(*zip(*ok), alpha)
    return Slope(float(slope), float(lo), float(hi))


@dataclass
class EqualTime:
    budget_seconds: float
    predicted_relmse: dict
    predicted_ranking: list
    spp: dict                  # spp each estimator gets in the budget
    measured_relmse: dict | None = None
    measured_seconds: dict | None = None
    measured_ranking: list | None = None

    @property
    def agrees(self) -> bool | None:
        if self.measured_ranking is None:
            return None
        return self.measured_ranking[0] == self.predicted_ranking[0]


def equal_time_plan(per_estimator: dict[str, list[RunStats]]) -> EqualTime | None:
    """Budget, predicted relMSE and ranking, and the spp each estimator gets."""
    fits, lines, middles = {}, {}, []
    for name, runs in per_estimator.items():
        ok = [r for r in runs if r.relmse > 0]
        if len(ok) < 2:
            return None
        t = [r.median_seconds for r in ok]
        slope, intercept, _ = loglog_fit(t, [r.relmse for r in ok])
        fits[name] = (slope, intercept)
        lines[name] = ([r.spp for r in ok], t)
        middles.append(ok[len(ok) // 2].median_seconds)
    budget = float(np.exp(np.mean(np.log(middles))))
    predicted = {n: float(np.exp(b + a * np.log(budget))) for n, (a, b) in fits.items()}
    spp = {n: spp_for_budget(budget, *pts) for n, pts in lines.items()}
    return EqualTime(budget, predicted, sorted(predicted, key=predicted.get), spp)


def spp_for_budget(budget: float, spp, seconds) -> int:
    """spp whose render takes ``budget`` seconds, read off the measured ladder:
    log-log interpolation between rungs (times made non-decreasing), and
    proportional scaling beyond its ends. A straight-line fit of time against
    spp is useless at small images, where launch overhead dominates: its
    slope is ~0 and the solved spp explodes (seen: 550 spp for a 4 ms budget
    that took 150 ms)."""
    spp = np.asarray(spp, float)
    t = np.maximum.accumulate(np.asarray(seconds, float))
    if budget <= t[0]:
        return max(1, int(spp[0] * budget / t[0]))
    if budget >= t[-1]:
        return max(1, int(spp[-1] * budget / t[-1]))
    return max(1, int(round(np.exp(np.interp(np.log(budget), np.log(t), np.log(spp))))))


def equal_time_measure(plan: EqualTime, units: dict, reference) -> EqualTime:
    stats_ = {n: run_stats(u, reference) for n, u in units.items()}
    plan.measured_relmse = {n: s.relmse for n, s in stats_.items()}
    plan.measured_seconds = {n: s.median_seconds for n, s in stats_.items()}
    plan.measured_ranking = sorted(plan.measured_relmse, key=plan.measured_relmse.get)
    return plan
