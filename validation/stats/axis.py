"""The budget axis's statistics (stages/budget_axis.py): relMSE from the
spread of K renders, a model of relMSE against time, efficiency ratios and
where two estimators' curves cross.

Why the spread and not a reference: at a minute per render `path`'s own
error is far below any reference the run could afford (its display
reference is about 16× `path`'s spp at the speed stage's budget of a tenth
of a second), and a relMSE against it would read the reference's noise.
For an unbiased estimator the per-pixel sample variance s² over K
independent renders is an unbiased estimate of its MSE, whatever the
reference, which only scales each pixel (r² + ε, as metrics.relmse):

    relMSE ≈ mean over pixels and RGB of s²(p) / (r(p)² + ε)

An estimator biased by design adds its bias² against the reference, less
what the reference's and the renders' own noise put into it
(:func:`error_relmse`).
"""

from __future__ import annotations

import math
import typing

import numpy as np

from ..results import Interval
from .metrics import EPSILON

#: Tiles of TILE² pixels are what the interval's bootstrap resamples: a
#: pixel's error is independent of its neighbours' for a box-filtered
#: film, and tiles keep what little a wider filter shares.
TILE = 8
BOOTSTRAP = 500
Z = 1.959963984540054            # 95 % two-sided normal quantile
#: A crossing needs a budget where an estimator's ratio to the base lies
#: below 1 at this level and one where it lies above: 99 %, two-sided.
#: Among 7 budgets two equal estimators read one at 95 % in about 2.3 % of
#: scenes (1 − 2·0.975⁷ + 0.95⁷), one at 99 % in about 0.1 %
#: (tests/test_budget_axis.py measures both and the power).
CROSSING_Z = 2.5758293035489004


class Estimate(typing.NamedTuple):
    """A relMSE and its 95 % interval, and the log-scale standard error
    that the interval implies (for ratios of two)."""

    value: float
    ci: Interval
    log_se: float


def _per_pixel_spread(images: np.ndarray, r: np.ndarray, eps: float) -> np.ndarray:
    """(H, W): mean over RGB of the sample variance over the K renders over
    (r² + ε)."""
    x = np.asarray(images, np.float64)[..., :3]
    s2 = x.var(axis=0, ddof=1)
    return np.mean(s2 / (np.asarray(r, np.float64)[..., :3] ** 2 + eps), axis=-1)


def _tiled(values: np.ndarray, tile: int) -> np.ndarray:
    """Sums of ``values`` (H, W) over tiles of tile² pixels (the edge tiles
    smaller), one per tile."""
    h, w = values.shape
    rows = np.add.reduceat(values, np.arange(0, h, tile), axis=0)
    return np.add.reduceat(rows, np.arange(0, w, tile), axis=1).ravel()


def _bootstrap(values: np.ndarray, seed: int) -> Estimate:
    """The mean of per-pixel ``values`` (H, W) and its percentile interval
    from resampling tiles with replacement."""
    n = values.size
    tiles = _tiled(values, TILE)
    mean = float(values.mean())
    rng = np.random.default_rng(seed)
    draws = tiles[rng.integers(0, len(tiles), (BOOTSTRAP, len(tiles)))].sum(axis=1) / n
    low, high = (float(x) for x in np.percentile(draws, [2.5, 97.5]))
    positive = max(low, 1e-300)
    log_se = (math.log(max(high, positive)) - math.log(positive)) / (2 * Z) if mean > 0 \
        else math.inf
    return Estimate(mean, Interval(max(low, 0.0), high), log_se)


def spread_relmse(images, r, eps: float = EPSILON, seed: int = 0) -> Estimate:
    """The relMSE of one render of an unbiased estimator from the spread of
    its K ≥ 2 renders (the module's formula) with a 95 % interval by
    bootstrap over tiles. Raises ValueError for fewer than two renders."""
    if len(images) < 2:
        raise ValueError(f"a spread needs two renders or more, got {len(images)}")
    return _bootstrap(_per_pixel_spread(images, r, eps), seed)


def error_relmse(images, r, variance_of_mean, eps: float = EPSILON, seed: int = 0) -> Estimate:
    """:func:`spread_relmse` plus the bias² of the renders' mean against
    reference ``r`` (per pixel (x̄ − r)² less the variance of x̄, s²/K, and
    the reference's ``variance_of_mean``): the relMSE of one render of an
    estimator that may be biased."""
    x = np.asarray(images, np.float64)[..., :3]
    k = len(x)
    rr = np.asarray(r, np.float64)[..., :3]
    s2 = x.var(axis=0, ddof=1)
    bias2 = (x.mean(axis=0) - rr) ** 2 - s2 / k - np.asarray(variance_of_mean)[..., :3]
    return _bootstrap(np.mean((s2 + bias2) / (rr ** 2 + eps), axis=-1), seed)


