"""Heavy tails: how the error of one render is distributed over many seeds.

An estimator that finds a small bright source (the sun) only by chance stays
unbiased but puts most of its error into rare renders and rare pixels. Its
mean relMSE then says little about a typical render, and a t-test on K renders
trusts a sample variance that rests on a few of them. Definitions (used by
``mcillum validate``'s failures group and written into results.json):

* per-render relMSE: :func:`metrics.per_render_relmse`, each seed's image
  against the reference; reported as median, 90th / 99th percentile (linear
  interpolation) and maximum over the seeds.
* firefly pixel: a pixel (of one render) whose luminance exceeds
  ``FIREFLY_FACTOR`` × the reference luminance there, the reference floored at
  ``FIREFLY_FLOOR`` × the reference image's mean luminance (so black pixels do
  not count every speck). Firefly fraction = firefly pixels / all pixels of all
  renders.
* spp to match: the spp at which an estimator's expected relMSE equals that of
  ``path`` at the same spp·(ratio), i.e. spp · mean relMSE(estimator) / mean
  relMSE(path) — valid for unbiased estimators, whose relMSE falls as 1/spp —
  with a bootstrap interval over seeds (heavy tails make it wide: say so).
* heavy tail (:func:`is_heavy`, the one rule every report and verdict
  uses): the worst render's relMSE is over ``TAIL_RATIO`` × the median and
  over ``TAIL_RELMSE`` (a near-exact estimator's ratio of tiny numbers names
  no tail), or fireflies are over ``TAIL_FIREFLIES`` of all pixels.
* an error whose mean K renders cannot bound (:func:`error_tail`): the
  fireflies carry at least ``TAIL_ERROR_SHARE`` of the renders' squared
  relative error, and either they are fewer than ``TAIL_FIT_EVENTS`` or the
  generalized Pareto shape fitted to their errors (maximum likelihood over
  the excess above the smallest; a fit that fails counts) is at least
  ``TAIL_SHAPE``. A tail of
  shape ≥ ½ has no finite variance, so a mean over renders has no normal
  limit and the Student-t interval misses the rare errors it has not seen
  yet (tests/test_costs.py measures how often).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from mcillum.envmaps.sun import luminance

from ..results import Percentiles, SppToMatch
from . import metrics

FIREFLY_FACTOR = 10.0
FIREFLY_FLOOR = 0.01
TAIL_RATIO = 10.0
TAIL_RELMSE = 1e-3
TAIL_FIREFLIES = 1e-3
TAIL_ERROR_SHARE = 0.25
TAIL_SHAPE = 0.5
TAIL_FIT_EVENTS = 20


def bad_values(x: np.ndarray) -> tuple[int, int]:
    """(NaN/Inf values, negative values) in renders ``x``."""
    return int((~np.isfinite(x)).sum()), int((x < 0).sum())


def tail_ratio(per_render: np.ndarray) -> float:
    """Worst over median per-render relMSE (1 where the median is 0)."""
    med = float(np.median(per_render))
    return float(np.max(per_render) / med) if med > 0 else 1.0


def is_heavy(relmse_max: float, relmse_median: float, firefly_fraction: float) -> bool:
    """Is an error distribution heavy-tailed (see the module doc)?"""
    ratio = relmse_max / relmse_median if relmse_median > 0 else 1.0
    return (ratio > TAIL_RATIO and relmse_max > TAIL_RELMSE) or \
        firefly_fraction > TAIL_FIREFLIES


def percentiles(values: np.ndarray) -> Percentiles:
    v = np.asarray(values, np.float64)
    return Percentiles(mean=float(v.mean()), median=float(np.median(v)),
                       p90=float(np.percentile(v, 90)), p99=float(np.percentile(v, 99)),
                       max=float(v.max()))


def firefly_mask(renders: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(K, H, W) True where a render's pixel is a firefly (see module doc)."""
    ref = luminance(reference)
    floor = FIREFLY_FLOOR * max(float(ref.mean()), 1e-12)
    return luminance(renders) > FIREFLY_FACTOR * np.maximum(ref, floor)


def firefly_fraction(renders: np.ndarray, reference: np.ndarray) -> float:
    return float(firefly_mask(renders, reference).mean())


def tail_events(stacks, reference: np.ndarray, weights=None):
    """Fireflies per pixel (H, W) over every render of ``stacks`` (an iterable
    of (K, H, W, C) stacks, e.g. the rungs of a ladder), the number of
    renders, and what the fireflies carried (C,): their excess over the
    reference, summed over pixels and averaged over renders as the mean of
    the stacks weighs them (``weights``: one per stack, e.g. its spp, as
    statistics.Moments.pooled weighs rungs; default equal), in radiance, as
    a share of the image mean of one render. Each firefly is a render in
    which that pixel caught a rare, bright contribution: the evidence that an
    estimator is heavy-tailed here."""
    stacks = list(stacks)
    weights = [1.0] * len(stacks) if weights is None else list(weights)
    events, n, carried, total = 0, 0, 0.0, 0.0
    r = reference[..., :3]
    for x, w in zip(stacks, weights):
        x = np.nan_to_num(np.asarray(x[..., :3], np.float64))
        fire = firefly_mask(x, r)                                   # (K, H, W)
        events = events + fire.sum(axis=0)
        excess = np.where(fire[..., None], x - r, 0.0).mean(axis=(1, 2))   # (K, C)
        carried = carried + w * excess.sum(axis=0)
        total += w * x.shape[0]
        n += x.shape[0]
    return np.asarray(events, np.int64), n, np.asarray(carried, np.float64) / max(total, 1e-300)


