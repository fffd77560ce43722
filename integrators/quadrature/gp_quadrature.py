r"""Bayesian Monte Carlo (Gaussian-process quadrature) on the cosine-weighted
hemisphere: variant-free float64 maths (numpy + scipy, no Mitsuba).

Model. The incident radiance Y(ω) on the upper hemisphere H (local frame,
normal +z) is a Gaussian process with covariance σ²·k̃ and the spherical
Gaussian kernel of unit amplitude

    k̃(ω, ω′) = exp((ω·ω′ − 1) / ℓ²) = exp(−λ ‖ω − ω′‖² / 2),   λ = 1/ℓ².

The target is I = ∫_H Y(ω) p(ω) dω with p(ω) = cos θ / π (∫ p = 1). The n
samples Y_j = Y(ω_j) + ε_j carry noise of variance σ²·s (s = ``noise``,
relative to σ²), so Q̃ = K̃ + s·I, K̃_ij = k̃(ω_i, ω_j), and σ² cancels from
the weights. With the kernel mean z̃_j = ∫ k̃(ω, ω_j) p(ω) dω and its mean
Ṽ = ∫∫ k̃ p p, the posterior mean of I is Σ_j a_j Y_j:

* zero prior mean:            a = w = Q̃⁻¹ z̃;
* prior mean = sample mean Ȳ: a = w + (1 − Σw)/n · 1, so Σa = 1 = ∫p.

The error variance of Σ a_j Y_j is σ²·c, c = aᵀQ̃a − 2aᵀz̃ + Ṽ (with Σa = 1 an
unknown constant mean cancels). σ² is estimated per shading point from the
samples by moments: E[Σ(Y_j − Ȳ)²] = σ²·(tr Q̃ − 1ᵀQ̃1/n), E[ΣY_j²] = σ²·tr Q̃.

Kernel mean. With cos θ = μ, sin θ = √(1−μ²) and ω·ω_j = cos θ cos θ_j +
sin θ sin θ_j cos(φ − φ_j), integrating over φ gives 2π I₀(λ sin θ sin θ_j):

    z̃(θ_j) = 2 ∫₀^{π/2} e^{λ(cos(θ−θ_j) − 1)} ive₀(λ sin θ sin θ_j) sin θ cos θ dθ

(ive₀(x) = e^{−x} I₀(x); the exponent is ≤ 0, so it is stable). The integral
runs over θ rather than μ (the same integral with μ = cos θ) because the
integrand's width is ≈ ℓ in θ everywhere, while in μ it shrinks to ℓ² at the
pole; composite Gauss–Legendre with panels about as wide as the smallest ℓ is
accurate to ~1e-14 relative for ℓ ≥ 0.02. Ṽ = ∫₀^{π/2} z̃(θ) 2 sin θ cos θ dθ.

Glossy lobes. The same model integrates against a Phong lobe about an axis
(the mirror direction), p_n(ω) = (n + 1)/(2π) cosⁿ α, with θ now the angle
to the axis and the weight 2 sin θ cos θ replaced by (n + 1) cosⁿ θ sin θ
(n = 1 is the cosine case). The rule then spans θ ∈ [0, min(π/2, 8/√(n+1))]:
beyond it cosⁿ θ < e⁻³² of its peak, and its panels narrow with the lobe.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.interpolate
import scipy.linalg
import scipy.optimize
from scipy.special import ive

GOLDEN = (1 + 5 ** 0.5) / 2
#: Largest 2-norm condition number of Q̃ solved without extra jitter.
MAX_CONDITION = 1e10
PRIOR_MEANS = ("constant", "zero")

# Composite Gauss–Legendre over θ ∈ [0, π/2]: 32 panels (width 0.049 rad) of
# 12 nodes; against adaptive quadrature z̃ and Ṽ agree to < 1e-14 relative for
# every ℓ in [0.02, 3] (24 panels still do; 32 keep a margin).
_PANELS, _ORDER = 32, 12


def _theta_rule(top: float = np.pi / 2) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(_ORDER)
    edges = np.linspace(0.0, top, _PANELS + 1)
    half = np.diff(edges)[:, None] / 2
    nodes = (edges[:-1, None] + half * (x + 1)).ravel()
    return nodes, (half * w).ravel()


_THETA, _THETA_W = _theta_rule()


@functools.lru_cache(maxsize=64)
def _lobe_rule(exponent: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(θ nodes, quadrature weights, the lobe's weight (n + 1) cosⁿ θ sin θ at
    the nodes) for the Phong lobe of ``exponent`` n; n = 1 is the cosine
    rule, 2 sin θ cos θ over [0, π/2]."""
    if exponent == 1.0:
        t, w = _THETA, _THETA_W
        return t, w, 2.0 * np.sin(t) * np.cos(t)
    t, w = _theta_rule(min(np.pi / 2, 8.0 / np.sqrt(exponent + 1.0)))
    return t, w, (exponent + 1.0) * np.cos(t) ** exponent * np.sin(t)