# ------------------------------ The model ----------------------------------------

class Model(typing.NamedTuple):
    """relMSE(t) = c / (t − t0) for t > t0: a fixed-pdf estimator's variance
    per sample times its cost per sample over the time left after its fixed
    cost t0. ``log_se`` is log c's standard error."""

    c: float
    t0: float
    log_se: float

    def relmse(self, seconds: float) -> float:
        return self.c / (seconds - self.t0) if seconds > self.t0 else math.inf


def fit(seconds, relmse, log_ses, t0: float) -> Model:
    """The :class:`Model` through measured points (median wall time,
    relMSE, its log-scale standard error) with the fixed cost ``t0`` of the
    estimator's cost model (clipped to [0, ½ the smallest time]): log c the
    mean of log(relMSE·(t − t0)); its standard error the points' own and
    their scatter about the line, in quadrature. Raises ValueError without
    points."""
    t = np.asarray(seconds, float)
    if not len(t):
        raise ValueError("a model needs a measured point at least")
    t0 = min(max(t0, 0.0), 0.5 * float(t.min()))
    logs = np.log(np.asarray(relmse, float) * (t - t0))
    own = float(np.sqrt(np.sum(np.square(log_ses)))) / len(t)
    scatter = float(logs.std(ddof=1) / np.sqrt(len(t))) if len(t) > 1 else 0.0
    return Model(float(np.exp(logs.mean())), t0, float(np.hypot(own, scatter)))


def agrees(model: Model, seconds: float, measured: Estimate) -> bool:
    """Does a point measured at ``seconds`` agree with ``model``'s
    prediction there, within both's 95 % intervals (log scale)?"""
    predicted = model.relmse(seconds)
    if not (math.isfinite(predicted) and measured.value > 0):
        return False
    return abs(math.log(measured.value / predicted)) <= Z * math.hypot(model.log_se,
                                                                       measured.log_se)


# ------------------------------ Efficiency ---------------------------------------

def log_se_of_times(seconds) -> float:
    """Log-scale standard error of the mean of render times."""
    t = np.asarray(seconds, float)
    return float(t.std(ddof=1) / (t.mean() * np.sqrt(len(t)))) if len(t) > 1 else 0.0


def ratio(relmse: float, seconds: float, log_se: float, base_relmse: float,
          base_seconds: float, base_log_se: float) -> tuple[float, Interval]:
    """Efficiency 1/(relMSE·t) over a base's, and its 95 % interval from
    the two log-scale standard errors (each of relMSE and time together)."""
    value = (base_relmse * base_seconds) / (relmse * seconds)
    half = Z * math.hypot(log_se, base_log_se)
    return value, Interval(value * math.exp(-half), value * math.exp(half))


class Crossing(typing.NamedTuple):
    """Where an estimator's efficiency ÷ a base's changes sides: from
    behind (the ratio's interval below 1) at ``behind_at`` to ahead (above
    1) at ``ahead_at``, or back, with ties between; ``seconds`` where the
    ratio passes 1 in between (log-log interpolation at its last change of
    sign there)."""

    estimator: str
    seconds: float
    overtakes: bool        # True: behind before ``seconds``, ahead after
    behind_at: float
    ahead_at: float


def _side(value: float, log_se: float) -> int:
    """+1 ahead (the ratio's CROSSING_Z interval above 1), −1 behind
    (below), 0 a tie."""
    margin = CROSSING_Z * log_se
    return 1 if math.log(value) > margin else -1 if math.log(value) < -margin else 0


def crossings(name: str, budgets, ratios) -> list[Crossing]:
    """The crossings of ``name``'s efficiency ratios (value, log-scale
    standard error) at increasing ``budgets`` (seconds; None where it has
    no ratio): each pair of budgets whose ratios lie on opposite sides of 1
    at CROSSING_Z with only ties between. A sign change of the ratio among
    ties alone is noise, not a crossing."""
    points = [(b, r) for b, r in zip(budgets, ratios) if r is not None and r[0] > 0]
    sided = [(i, _side(v, se)) for i, (_, (v, se)) in enumerate(points) if _side(v, se)]
    found = []
    for (i, a), (j, b) in zip(sided, sided[1:]):
        if a == b:
            continue
        at = points[j][0]
        for (b0, (v0, _)), (b1, (v1, _)) in zip(points[i:j], points[i + 1:j + 1]):
            if (v0 < 1) != (v1 < 1):
                l0, l1 = math.log(v0), math.log(v1)
                at = math.exp(math.log(b0) + (math.log(b1) - math.log(b0)) * l0 / (l0 - l1))
        found.append(Crossing(name, at, b > 0, points[i if a < 0 else j][0],
                              points[j if a < 0 else i][0]))
    return found
