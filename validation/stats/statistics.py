"""Is an estimator unbiased? Batch-means tests against a reference.

Both sides are given as independent renders (different seeds): K images of the
estimator, M of the reference. Each render is itself a mean over spp samples,
so by the central limit theorem it is close to normal even where single
samples are heavy-tailed; the spread over renders measures each side's *own*
variance. (Mitsuba's render test uses the reference integrator's variance for
both sides, which wrongly rejects correct hemisphere estimators.)

Per pixel and colour channel, Welch's t statistic

    t = (ȳ_est − ȳ_ref) / sqrt(s²_est/K + s²_ref/M)

with Welch–Satterthwaite degrees of freedom gives a two-sided p-value. The
pooled test does the same, per channel, on the image mean of each render.
Channels are tested separately so that a colour shift with an unchanged
channel mean is caught; an alpha channel (4th) is ignored.

Error budget: total α (default 0.01), split by Bonferroni into α/2 for the
pooled tests (α/(2C) per channel) and α/2 for the per-pixel family, which is
Šidák-corrected over the P·C tested pixel channels:
α_px = 1 − (1 − α/2)^(1/(P·C)). The estimator passes when no pixel channel has
p < α_px and every pooled p ≥ α/(2C). Under the null hypothesis it fails with
probability ≤ α.

Pixels of constant radiance (zero variance on both sides) are compared to
float32 rounding: the standard error has a floor of 1e-5 × |mean|, so two
exact answers that differ by more than ~4e-5 relative still fail.

Reading a rejection (:mod:`checks`, "the rules of evidence"): a per-pixel
test on K renders of a heavy-tailed estimator rejects more often than its
level says (the mean of a right-skewed sample is usually low, and so is its
variance estimate). The checks module decides which rejections count (by
their direction and the estimator's fireflies); replication.py tests a
rejection that counts again on fresh renders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


#: Default family-wise significance level of :func:`compare`.
ALPHA = 0.01

#: Relative tolerance for "equal" zero-variance pixels (float32 rounding).
EXACT_RTOL = 1e-5


@dataclass
class Comparison:
    """Outcome of :func:`compare` (p-values are two-sided)."""

    alpha: float
    alpha_pixel: float       # Šidák-corrected level per pixel channel
    n_pixels: int
    n_channels: int
    pixel_p: np.ndarray      # (H, W) smallest p over channels (NaN: not tested)
    pixel_t: np.ndarray      # (H, W) t of that channel
    pass_fraction: float     # fraction of pixels whose channels all pass
    min_p: float
    pooled_t: np.ndarray     # (C,) per channel
    pooled_p: np.ndarray     # (C,)
    alpha_pooled: float      # level per pooled channel test
    passed: bool
    pooled_diff: np.ndarray | None = None   # (C,) image mean, estimator − reference
    pooled_se: np.ndarray | None = None     # (C,) its standard error
    pixel_diff: np.ndarray | None = None    # (H, W) estimator − reference in pixel_t's channel
    pixel_se: np.ndarray | None = None      # (H, W) its standard error
    reference_image_mean: np.ndarray | None = None   # (C,) the reference's image mean

    def relative_bias(self) -> tuple[np.ndarray, np.ndarray]:
        """(relative bias of the image mean per channel, the half-width of
        its interval at the pooled test's level), both as fractions of the
        reference's image mean (NaN where that is 0)."""
        ref = np.asarray(self.reference_image_mean, np.float64)
        z = stats.norm.isf(self.alpha_pooled / 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(ref > 0, ref, np.nan)
            return (np.asarray(self.pooled_diff) / scale,
                    z * np.asarray(self.pooled_se) / scale)

    def summary(self) -> str:
        # (the test's own result; checks/evidence.py decides what a rejection means)
        verdict = "no rejection" if self.passed else "rejected"
        pooled = ", ".join(f"{t:+.2f}" for t in self.pooled_t)
        return (f"{verdict}: {self.pass_fraction:.2%} of {self.n_pixels} pixels pass "
                f"at Šidák α_px={self.alpha_pixel:.2e} over {self.n_channels} channels "
                f"(min p={self.min_p:.2e}); pooled t=[{pooled}], "
                f"min p={self.pooled_p.min():.3g} (level {self.alpha_pooled:.3g})")


def welch(mean_a, var_a, n_a, mean_b, var_b, n_b):
    """Welch's two-sample t-test from means and sample variances.

    Returns (t, p). The squared standard error gets a floor of
    (EXACT_RTOL·max|mean|)²: float32 renders of a constant pixel differ by
    rounding (~1e-7 relative) depending on spp, and a sample variance of 1e-15
    against an exact 0 must not count as evidence. Where everything is zero,
    p = 1.
    """
    mean_a, var_a, mean_b, var_b = (np.asarray(x, np.float64)
                                    for x in (mean_a, var_a, mean_b, var_b))
    va, vb = var_a / n_a, var_b / n_b
    scale = np.maximum(np.abs(mean_a), np.abs(mean_b))
    se2 = va + vb + (EXACT_RTOL * scale) ** 2
    diff = mean_a - mean_b
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(se2 > 0, diff / np.sqrt(se2), 0.0)
        df = np.where(va + vb > 0,
                      (va + vb) ** 2 / (va ** 2 / (n_a - 1) + vb ** 2 / (n_b - 1)), 1e6)
    p = 2 * stats.t.sf(np.abs(t), np.maximum(df, 1.0))
    return t, np.where(se2 > 0, p, 1.0)


def batch_moments(renders: np.ndarray):
    """Mean and unbiased sample variance over axis 0 of a stack of renders."""
    renders = np.asarray(renders, np.float64)
    if renders.shape[0] < 2:
        raise ValueError("need at least 2 independent renders per side")
    return renders.mean(axis=0), renders.var(axis=0, ddof=1), renders.shape[0]


@dataclass
class Moments:
    """One side of a comparison, summarised: per-pixel mean and sample variance
    of one render (H, W, C) over n renders, and the same for the image mean
    (C,), which the pooled test uses."""

    mean: np.ndarray
    var: np.ndarray
    n: int | np.ndarray             # renders, or per pixel channel (pooled batches)
    image_mean: np.ndarray
    image_var: np.ndarray
    image_n: int | np.ndarray | None = None     # (None: n)

    @property
    def n_image(self):
        return self.n if self.image_n is None else self.image_n

    @classmethod
    def pooled(cls, stacks) -> "Moments":
        """All rungs of a ladder, {spp: (K, H, W, C) renders} or a list of
        (spp, renders) pairs (batches may share an spp), as one side.

        The mean weights each rung by its samples (spp·K); the variance of
        the mean from each batch's own spread (:func:`_pool`),
        with Welch–Satterthwaite degrees of freedom per pixel channel. More
        samples per pixel than the top rung alone, so rarer events are seen
        before judging.
        """
        pairs = stacks.items() if isinstance(stacks, dict) else stacks
        pairs = [(spp, np.asarray(x, np.float64)) for spp, x in pairs]
        pixel = _pool(pairs)
        image = _pool([(spp, x.mean(axis=(1, 2))) for spp, x in pairs])
        return cls(pixel[0], pixel[1], pixel[2], image[0], image[1], image[2])

    @classmethod
    def of(cls, renders) -> "Moments":
        renders = np.asarray(renders, np.float64)
        if renders.ndim == 3:
            renders = renders[..., None]
        mean, var, n = batch_moments(renders)
        im, iv, _ = batch_moments(renders.mean(axis=(1, 2)))
        return cls(mean, var, n, im, iv)


def _pool(pairs):
    """(mean, variance of one equivalent render, n) of batches [(spp, (K, ...))].

    The mean weights each batch by its samples, w_b = spp_b·K_b / N. The
    variance of that mean is Σ w_b² s_b² / K_b, each batch's own sample
    variance s_b² (not one variance pooled over batches: a batch of few
    samples per render misses a rare tail, and its small variance must not
    stand for the others'). n is the Welch–Satterthwaite degrees of freedom
    of that sum plus one, and the variance is scaled so that var / n is the
    variance of the mean.
    """
    n_all = sum(spp * x.shape[0] for spp, x in pairs)
    total, var_mean, dof_den, usable = 0.0, 0.0, 0.0, 0
    for spp, x in pairs:
        k = x.shape[0]
        w = spp * k / n_all
        total = total + spp * x.sum(axis=0)
        if k < 2:
            continue
        usable += 1
        v = w * w * x.var(axis=0, ddof=1) / k
        var_mean = var_mean + v
        dof_den = dof_den + v * v / (k - 1)
    if usable == 0:
        raise ValueError("need at least 2 renders on some rung")
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = np.where(dof_den > 0, np.asarray(var_mean) ** 2 / dof_den,
                       sum(x.shape[0] - 1 for _, x in pairs))
    n = np.maximum(2.0, dof + 1.0)              # per pixel channel
    return total / n_all, var_mean * n, n


def _channels(n, c: int):
    """Renders ``n`` of one side: a number, or per channel (pooled batches,
    :func:`_pool`) cut to the ``c`` channels tested."""
    return np.asarray(n)[..., :c] if np.ndim(n) else n


def compare(estimator, reference, alpha: float = ALPHA,
            mask: np.ndarray | None = None) -> Comparison:
    """Test that ``estimator`` and ``reference`` have equal means.

    Each side is a stack of independent renders, shape (n, H, W, C) with C in
    {1, 3, 4}, or its :class:`Moments` (a 4th, alpha channel is ignored).
    ``mask`` (H, W) selects the pixels to test (default: all).
    """
    est = estimator if isinstance(estimator, Moments) else Moments.of(estimator)
    ref = reference if isinstance(reference, Moments) else Moments.of(reference)
    if est.mean.shape != ref.mean.shape:
        raise ValueError(f"image sizes differ: {est.mean.shape} vs {ref.mean.shape}")
    c = min(3, est.mean.shape[-1])
    for side in (est, ref):
        if not (np.isfinite(side.mean).all() and np.isfinite(side.var).all()):
            raise ValueError("renders contain NaN or Inf")
    mask = np.ones(est.mean.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    n_pixels, n_channels = int(mask.sum()), c
    if n_pixels == 0:
        raise ValueError("the mask selects no pixels to test")

    est_pn, ref_pn = _channels(est.n, c), _channels(ref.n, c)
    t, p = welch(est.mean[..., :c], est.var[..., :c], est_pn,
                 ref.mean[..., :c], ref.var[..., :c], ref_pn)            # (H, W, C)
    alpha_pixel = 1.0 - (1.0 - alpha / 2) ** (1.0 / (n_pixels * n_channels))
    tested = p[mask]                                                 # (P, C)

    # Pooled: per channel, the mean over the whole image.
    pooled_diff = est.image_mean[:c] - ref.image_mean[:c]
    est_n, ref_n = _channels(est.n_image, c), _channels(ref.n_image, c)
    pooled_se = np.sqrt(est.image_var[:c] / est_n + ref.image_var[:c] / ref_n)
    if mask.all():
        pooled_t, pooled_p = welch(est.image_mean[:c], est.image_var[:c], est_n,
                                   ref.image_mean[:c], ref.image_var[:c], ref_n)
    else:  # image means over a mask are not kept in Moments: pixels only
        pooled_t, pooled_p = np.zeros(c), np.ones(c)
    alpha_pooled = alpha / (2 * n_channels)

    worst = np.argmin(p, axis=-1)[..., None]
    pixel_p = np.where(mask, np.take_along_axis(p, worst, -1)[..., 0], np.nan)
    pixel_t = np.where(mask, np.take_along_axis(t, worst, -1)[..., 0], np.nan)
    diff = est.mean[..., :c] - ref.mean[..., :c]
    se = np.sqrt(est.var[..., :c] / est_pn + ref.var[..., :c] / ref_pn)
    pixel_diff = np.take_along_axis(diff, worst, -1)[..., 0]
    pixel_se = np.take_along_axis(se, worst, -1)[..., 0]
    passed = bool(tested.min() >= alpha_pixel and pooled_p.min() >= alpha_pooled)
    return Comparison(alpha, alpha_pixel, n_pixels, n_channels, pixel_p, pixel_t,
                      float((tested.min(axis=-1) >= alpha_pixel).mean()),
                      float(tested.min()), np.atleast_1d(pooled_t),
                      np.atleast_1d(pooled_p), alpha_pooled, passed, pooled_diff, pooled_se,
                      pixel_diff, pixel_se, ref.image_mean[:c])


def mean_interval(values, alpha: float = ALPHA) -> tuple[float, float]:
    """Mean of independent ``values`` and the half-width of its two-sided
    (1 − α) Student-t confidence interval; raises ValueError for fewer than
    two values."""
    values = np.asarray(values, np.float64)
    n = values.size
    if n < 2:
        raise ValueError("need at least 2 independent values for an interval")
    half = stats.t.ppf(1 - alpha / 2, n - 1) * values.std(ddof=1) / np.sqrt(n)
    return float(values.mean()), float(half)


def loglog_fit(x, y, alpha: float = 0.05, y_var=None):
    """(slope, intercept, (1 − α) slope interval) of the least-squares line
    through log y against log x; the interval is Student-t with n − 2
    degrees of freedom (unbounded with fewer than 3 points). With ``y_var``
    (the sampling variance of each y) it is at least as wide as those
    variances make the slope's, carried through the least-squares weights
    (normal quantile): points that lie on a line by chance say little when
    each of them is uncertain (a heavy tail's rare render at one rung)."""
    lx, ly = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    fit = stats.linregress(lx, ly)
    dof = len(lx) - 2
    half = stats.t.ppf(1 - alpha / 2, dof) * fit.stderr if dof > 0 else np.inf
    if y_var is not None and dof > 0:
        # slope = Σ c_i log y_i, c_i = (lx_i − mean) / Sxx; var(log y) ≈ var(y) / y²
        c = (lx - lx.mean()) / np.sum((lx - lx.mean()) ** 2)
        carried = np.sqrt(np.sum(c ** 2 * np.asarray(y_var, float) / np.asarray(y, float) ** 2))
        half = max(half, stats.norm.ppf(1 - alpha / 2) * carried)
    return fit.slope, fit.intercept, (fit.slope - half, fit.slope + half)