def fibonacci_square(n: int, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The Fibonacci lattice on [0,1)², u shifted: u_j = frac((j + ½)/n + shift),
    v_j = frac(j/Φ)."""
    j = np.arange(n, dtype=np.float64)
    return np.mod((j + 0.5) / n + shift, 1.0), np.mod(j / GOLDEN, 1.0)


def set_shift(s: int, sets: int, n: int) -> float:
    """The u shift of set s of ``sets``: ((s + ½)/sets − ½)/n, the sets'
    nodes evenly between the unshifted set's neighbours (0 for one set)."""
    return ((s + 0.5) / sets - 0.5) / n


def cosine_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Malley's map to the cosine-weighted hemisphere, (n, 3):
    cos θ = √(1 − u), φ = 2π v."""
    cos_t = np.sqrt(1.0 - np.asarray(u, dtype=np.float64))
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    phi = 2 * np.pi * np.asarray(v, dtype=np.float64)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def kernel_matrix(x: np.ndarray, y: np.ndarray, length_scale: float) -> np.ndarray:
    """k̃(x_i, y_j) = exp(−‖x_i − y_j‖² / (2ℓ²)) for unit rows of x and y
    (= exp((x_i·y_j − 1)/ℓ²) without the cancellation near the peak)."""
    d2 = np.sum((np.asarray(x)[:, None, :] - np.asarray(y)[None, :, :]) ** 2, axis=-1)
    return np.exp(-0.5 * d2 / length_scale ** 2)


def kernel_mean(mu: np.ndarray, length_scale: float, exponent: float = 1.0) -> np.ndarray:
    """z̃(μ_j) = ∫ k̃(ω, ω_j) p(ω) dω for nodes with cos θ_j = μ_j, θ measured
    from the pole of p: cos θ/π on the hemisphere (``exponent`` 1), or the
    Phong lobe (n + 1)/(2π) cosⁿ θ of that exponent."""
    lam = 1.0 / length_scale ** 2
    mu = np.clip(np.asarray(mu, dtype=np.float64), -1.0, 1.0)
    theta_j = np.arctan2(np.sqrt(1.0 - mu ** 2), mu)[..., None]
    t, w, lobe = _lobe_rule(float(exponent))
    # cos(θ − θ_j) − 1 = −2 sin²((θ − θ_j)/2), exact near the peak.
    expo = -2.0 * lam * np.sin((t - theta_j) / 2) ** 2
    f = np.exp(expo) * ive(0, lam * np.sin(t) * np.sin(theta_j)) * lobe
    return f @ w


@functools.lru_cache(maxsize=256)
def kernel_mean_mean(length_scale: float, exponent: float = 1.0) -> float:
    """Ṽ = ∫∫ k̃(ω, ω′) p(ω) p(ω′) dω dω′, p as in :func:`kernel_mean` (cached
    per ℓ and exponent: 384 kernel means, ~0.1 s)."""
    t, w, lobe = _lobe_rule(float(exponent))
    return float(np.sum(kernel_mean(np.cos(t), length_scale, exponent) * lobe * w))


@dataclass(frozen=True)
class Weights:
    """BMC weights for n Fibonacci cosine directions (arrays read-only).

    ``weights``: a_j, the estimate is Σ a_j Y_j. ``error_factor``: its error
    variance per unit σ² (with the requested noise). ``amplitude_divisor``: D
    of σ̂² = Σ(Y_j − Ȳ)²/D ("constant") or ΣY_j²/D ("zero"). ``condition``:
    cond₂ of the Q̃ solved; ``jitter``: noise added beyond ``noise`` for it.
    """

    n: int
    length_scale: float
    noise: float
    prior_mean: str
    weights: np.ndarray
    error_factor: float
    amplitude_divisor: float
    condition: float
    jitter: float


def _check(n: int, length_scale: float, noise: float, prior_mean: str) -> None:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"bayesian_hemisphere: the number of directions must be an "
                         f"integer >= 1, got {n!r}")
    if not (np.isfinite(length_scale) and length_scale > 0):
        raise ValueError(f"bayesian_hemisphere: `length_scale` must be a finite number "
                         f"> 0 (radians, e.g. 0.3), got {length_scale!r}")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"bayesian_hemisphere: `noise` (σ_n²/σ²) must be a finite "
                         f"number >= 0 (e.g. 1e-6), got {noise!r}")
    if prior_mean not in PRIOR_MEANS:
        raise ValueError(f"bayesian_hemisphere: `prior_mean` must be one of "
                         f"{PRIOR_MEANS}, got {prior_mean!r}")


def uniform_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The area-preserving map to the hemisphere, (n, 3): cos θ = 1 − u, φ = 2π v."""
    cos_t = 1.0 - np.asarray(u, dtype=np.float64)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    phi = 2 * np.pi * np.asarray(v, dtype=np.float64)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


#: How the Fibonacci square is mapped to the nodes (the measure stays cos θ/π).
MAPPINGS = {"cosine": cosine_directions, "uniform": uniform_directions}


def lobe_directions(u: np.ndarray, v: np.ndarray, exponent: float) -> np.ndarray:
    """The Phong lobe's map about +z (the lobe's axis), (n, 3): cos α =
    u^{1/(n+1)}, φ = 2π v, density (n + 1)/(2π) cosⁿ α."""
    cos_t = np.asarray(u, dtype=np.float64) ** (1.0 / (exponent + 1.0))
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    phi = 2 * np.pi * np.asarray(v, dtype=np.float64)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


#: Chebyshev points in θ of the kernel-mean interpolant (for ℓ ≥ INTERPOLATED:
#: 1e-12 relative against kernel_mean there).
_CHEBYSHEV = 257
INTERPOLATED = 0.05


@functools.lru_cache(maxsize=64)
def _kernel_mean_interpolant(length_scale: float):
    """z̃ as a function of θ_j ∈ [0, π/2], interpolated from its values at
    Chebyshev points (one set of Bessel-form integrals per ℓ, shared by
    every N, mapping and set shift)."""
    theta = np.pi / 4 * (1 - np.cos(np.pi * np.arange(_CHEBYSHEV) / (_CHEBYSHEV - 1)))
    return scipy.interpolate.BarycentricInterpolator(theta, kernel_mean(np.cos(theta),
                                                                        length_scale))


@functools.lru_cache(maxsize=4096)
def _node_terms(n: int, length_scale: float, mapping: str, shift: float,
                exponent: float = 1.0):
    """(K̃, its eigenvalues and eigenvectors, z̃) of the nodes: what the
    weights of every noise share (one eigendecomposition solves K̃ + t·I
    for every t)."""
    if mapping == "lobe":
        dirs = lobe_directions(*fibonacci_square(n, shift), exponent)
    else:
        dirs = MAPPINGS[mapping](*fibonacci_square(n, shift))
    K = kernel_matrix(dirs, dirs, length_scale)
    mu = np.clip(dirs[:, 2], -1.0, 1.0)
    if mapping == "lobe":
        z = kernel_mean(mu, length_scale, exponent)
    elif length_scale >= INTERPOLATED:
        z = _kernel_mean_interpolant(length_scale)(np.arctan2(np.sqrt(1.0 - mu ** 2), mu))
    else:
        z = kernel_mean(mu, length_scale)
    eig, vectors = np.linalg.eigh(K)
    return K, (eig, vectors), z


@functools.lru_cache(maxsize=4096)
def weights(n: int, length_scale: float, noise: float,
            prior_mean: str = "constant", mapping: str = "cosine",
            shift: float = 0.0, exponent: float = 1.0) -> Weights:
    """BMC weights for the nodes ``MAPPINGS[mapping](*fibonacci_square(n, shift))``
    (the integral is against p = cos θ/π), or, for ``mapping`` "lobe", the
    nodes ``lobe_directions(*fibonacci_square(n, shift), exponent)`` and the
    integral against the lobe (n + 1)/(2π) cosⁿ α.

    If cond₂(K̃ + noise·I) > MAX_CONDITION the noise of the solve is raised
    tenfold (from max(noise, 1e-12)) until it is not, with a warning; the
    error factor and the amplitude divisor keep the requested noise. Cached,
    so the warning comes once per setting and process.
    """
    _check(n, length_scale, noise, prior_mean)
    n, length_scale, noise = int(n), float(length_scale), float(noise)
    if mapping not in MAPPINGS and mapping != "lobe":
        raise ValueError(f"bayesian_hemisphere: mapping must be one of {', '.join(MAPPINGS)}, "
                         f"got {mapping!r}")
    if not (np.isfinite(exponent) and exponent > 0):
        raise ValueError(f"bayesian_hemisphere: the lobe's exponent must be a finite number "
                         f"> 0, got {exponent!r}")
    exponent = float(exponent) if mapping == "lobe" else 1.0
    K, (eig, vectors), z = _node_terms(n, length_scale, mapping, shift, exponent)

    def cond(t: float) -> float:
        return float((eig[-1] + t) / (eig[0] + t)) if eig[0] + t > 0 else np.inf

    total = noise
    if cond(total) > MAX_CONDITION:
        total = max(noise, 1e-12)
        while cond(total) > MAX_CONDITION and total < 1e6:
            total *= 10
        shown = f"{cond(noise):.3g}" if np.isfinite(cond(noise)) else "inf (singular)"
        warnings.warn(
            f"bayesian_hemisphere: Q = K + σ_n² I for N = {n}, ℓ = {length_scale:g} has "
            f"condition number {shown} (> {MAX_CONDITION:g}): added "
            f"{total - noise:.3g} to the noise; raise `noise` or lower "
            f"`length_scale`/`directions`", RuntimeWarning, stacklevel=2)
    if not eig[0] + total > 0:
        raise ValueError(
            f"bayesian_hemisphere: Q = K + σ_n² I is not positive definite for N = {n}, "
            f"ℓ = {length_scale:g}, noise = {total:g}; raise `noise` or lower "
            f"`length_scale`/`directions`")
    # Q⁻¹z = V (Λ + t)⁻¹ Vᵀ z
    w = vectors @ ((vectors.T @ z) / (eig + total))
    a = w + (1.0 - w.sum()) / n if prior_mean == "constant" else w
    Q = K + noise * np.eye(n)
    c = float(a @ Q @ a - 2 * a @ z + kernel_mean_mean(length_scale, exponent))
    if c < -1e-9:
        raise ValueError(f"bayesian_hemisphere: negative error factor {c:.3g} for "
                         f"N = {n}, ℓ = {length_scale:g}: raise `noise`")
    divisor = float(np.trace(Q) - (Q.sum() / n if prior_mean == "constant" else 0.0))
    a.setflags(write=False)
    return Weights(n, length_scale, noise, prior_mean, a, max(c, 0.0), divisor,
                   cond(total), total - noise)


def log_marginal_likelihood(directions: np.ndarray, values: np.ndarray,
                            length_scale: float, noise: float) -> tuple[float, float]:
    """Profiled log-likelihood of y ~ N(m·1, σ²(K̃ + noise·I)) at unit
    ``directions`` (M, 3) anywhere on the sphere, and σ̂².

    m̂ = 1ᵀQ̃⁻¹y / 1ᵀQ̃⁻¹1 (GLS), σ̂² = rᵀQ̃⁻¹r / M with r = y − m̂, and
    log L = −½ (M log(2π σ̂²) + log det Q̃ + M). Values that are constant (to
    1e-12 relative) carry no information about ℓ: the likelihood is then
    unbounded as σ² → 0 for every ℓ, and (−inf, 0.0) is returned.
    """
    x = np.asarray(directions, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or y.shape != (x.shape[0],) or x.shape[0] < 2:
        raise ValueError(f"directions must be (M, 3) and values (M,) with M >= 2, got "
                         f"{x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("directions and values must be finite")
    m = x.shape[0]
    try:
        factor = scipy.linalg.cho_factor(kernel_matrix(x, x, length_scale) + noise * np.eye(m))
    except np.linalg.LinAlgError as err:
        raise ValueError(f"Q = K + noise·I is singular for M = {m}, ℓ = {length_scale:g}, "
                         f"noise = {noise:g}: raise `noise`") from err
    qi_1 = scipy.linalg.cho_solve(factor, np.ones(m))
    r = y - (qi_1 @ y) / qi_1.sum()
    var = float(r @ scipy.linalg.cho_solve(factor, r)) / m
    if var <= (1e-12 * np.max(np.abs(y))) ** 2:
        return -np.inf, 0.0
    logdet = 2.0 * np.sum(np.log(np.diag(factor[0])))
    return float(-0.5 * (m * np.log(2 * np.pi * var) + logdet + m)), var


@dataclass(frozen=True)
class Fit:
    """Maximum-likelihood ℓ, its σ̂², and the grid scanned with its log L."""

    length_scale: float
    variance: float
    grid: np.ndarray
    loglik: np.ndarray


def fit(directions: np.ndarray, values: np.ndarray, noise: float = 1e-3,
        grid: np.ndarray | None = None) -> Fit:
    """Type-II maximum likelihood ℓ over ``grid`` (default geomspace(0.05, 2, 40)),
    refined by a bounded search in log ℓ between the argmax's grid neighbours.
    Constant (or all-zero) values carry no information: the largest grid ℓ and
    variance 0.0 are returned."""
    g = np.array(np.geomspace(0.05, 2.0, 40) if grid is None else grid, dtype=np.float64)
    ll = np.array([log_marginal_likelihood(directions, values, s, noise)[0] for s in g])
    g.setflags(write=False)
    ll.setflags(write=False)
    if not np.any(np.isfinite(ll)):
        return Fit(float(g.max()), 0.0, g, ll)
    i = int(np.argmax(ll))
    best = float(g[i])
    lo, hi = g[max(i - 1, 0)], g[min(i + 1, len(g) - 1)]
    if hi > lo:
        res = scipy.optimize.minimize_scalar(
            lambda t: -log_marginal_likelihood(directions, values, np.exp(t), noise)[0],
            bounds=(np.log(lo), np.log(hi)), method="bounded",
            options={"xatol": 1e-4})
        if res.success and -res.fun > ll[i]:
            best = float(np.exp(res.x))
    return Fit(best, log_marginal_likelihood(directions, values, best, noise)[1], g, ll)


def pixel_std(posterior_var: np.ndarray, sample_sq: np.ndarray | None, mean: np.ndarray,
              spp: int) -> np.ndarray:
    """A pixel's error bar from the film means of a render of ``spp`` camera
    samples: √(posterior_var + s²/spp), s² = spp/(spp − 1)·(mean L² − (mean L)²)
    the spread of its samples (the part that averages down; the posterior
    variance, shared by samples that integrate nearly the same lighting,
    does not). ``mean`` is the radiance (H, W, C); a one-channel
    ``sample_sq`` (mono, spectral) is compared with its channel mean."""
    var = np.maximum(posterior_var, 0)
    if sample_sq is None or spp < 2:
        return np.sqrt(var)
    mean = mean[..., :3] if sample_sq.shape[-1] == 3 else \
        mean[..., :3].mean(axis=-1, keepdims=True)
    spread = sample_sq - np.square(mean)
    # (a spread below 1e-5 of the mean square is float32 cancellation)
    spread = np.where(spread > 1e-5 * sample_sq, spread, 0) * spp / (spp - 1)
    return np.sqrt(var + spread / spp)
