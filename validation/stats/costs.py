"""What a render costs, and how much error it buys in a given time.

The numbers of the speed-and-images stage (stages/speed.py) and of
``mcillum bench``, as small pure functions:

* **Cost model** t(spp) = a + b·spp: least squares over warm renders at two
  or more spp values with several repeats each; a is the fixed cost of a
  render (launch, film, develop), b the seconds per sample per pixel. The
  95 % intervals are percentile bootstraps over the repeats, resampled
  within each spp value (:data:`BOOTSTRAP` resamples, a fixed generator, so
  the same timings give the same intervals).
* **spp for a budget** T: max(1, round((T − a)/b)) (:func:`spp_for`).
* **relMSE at a budget**: the mean over K renders with a Student-t 95 %
  interval (K − 1 degrees of freedom), :func:`relmse_interval`.
* **Efficiency** 1/((relMSE − the reference's share)·t), t the mean wall
  time of the K renders (:func:`efficiency`); its interval and that of a
  ratio of two efficiencies (:func:`ratio`) come from the delta method on
  logarithms, with K − 1 degrees of freedom (conservative for a ratio), the
  share's standard error included; where the net relMSE is not above 0 at
  95 %, only a lower bound.
* **Ranking with ties**: A beats B only where their efficiency intervals
  separate; an estimator's rank is one plus the number that beat it.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..results import CostModel, Interval, Placement
from . import metrics
from .statistics import mean_interval

BOOTSTRAP = 2000
LEVEL = 0.95
#: The fixed cost may be at most this share of the largest budget's time,
#: where efficiency is read (stages/speed.budget_spp).
MAX_OVERHEAD = 0.10


# ------------------------------- Cost model -------------------------------------

def _line(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(intercept, slope) of least-squares lines through (x, y[i]) for every
    row i of y (closed form, vectorised over bootstrap replicates)."""
    xm = x.mean()
    slope = ((x - xm) * (y - y.mean(axis=-1, keepdims=True))).sum(axis=-1) / \
        ((x - xm) ** 2).sum()
    return y.mean(axis=-1) - slope * xm, slope


def fit_cost(timings: dict[int, list[float]], seed: int = 0) -> CostModel:
    """t = a + b·spp fitted to ``timings`` ({spp: [seconds of each repeat]}),
    with 95 % intervals of a and b: bootstrap standard errors (repeats
    resampled within each spp value, each value's spread first scaled by
    √(n/(n − 1)) so that n repeats do not understate it), times the Student-t
    quantile with N − 2 degrees of freedom (N timings). Plain percentile
    intervals of 5 repeats covered b in only 84 % of synthetic data sets
    (tests/test_costs.py)."""
    groups = {int(s): np.asarray(t, float) for s, t in timings.items() if len(t)}
    if len(groups) < 2:
        raise ValueError(f"a cost model needs timings at two spp values or more, got "
                         f"{sorted(groups)}")
    x = np.concatenate([np.full(len(t), s, float) for s, t in groups.items()])
    y = np.concatenate(list(groups.values()))
    a, b = _line(x, y)
    rng = np.random.default_rng(seed)
    pools = [t.mean() + (t - t.mean()) * np.sqrt(len(t) / max(len(t) - 1, 1))
             for t in groups.values()]
    resampled = np.concatenate([p[rng.integers(0, len(p), (BOOTSTRAP, len(p)))]
                                for p in pools], axis=1)
    ab, bb = _line(x, resampled)
    q = float(stats.t.ppf((1 + LEVEL) / 2, max(len(y) - 2, 1)))
    sa, sb = q * float(ab.std(ddof=1)), q * float(bb.std(ddof=1))
    return CostModel(fixed_s=float(a), per_spp_s=float(b),
                     fixed_s_ci=Interval(float(a) - sa, float(a) + sa),
                     per_spp_s_ci=Interval(float(b) - sb, float(b) + sb),
                     timings={str(s): [float(v) for v in t]
                              for s, t in sorted(groups.items())})


