"""The moments of a launch's pixels (:class:`PixelMoments`) and what they
tell `guided_path`'s trainer: whether a learned density paid on its own
paths (:func:`measured_ratios`), and how much each training iteration's
image weighs in the result (:func:`inverse_variance_weights`)."""

from __future__ import annotations

import numpy as np


class PixelMoments:
    """Σ L and Σ L² per pixel of the paths' radiance in the training passes
    drawn with one density (:meth:`.records.Records.pixel_moments`), in two halves (a
    pixel's even and odd samples, so that one half can weigh the other
    without bias), and each half's samples per pixel."""

    def __init__(self):
        self.halves = [[None, None, 0], [None, None, 0]]

    def add(self, moments) -> None:
        """Add ``moments`` (as :meth:`.records.Records.pixel_moments` gives
        them; None: nothing)."""
        if moments is None:
            return
        for half, (first, second, n) in zip(self.halves, moments):
            if n:
                half[0] = first if half[0] is None else half[0] + first
                half[1] = second if half[1] is None else half[1] + second
                half[2] += n

    def mean_square(self, half=None) -> tuple:
        """(mean, mean of squares) per pixel of one half (0, 1) or of both;
        (None, None) where it holds no samples."""
        parts = [h for i, h in enumerate(self.halves) if h[2] and half in (None, i)]
        if not parts:
            return None, None
        n = sum(h[2] for h in parts)
        return sum(h[0] for h in parts) / n, sum(h[1] for h in parts) / n


#: Relative variance as relMSE weighs it: over (μ² + this) per pixel (tev's
#: convention, as validation/stats/metrics.py).
RELATIVE_EPSILON = 0.01


#: A guided pass whose pixels' mean (weighted as relMSE weighs them) is this
#: much above the unguided pass's found light the unguided paths missed:
#: their variance reads low, and the measured share is not trusted.
#: sunlit_room under its hole (sun 500), where guiding cut relMSE to 0.29×
#: at 64² × 1 024 spp, read 1.11 with a variance share of 1.16 in one of
#: three renders at 32² × 512 spp; the Cornell box, the sunrise and city
#: probes, phong_spheres and sun_sky, where guiding did not pay, read
#: 0.98-1.02 (docs/measurements.md#2026-12-06-guided-path-measures-whether-guide).
UNSEEN_ABOVE = 1.05


def measured_ratios(unguided: PixelMoments, guided: PixelMoments) -> tuple[float, float]:
    """(variance, mean): the relative variance of one sample of the pixels'
    estimate drawn with a learned density (``guided``) over that of BSDF
    sampling's (``unguided``), measured on the training passes' own paths,
    and the ratio of their means. Per pixel the variance is E[L²] − μ², μ²
    estimated without bias by the product of the two passes' means
    (independent samples of one pixel), weighted by 1/(μ̂² + ε) as relMSE
    weighs pixels, μ̂ the mean of the guided pass's other half (a weight
    drawn from the samples it weighs biased the variances by more than
    they are); both ways round, summed. What the whole path's estimate
    gains, direct light and path weights included, where
    :meth:`.guide.Guide.variance_ratio` predicts the indirect light's alone. A mean ratio
    above :data:`UNSEEN_ABOVE` says the unguided paths missed light (their
    variance reads low). (NaN, NaN) where either was not measured or the
    guided pass has one sample per pixel; inf where the unguided paths show
    no variance."""
    m_u, s_u = unguided.mean_square()
    if m_u is None or not all(h[2] for h in guided.halves):
        return float("nan"), float("nan")
    v_u = v_g = mean_u = mean_g = 0.0
    for weighs, weighed in ((0, 1), (1, 0)):
        m_w, _ = guided.mean_square(weighs)
        m_g, s_g = guided.mean_square(weighed)
        weight = 1.0 / (np.square(m_w) + RELATIVE_EPSILON)
        v_u += float(np.sum(weight * (s_u - m_u * m_g)))
        v_g += float(np.sum(weight * (s_g - m_u * m_g)))
        mean_u += float(np.sum(weight * m_u))
        mean_g += float(np.sum(weight * m_g))
    return (v_g / v_u if v_u > 0 else float("inf")), \
        (mean_g / mean_u if mean_u > 0 else float("inf"))


def relative_variances(moments: list[PixelMoments]) -> list[float]:
    """Per entry of ``moments`` (one per iteration, each drawn with its own
    density), the relative variance of one sample of its pixels' estimate:
    per pixel its samples' variance (n/(n − 1)·(E[L²] − m²); with one sample
    a pixel, E[L²] − m·m', m' the other entries' mean, independent of it),
    over (μ̂² + ε) as relMSE weighs pixels, averaged over the pixels. μ̂ is
    the mean of every entry's samples, the same for all: only the ratios of
    the variances weigh the images, and a noisy μ̂ scales them all alike
    (the other entries' mean alone, noisier for some entries than others,
    inflated those by up to 1.6× on 8 and 32 spp of relative variance 2).
    NaN for an entry without samples, or of one sample a pixel where no
    other entry has any."""
    parts = [m.mean_square() + (sum(h[2] for h in m.halves),) for m in moments]
    seen = [(m, n) for m, _, n in parts if m is not None]
    if not seen:
        return [float("nan")] * len(parts)
    weight = 1.0 / (np.square(sum(m * n for m, n in seen) / sum(n for _, n in seen))
                    + RELATIVE_EPSILON)
    out = []
    for k, (m_k, s_k, n_k) in enumerate(parts):
        others = [(m, n) for j, (m, _, n) in enumerate(parts) if j != k and m is not None]
        if m_k is None or (n_k < 2 and not others):
            out.append(float("nan"))
            continue
        if n_k >= 2:
            variance = (s_k - np.square(m_k)) * n_k / (n_k - 1)
        else:
            variance = s_k - m_k * sum(m * n for m, n in others) / sum(n for _, n in others)
        out.append(float(np.mean(weight * variance)))
    return out


#: Samples' worth of the pooled variance each iteration's own estimate is
#: shrunk towards: an estimate from few samples (a small film, an iteration
#: of 1 spp) is noisy, and a noisy weight both adds variance and, drawn
#: from the samples it weighs, favours images whose samples came out low.
#: On the Cornell box at 16² × 64 spp the unshrunk weights left 1.26× the
#: variance of the last pass alone; at 256² an iteration holds 65 536
#: samples per spp and its own estimate dominates.
SHRINK_SAMPLES = 1 << 16


def inverse_variance_weights(spp: list[int], variances: list[float],
                             samples: list[int] | None = None) -> list[float]:
    """Weights (summing to 1) of images of ``spp`` samples per pixel whose
    one sample has relative variance ``variances`` (estimated from
    ``samples`` samples each): ∝ spp / variance, the combination of least
    variance (Müller 2019, "Practical Path Guiding in Production"), each
    variance first shrunk towards their sample-weighted mean by
    :data:`SHRINK_SAMPLES`; ∝ spp (every sample alike) where a variance is
    not a positive number. Each weight is one number for a whole image, so
    that a pixel's weight hardly depends on its own samples and the
    combination of unbiased images stays unbiased but for that little."""
    v = np.asarray(variances, float)
    n = np.asarray(spp, float)
    if len(v) < 2 or not np.all(np.isfinite(v) & (v > 0)):
        return list(n / n.sum())
    count = np.asarray(samples if samples is not None else n, float)
    pooled = float(np.sum(count * v) / np.sum(count))
    v = (count * v + SHRINK_SAMPLES * pooled) / (count + SHRINK_SAMPLES)
    w = n / v
    return list(w / w.sum())