def largest_event(stacks, reference: np.ndarray, spps) -> float:
    """The largest contribution one rare event can have made to a pixel's
    sum of samples, over every firefly of ``stacks`` (renders at ``spps``
    samples per pixel): spp × its excess over the reference in its
    brightest channel, since a render's pixel is the mean of its spp samples
    and holds at least one event (0: no firefly). The rules of evidence
    weigh a pixel's deficit in these units."""
    largest = 0.0
    r = reference[..., :3]
    for x, spp in zip(stacks, spps):
        x = np.nan_to_num(np.asarray(x[..., :3], np.float64))
        fire = firefly_mask(x, r)
        if fire.any():
            excess = (x - r)[fire].max()
            largest = max(largest, float(spp * excess))
    return largest


@dataclass(frozen=True)
class ErrorTail:
    """What the fireflies of K renders carry of their squared relative error
    (:func:`error_tail`)."""

    fireflies: int
    share: float                # of the renders' summed squared relative error
    #: generalized Pareto shape of their errors (None: fewer than
    #: TAIL_FIT_EVENTS, or a share below TAIL_ERROR_SHARE, not fitted; NaN:
    #: the fit failed, read as heavy)
    shape: float | None
    unbounded: bool             # K renders cannot bound the mean error from above

    def text(self) -> str:
        """In words: 'N fireflies carry S % of its squared error, their tail's
        shape k (≥ 0.5: no finite variance)'."""
        if self.shape is None:
            shape = f", too few (< {TAIL_FIT_EVENTS}) to give their tail's shape"
        elif np.isnan(self.shape):
            shape = ", their tail's shape not to be fitted (no spread)"
        else:
            heavy = self.shape >= TAIL_SHAPE
            shape = (f", their tail's shape {self.shape:.2f} ({'≥' if heavy else '<'} "
                     f"{TAIL_SHAPE:g}: {'no' if heavy else 'a'} finite variance)")
        return (f"{self.fireflies} fireflies carry {100 * self.share:.0f} % of its squared "
                f"error{shape}")


def error_tail(renders: np.ndarray, reference: np.ndarray) -> ErrorTail:
    """The fireflies (:func:`firefly_mask`) of ``renders`` (K, H, W, C)
    against ``reference``, the share of the squared relative error
    (metrics.squared_relative_error, averaged over RGB) they carry, the
    generalized Pareto shape of their errors, and whether the rule of the
    module doc says K renders cannot bound the mean error."""
    x, r = np.asarray(renders[..., :3], np.float64), np.asarray(reference[..., :3], np.float64)
    e = metrics.squared_relative_error(x, r).mean(axis=-1)              # (K, H, W)
    fire = firefly_mask(np.nan_to_num(x), r)
    total = float(e.sum())
    share = float(e[fire].sum()) / total if total > 0 else 0.0
    count = int(fire.sum())
    shape = None
    if count >= TAIL_FIT_EVENTS and share >= TAIL_ERROR_SHARE:
        v = e[fire]
        try:
            shape = float(stats.genpareto.fit(v - v.min(), floc=0)[0])
        except (stats.FitError, ValueError, RuntimeError):
            shape = float("nan")        # (ties, no spread: no shape to read)
    unbounded = share >= TAIL_ERROR_SHARE and (shape is None or not shape < TAIL_SHAPE)
    return ErrorTail(fireflies=count, share=share, shape=shape, unbounded=unbounded)


def spp_to_match(relmse_est: np.ndarray, relmse_ref: np.ndarray, spp: int,
                 boot: int = 2000, level: float = 0.9, seed: int = 0) -> SppToMatch:
    """spp an estimator needs for the mean relMSE ``path`` has at ``spp``,
    assuming relMSE ∝ 1/spp, with a bootstrap ``level`` interval over seeds."""
    a, b = np.asarray(relmse_est, np.float64), np.asarray(relmse_ref, np.float64)
    point = spp * a.mean() / b.mean()
    rng = np.random.default_rng(seed)
    ia = rng.integers(0, a.size, (boot, a.size))
    ib = rng.integers(0, b.size, (boot, b.size))
    ratios = spp * a[ia].mean(axis=1) / b[ib].mean(axis=1)
    lo, hi = np.percentile(ratios, [50 * (1 - level), 50 * (1 + level)])
    return SppToMatch(spp=float(point), low=float(lo), high=float(hi), level=level)