def seconds_at(model: CostModel, spp: float) -> float:
    """The time the model predicts for one render at ``spp``. A fitted fixed
    cost below 0 (timing noise on a loaded machine) counts as 0, and a
    per-spp cost below 0 as 0: no render takes less than nothing, nor less
    at more spp."""
    return max(model.fixed_s, 0.0) + max(model.per_spp_s, 0.0) * spp


def spp_for(model: CostModel, budget: float) -> int:
    """The spp whose render the model says takes ``budget`` seconds (≥ 1)."""
    if model.per_spp_s <= 0:
        return 1
    return max(1, int(round((budget - max(model.fixed_s, 0.0)) / model.per_spp_s)))


def overhead_share(model: CostModel, seconds: float) -> float:
    """The share of a ``seconds`` render that is fixed cost."""
    return max(model.fixed_s, 0.0) / seconds if seconds > 0 else float("inf")


# ------------------------------ Error and time ----------------------------------

def _t(k: int) -> float:
    return float(stats.t.ppf((1 + LEVEL) / 2, max(k - 1, 1)))


def relmse_interval(values) -> tuple[float, Interval]:
    """Mean relMSE of independent renders and its Student-t 95 % interval,
    its lower end clipped at 0 (a relMSE is never negative); unbounded from
    fewer than two renders."""
    v = np.asarray(values, float)
    if len(v) < 2:
        return float(v.mean()), Interval(float("-inf"), float("inf"))
    m, half = mean_interval(v, 1 - LEVEL)
    return m, Interval(max(m - half, 0.0), m + half)


def _log_se(values) -> float:
    """Standard error of log(mean of ``values``) (delta method)."""
    v = np.asarray(values, float)
    m = v.mean()
    if len(v) < 2 or m <= 0:
        return 0.0
    return float(v.std(ddof=1) / (m * np.sqrt(len(v))))


#: The log-scale spread the load of other processes adds to a render set's
#: mean time beyond what the set's own scatter shows, per share of the
#: machine's cores they used: load comes and goes on longer time scales than
#: a set of renders. With a busy loop on one of two cores, efficiency ÷ path
#: moved from a quiet run by up to 16 % here and 20 % on CI, where the
#: loaded set's interval claimed ±15 %
#: (docs/measurements.md#2026-12-05-loaded-machine-intervals).
LOAD_SPREAD = 0.15


def load_log_se(others_cores: float | None, cores: int) -> float:
    """The log-scale standard error a render set's mean time gains from
    other processes that used ``others_cores`` of the machine's ``cores`` on
    average meanwhile (run/load.py); 0 where that is unknown."""
    if not others_cores or cores <= 0:
        return 0.0
    return LOAD_SPREAD * min(others_cores / cores, 1.0)


class Share(typing.NamedTuple):
    """What a reference's own noise adds to every relMSE measured against it
    (metrics.reference_relmse), and the standard error of that figure."""

    value: float = 0.0
    se: float = 0.0


def reference_share(r, variance_of_mean, passes: int) -> Share:
    """The share of reference ``r`` (its per-pixel ``variance_of_mean`` from
    ``passes`` passes). Its standard error treats the image's variance as
    estimated from ``passes`` values, √(2/(passes − 1)) of it: what one
    pixel's estimate would have, an upper bound where pixels are
    independent, and honest where a few fireflies carry the variance."""
    value = metrics.reference_relmse(r, variance_of_mean)
    return Share(value, value * float(np.sqrt(2.0 / max(passes - 1, 1))))


@dataclass(frozen=True)
class Efficiency:
    """1/(net relMSE · mean seconds) with its 95 % interval; net = the mean
    relMSE of the renders less the reference's share. ``resolved`` is False
    where the net relMSE is not above 0 at 95 %: the error is the
    reference's noise, and only the lower end of the interval means
    anything (its upper end is +inf)."""

    value: float
    log_se: float
    ci: Interval
    resolved: bool


