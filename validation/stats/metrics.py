"""Error metrics, defined once. Every number in results.json comes from here.

Notation: x is a rendered image, r the reference mean image, both (H, W, C)
linear radiance; means run over all pixels and colour channels.

* MSE     = mean (x − r)²
* relMSE  = mean (x − r)² / (r² + ε),  ε = 0.01   (tev's convention; ε keeps
            black pixels from dominating; pbrt's (r + ε)² differs)
* MAPE    = mean |x − r| / (|r| + ε),  ε = 0.01; per pixel (mean over
            channels) it is the relative-error map of the report
* bias    = mean over pixels of (x̄ − r), x̄ the mean of K renders, with its
            standard error from the spread of per-render image means and the
            reference's own standard error
* variance per render = mean over pixels of the sample variance over K renders
* non-finite fraction = share of NaN/±Inf values (must be 0)
* FLIP    = NVIDIA's perceptual difference (Andersson et al. 2020, 2021) in its
            HDR mode, per pixel in [0, 1], and its mean: the ``flip-evaluator``
            package, which tone-maps both images itself (ACES, exposures
            from the reference), as its documentation prescribes for
            linear HDR input; 67 pixels per degree (its default)
"""

from __future__ import annotations

import flip_evaluator
import numpy as np

EPSILON = 0.01

#: A relMSE counts as resolved from the reference's own noise above this
#: multiple of the reference's share (:func:`reference_relmse`); within it
#: the reference limits the figure.
RESOLVED = 2.0

#: What each number of results.json means, written into it (``definitions``).
DEFINITIONS = {
    "mse": "mean over pixels and channels of (x - r)^2",
    "relmse": f"mean of (x - r)^2 / (r^2 + {EPSILON}) (tev convention)",
    "mape": f"mean of |x - r| / (|r| + {EPSILON})",
    "bias": "image mean of (mean of K renders - reference), with standard error",
    "variance_per_render": "mean over pixels of the sample variance over K renders",
    "nonfinite_fraction": "share of NaN/Inf values in the K renders (must be 0)",
    "firefly_fraction": "share of pixels of all renders brighter than 10x the reference there",
    "efficiency": "1 / (relmse * median seconds per render)",
    "unbiasedness": "per-pixel-channel Welch t-tests (Sidak) + pooled per-channel tests "
                    "(Bonferroni), family-wise alpha, variances from each side's own renders",
    "slope": "least-squares slope of log relmse vs log spp, Student-t interval",
}


def _finite(x):
    x = np.asarray(x, np.float64)
    return np.where(np.isfinite(x), x, 0.0)


def mse(x, r) -> float:
    return float(np.mean((_finite(x) - r) ** 2))


def squared_relative_error(x, r, eps: float = EPSILON) -> np.ndarray:
    """(x − r)² / (r² + ε) per value: what :func:`relmse` averages."""
    r = np.asarray(r, np.float64)
    return (_finite(x) - r) ** 2 / (r ** 2 + eps)


def relmse(x, r, eps: float = EPSILON) -> float:
    return float(np.mean(squared_relative_error(x, r, eps)))


def per_render_relmse(renders, r, eps: float = EPSILON) -> np.ndarray:
    """:func:`relmse` of each render of a (K, H, W, C) stack against r, RGB
    channels."""
    r = np.asarray(r, np.float64)[..., :3]
    return np.array([relmse(x[..., :3], r, eps) for x in renders])


def reference_relmse(r, variance_of_mean, eps: float = EPSILON) -> float:
    """What a reference's own noise adds to a relMSE against it: the mean of
    its variance of the mean over (r² + ε), RGB channels."""
    r = np.asarray(r, np.float64)[..., :3]
    return float(np.mean(np.asarray(variance_of_mean, np.float64)[..., :3] / (r ** 2 + eps)))


def net_relmse(renders, r, variance_of_mean, eps: float = EPSILON) -> np.ndarray:
    """:func:`per_render_relmse` of each render less :func:`reference_relmse`:
    its error against the truth rather than against the reference's noise."""
    return per_render_relmse(renders, r, eps) - reference_relmse(r, variance_of_mean, eps)


def mape(x, r, eps: float = EPSILON) -> float:
    r = np.asarray(r, np.float64)
    return float(np.mean(np.abs(_finite(x) - r) / (np.abs(r) + eps)))


def relative_error_map(x, r, eps: float = EPSILON) -> np.ndarray:
    """(H, W) per-pixel MAPE: |x − r| / (|r| + ε), mean over RGB."""
    x, r = _finite(x)[..., :3], np.asarray(r, np.float64)[..., :3]
    return (np.abs(x - r) / (np.abs(r) + eps)).mean(axis=-1)


def nonfinite_fraction(x) -> float:
    x = np.asarray(x)
    return float(1.0 - np.isfinite(x).mean()) if x.size else 0.0


def bias(renders, r, reference_image_mean_se=0.0):
    """(bias, standard error) of the mean of ``renders`` (K, H, W, C) against r."""
    renders = _finite(renders)
    k = renders.shape[0]
    per_render = renders.mean(axis=(1, 2, 3)) - float(np.mean(r))
    se = np.sqrt(per_render.var(ddof=1) / k + float(reference_image_mean_se) ** 2) \
        if k > 1 else float("nan")
    return float(per_render.mean()), float(se)


def variance_per_render(renders) -> float:
    renders = _finite(renders)
    return float(renders.var(axis=0, ddof=1).mean()) if renders.shape[0] > 1 else float("nan")


def flip(x, r) -> tuple[np.ndarray, float] | None:
    """(H, W) HDR-FLIP map of ``x`` against ``r`` and its mean; None where FLIP
    is undefined (a black reference: no exposure range to tone-map over).
    Negative and non-finite values are clamped to 0 (FLIP takes radiance ≥ 0)."""
    ref = np.maximum(_finite(r)[..., :3], 0.0).astype(np.float32)
    test = np.maximum(_finite(x)[..., :3], 0.0).astype(np.float32)
    if not np.any(ref > 0):
        return None
    try:
        error, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(ref),
                                                 np.ascontiguousarray(test), "HDR",
                                                 applyMagma=False)
    except SystemExit:          # flip_evaluator exits on inputs it cannot handle
        return None
    return np.asarray(error, np.float32)[..., 0], float(mean)