def efficiency(relmse, seconds, share: Share = Share(), load_se: float = 0.0) -> Efficiency:
    """The efficiency of K renders (per-render relMSE and wall times),
    against the truth rather than against the reference's noise: delta
    method on logarithms, Student-t with K − 1 degrees of freedom; the
    times' standard error widened by ``load_se`` (:func:`load_log_se`)."""
    v, t = np.asarray(relmse, float), np.asarray(seconds, float)
    q = _t(len(v))
    net = float(v.mean()) - share.value
    se = float(np.hypot(v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else np.inf, share.se))
    mean_t, t_se = float(t.mean()), float(np.hypot(_log_se(t), load_se))
    if net > q * se and mean_t > 0:
        log_se = float(np.hypot(se / net, t_se))
        value = 1.0 / (net * mean_t)
        return Efficiency(value, log_se, Interval(value * np.exp(-q * log_se),
                                                  value * np.exp(q * log_se)), True)
    # (only a lower bound: the net error may be 0)
    low = 1.0 / ((max(net, 0.0) + q * se) * mean_t * np.exp(q * t_se)) \
        if np.isfinite(se) and mean_t > 0 else 0.0
    value = 1.0 / (net * mean_t) if net > 0 and mean_t > 0 else float("inf")
    return Efficiency(value, float("inf"), Interval(float(low), float("inf")), False)


def ratio_interval(relmse, seconds, base_relmse, base_seconds, share: Share = Share(),
                   load_se: float = 0.0, base_load_se: float = 0.0) -> tuple[float, Interval]:
    """Efficiency of one estimator over a base's (``path``) and its interval,
    both net of the reference's ``share``, each's times widened by its own
    load (:func:`efficiency`, :func:`ratio`)."""
    return ratio(efficiency(relmse, seconds, share, load_se),
                 efficiency(base_relmse, base_seconds, share, base_load_se),
                 min(len(relmse), len(base_relmse)))


def ratio(e: Efficiency, base: Efficiency, renders: int) -> tuple[float, Interval]:
    """Efficiency ``e`` over ``base``'s, of ``renders`` renders each at least,
    and its interval. Where ``e`` is not resolved from the reference's noise
    the interval is a lower bound (its upper end +inf); where ``base`` is
    not, the ratio is NaN."""
    q = _t(renders)
    if not base.resolved:
        return float("nan"), Interval(0.0, float("inf"))
    value = e.value / base.value
    if not e.resolved:
        return value, Interval(e.ci.low / base.value * np.exp(-q * base.log_se), float("inf"))
    half = q * float(np.hypot(e.log_se, base.log_se))
    return value, Interval(value * np.exp(-half), value * np.exp(half))


def ranking(intervals: dict[str, tuple[float, Interval]]) -> list[Placement]:
    """Estimators from most to least efficient: ``intervals`` is {name:
    (efficiency, interval)}. A beats B only where A's interval lies wholly
    above B's; rank = 1 + the number that beat it; ties are listed."""
    def beats(a: str, b: str) -> bool:
        return intervals[a][1].low > intervals[b][1].high

    names = sorted(intervals, key=lambda n: -intervals[n][0])
    return [Placement(estimator=n, rank=1 + sum(beats(o, n) for o in names),
                      tied_with=[o for o in names
                                 if o != n and not beats(o, n) and not beats(n, o)],
                      efficiency=intervals[n][0], ci=intervals[n][1])
            for n in names]


def separated(ranking: list[Placement]) -> set[tuple[str, str]]:
    """Pairs (A, B) where A beats B: A ranks above B and they are not tied."""
    return {(a.estimator, b.estimator) for i, a in enumerate(ranking)
            for b in ranking[i + 1:] if b.estimator not in a.tied_with and a.rank < b.rank}
