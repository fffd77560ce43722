"""Bayesian Monte Carlo maths (integrators/quadrature/gp_quadrature.py): kernel means
against brute-force quadrature, exactness on the kernel, convergence on a
smooth function, the error factor and the amplitude divisor against sampled
Gaussian processes, conditioning, and the maximum-likelihood length scale."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import chi2

from mcillum.integrators.quadrature import gp_quadrature as gq
from mcillum.integrators.quadrature import gp_settings as gs


def product_grid(n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force rule for ∫_H f(ω) cos θ/π dω on the raw (θ, φ) integrand:
    Gauss–Legendre in θ ∈ [0, π/2] × the periodic midpoint rule in φ (both
    converge exponentially for smooth integrands). Directions (N, 3), weights."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    theta, w_theta = (x + 1) * np.pi / 4, w * np.pi / 4
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    wts = w_theta[:, None] * np.sin(t) * np.cos(t) / np.pi * (2 * np.pi / n_phi)
    return dirs.reshape(-1, 3), wts.ravel()


def brute_kernel_mean(mu: np.ndarray, length_scale: float) -> np.ndarray:
    """z̃(μ_j) by the 2-D rule on exp((ω·ω_j − 1)/ℓ²) cos θ/π, nodes at φ_j = 0.7."""
    grid, w = product_grid(200, 256)
    mu = np.asarray(mu, dtype=np.float64)
    s = np.sqrt(1 - mu ** 2)
    nodes = np.stack([s * np.cos(0.7), s * np.sin(0.7), mu], -1)
    return np.exp((nodes @ grid.T - 1) / length_scale ** 2) @ w


def nodes(n: int) -> np.ndarray:
    return gq.cosine_directions(*gq.fibonacci_square(n))


@pytest.mark.parametrize("length_scale", [0.05, 0.1, 0.4, 1.5])
def test_kernel_mean_matches_brute_force(length_scale):
    mu = np.array([0.05, 0.5, 1.0])
    # Both rules agree to ~1e-14 (the brute force changes by < 3e-14 at twice
    # the resolution); 1e-10 leaves room for round-off, not for a wrong formula.
    np.testing.assert_allclose(gq.kernel_mean(mu, length_scale),
                               brute_kernel_mean(mu, length_scale), rtol=1e-10)


@pytest.mark.parametrize("length_scale", [0.1, 0.4, 1.5])
def test_kernel_mean_mean_matches_brute_force(length_scale):
    # Ṽ = ∫ z̃(θ) 2 sin θ cos θ dθ with z̃ from the 2-D brute force: a 3-D rule
    # that never uses the Bessel form. Measured agreement ~2e-15.
    x, w = np.polynomial.legendre.leggauss(48)
    theta, w_theta = (x + 1) * np.pi / 4, w * np.pi / 4
    z = brute_kernel_mean(np.cos(theta), length_scale)
    brute = np.sum(z * 2 * np.sin(theta) * np.cos(theta) * w_theta)
    assert gq.kernel_mean_mean(length_scale) == pytest.approx(brute, rel=1e-10)


def test_fibonacci_cosine_directions():
    u, v = gq.fibonacci_square(5)
    np.testing.assert_allclose(u, [0.1, 0.3, 0.5, 0.7, 0.9])
    np.testing.assert_allclose(v, np.mod(np.arange(5) / gq.GOLDEN, 1))
    d = gq.cosine_directions(u, v)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, rtol=1e-14)
    np.testing.assert_allclose(d[:, 2], np.sqrt(1 - u), rtol=1e-14)
    np.testing.assert_allclose(np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi),
                               2 * np.pi * v, atol=1e-12)


@pytest.mark.parametrize("n", [16, 64])
def test_weights_integrate_the_kernel_exactly(n):
    length_scale = 0.3
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # well conditioned: no jitter
        w = gq.weights(n, length_scale, 1e-10, "zero")
    assert w.jitter == 0.0
    d = nodes(n)
    z = gq.kernel_mean(d[:, 2], length_scale)
    # Σ_j a_j k̃(ω_j, ω_i) = (K Q⁻¹ z)_i = z_i − 1e-10 (Q⁻¹z)_i: exact to ~1e-9.
    applied = gq.kernel_matrix(d, d, length_scale) @ w.weights
    np.testing.assert_allclose(applied[[0, n // 3, n - 1]], z[[0, n // 3, n - 1]],
                               rtol=1e-6)
    c = gq.weights(n, length_scale, 1e-10, "constant")
    assert c.weights.sum() == pytest.approx(1.0, abs=1e-12)     # constants exact
    assert abs(w.weights.sum() - 1.0) > 1e-6    # ... which "zero" alone is not
    assert not c.weights.flags.writeable


def test_smooth_function_converges_far_faster_than_qmc():
    d0 = 1.5 * np.array([0.6, -0.3, 0.5]) / np.linalg.norm([0.6, -0.3, 0.5])
    f = lambda x: np.exp(x @ d0)                                 # noqa: E731
    grid, gw = product_grid(200, 256)
    exact = gw @ f(grid)             # changes by 5e-14 at twice the resolution
    err = {n: abs(gq.weights(n, 0.5, 1e-6).weights @ f(nodes(n)) - exact)
           for n in (16, 64, 256)}
    # Measured: 9.3e-3, 1.9e-3, 4.2e-5; randomly shifted lattice + plain mean
    # at n = 64: rms 2.1e-2. Bounds are the measurements × ~2.5.
    assert err[16] > err[64] > err[256]
    assert err[64] < 5e-3 and err[256] < 1e-4


def test_error_factor_decreases_and_matches_sampled_paths():
    factors = [gq.weights(n, 0.5, 1e-6).error_factor for n in (16, 64, 256)]
    assert factors[0] > factors[1] > factors[2] >= 0      # 9.4e-4, 4.1e-6, 8.4e-9

    n, ell, noise, sigma2, draws = 16, 0.5, 1e-6, 2.0, 2000
    w = gq.weights(n, ell, noise)
    grid, gw = product_grid(12, 24)
    x = np.vstack([nodes(n), grid])
    cov = gq.kernel_matrix(x, x, ell)
    cov[:n, :n] += noise * np.eye(n)
    # The grid's own quadrature error is negligible: the exact variance of
    # Σa_jY_j − Σb_gY_g equals c to 1e-10 relative (measured 2e-14).
    coef = np.concatenate([w.weights, -gw])
    assert coef @ cov @ coef == pytest.approx(w.error_factor, rel=1e-10)
    vals, vecs = np.linalg.eigh(cov)
    root = vecs * np.sqrt(np.clip(vals, 0, None))
    rng = np.random.default_rng(5)
    # A constant mean 3 that the "constant" weights must cancel.
    y = 3.0 + np.sqrt(sigma2) * rng.standard_normal((draws, len(x))) @ root.T
    err = y[:, :n] @ w.weights - y[:, n:] @ gw
    ratio = np.mean(err ** 2) / (sigma2 * w.error_factor)
    # err/√(σ²c) ~ N(0,1), so draws·ratio ~ χ²(draws); two-sided α = 1e-3
    # gives [0.899, 1.107]. Measured 1.017 (1.01, 1.04, 0.99, 1.00 on other seeds).
    lo, hi = chi2.ppf([0.0005, 0.9995], draws) / draws
    assert lo < ratio < hi


@pytest.mark.parametrize("prior_mean", ["constant", "zero"])
def test_amplitude_divisor_is_unbiased(prior_mean):
    n, ell, noise, sigma2, draws = 64, 0.5, 1e-2, 4.0, 4000
    w = gq.weights(n, ell, noise, prior_mean)
    q = gq.kernel_matrix(nodes(n), nodes(n), ell) + noise * np.eye(n)
    centre = np.eye(n) - (1 / n if prior_mean == "constant" else 0)
    rng = np.random.default_rng(3)
    y = ((5.0 if prior_mean == "constant" else 0.0)
         + np.sqrt(sigma2) * rng.standard_normal((draws, n)) @ np.linalg.cholesky(q).T)
    est = np.sum((y @ centre) ** 2, axis=1) / w.amplitude_divisor
    # Var(YᵀCY) = 2σ⁴ tr((CQ)²) exactly; 4 standard errors (≈0.13) of the mean.
    # Measured means 4.001 and 4.021; a divisor off by 5 % would move it by 0.2.
    se = np.sqrt(2 * np.trace(centre @ q @ centre @ q) / draws) * sigma2 / w.amplitude_divisor
    assert abs(est.mean() - sigma2) < 4 * se


def test_ill_conditioned_setting_gets_jitter_and_warns():
    with pytest.warns(RuntimeWarning, match=r"condition number .* raise `noise`"):
        w = gq.weights.__wrapped__(256, 3.0, 0.0)          # past the cache
    assert w.jitter > 0 and w.condition <= gq.MAX_CONDITION
    assert w.noise == 0.0 and w.error_factor >= 0
    assert w.weights.sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("args, match", [
    ((0, 0.3, 1e-6), "integer >= 1"), ((2.5, 0.3, 1e-6), "integer >= 1"),
    ((True, 0.3, 1e-6), "integer >= 1"), ((16, 0.0, 1e-6), "length_scale"),
    ((16, float("nan"), 1e-6), "length_scale"), ((16, 0.3, -1e-6), "noise"),
    ((16, 0.3, 1e-6, "mean"), "prior_mean"),
])
def test_bad_inputs_raise(args, match):
    with pytest.raises(ValueError, match=match):
        gq.weights(*args)


def gp_on_sphere(length_scale: float, m: int = 120, seed: int = 0):
    """GP values (σ² = 2, mean 1, noise 1e-3) at m uniform sphere directions.
    m = 120, not 400: a fit factors ~50 m×m matrices, and OpenBLAS, threaded
    above m ≈ 125, takes ~0.25 s per factor (not 1 ms) on a loaded 2-core
    machine; m = 120 stays single-threaded and still pins ℓ to ~10 %."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((m, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    chol = np.linalg.cholesky(gq.kernel_matrix(x, x, length_scale) + 1e-3 * np.eye(m))
    return x, 1.0 + np.sqrt(2.0) * chol @ rng.standard_normal(m)


def test_fit_recovers_the_length_scale():
    # Seeds 0-11 give ℓ in [0.27, 0.34] and σ̂² in [1.58, 3.10] (seed 0: 0.337, 3.10).
    fitted = gq.fit(*gp_on_sphere(0.3))
    assert 0.3 / 1.5 < fitted.length_scale < 0.3 * 1.5
    assert 1.0 < fitted.variance < 4.0
    # Negative control: data with ℓ = 1 fit ℓ ≈ 1 (0.96-1.11 over seeds 0-11).
    other = gq.fit(*gp_on_sphere(1.0))
    assert not 0.3 / 1.5 < other.length_scale < 0.3 * 1.5


def test_fit_of_constant_values_has_no_information():
    x, _ = gp_on_sphere(0.3)
    for y in (np.full(len(x), 2.5), np.zeros(len(x))):
        fitted = gq.fit(x, y)
        assert fitted.length_scale == fitted.grid.max() and fitted.variance == 0.0
        assert gq.log_marginal_likelihood(x, y, 0.3, 1e-3) == (-np.inf, 0.0)


# ------------------ Hyperparameters chosen for the quadrature ------------------

def _held_out(f, n: int, mapping: str, sets: int = 1, turns: int = 8, m: int = 24):
    """Node values of f at held_out_directions about m normals, and the
    integrals of f about them by the brute-force rule."""
    normals = gs.sphere_directions(m)
    grid, w = product_grid(64, 96)
    s, t = gs.tangent_frames(normals)
    truth = np.array([w @ f(grid[:, :1] * s[i] + grid[:, 1:2] * t[i] + grid[:, 2:] * normals[i])
                      for i in range(m)])
    world = gs.held_out_directions(normals, n, mapping, sets, turns)
    return f(world.reshape(-1, 3)).reshape(world.shape[:-1]), truth


def test_held_out_directions_are_the_sets_turned_about_each_normal():
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, -0.8]])
    world = gs.held_out_directions(normals, 16, "cosine", sets=4, turns=2)
    assert world.shape == (2, 8, 16, 3)
    np.testing.assert_allclose(np.linalg.norm(world, axis=-1), 1, rtol=1e-12)
    # cos θ about the normal is the shifted set's: sample k uses set k mod 4
    for k in range(8):
        u, _ = gq.fibonacci_square(16, gq.set_shift(k % 4, 4, 16))
        for i in range(2):
            np.testing.assert_allclose(world[i, k] @ normals[i], np.sqrt(1 - u), atol=1e-12)


def test_choose_interpolates_a_smooth_map_and_averages_white_noise():
    """The rule reads the data: on a smooth map it picks an interpolating GP
    whose held-out error is far below equal weights' (measured: 2.0e-5 vs
    2.8e-4 at N = 16, 4 spp); on values that are white noise about a constant (what
    no kernel predicts) it picks the safe, nearly equal weights (the least
    Σa², hence the least error)."""
    d0 = np.array([0.6, -0.3, 0.5]) / np.linalg.norm([0.6, -0.3, 0.5])
    f = lambda x: np.exp(1.5 * x @ d0)                           # noqa: E731
    values, truth = _held_out(f, 16, "cosine")
    smooth = gs.choose({"cosine": values}, truth, 16, spp=4)
    assert smooth.noise < max(gs.NOISES)
    equal = gs.held_out_relmse(values, truth, np.full(16, 1 / 16), spp=4)
    assert smooth.relmse < equal / 5, (smooth.relmse, equal)
    assert min(c.length_scale for c in smooth.candidates) >= gs.length_scale_floor(16)

    rng = np.random.default_rng(3)
    noisy = 1 + 0.5 * rng.standard_normal(values.shape)
    white = gs.choose({"cosine": noisy}, np.ones(len(truth)), 16, spp=4)
    assert white.noise == max(gs.NOISES), white


def test_a_candidate_must_beat_the_safe_one_by_more_than_its_noise():
    """With one normal's error per candidate there is no spread to judge by:
    the safe candidate stays; a consistent gain over many normals wins."""
    d0 = np.array([0.0, 0.0, 1.0])
    f = lambda x: np.exp(2.0 * x @ d0)                           # noqa: E731
    values, truth = _held_out(f, 16, "cosine", m=24)
    many = gs.choose({"cosine": values}, truth, 16, spp=16)
    assert many.noise < max(gs.NOISES)
    one = gs.choose({"cosine": values[:1]}, truth[:1], 16, spp=16)
    assert (one.noise, one.length_scale) == (max(gs.NOISES), gs.LENGTH_SCALES.max())


def test_pixel_error_counts_a_fixed_sets_bias_at_every_spp():
    """A set that errs the same way at every turn keeps its error as spp
    grows; one whose errors cancel over the turns loses it."""
    truth = np.ones(3)
    biased = np.ones((3, 8, 4)) * 1.1                              # +10 % at every turn
    cancelling = np.ones((3, 8, 4)) + 0.1 * np.where(np.arange(8) % 2, 1, -1)[None, :, None]
    a = np.full(4, 0.25)
    for spp in (1, 256):
        assert gs.held_out_relmse(biased, truth, a, spp) == pytest.approx(0.01)
    assert gs.held_out_relmse(cancelling, truth, a, 1) == pytest.approx(0.01)
    assert gs.held_out_relmse(cancelling, truth, a, 256) == pytest.approx(0.01 / 256)


# --------------------------- The Phong lobe's measure ---------------------------

def brute_lobe_kernel_mean(mu: np.ndarray, length_scale: float, exponent: float) -> np.ndarray:
    """z̃(μ_j) against (n + 1)/(2π) cosⁿ θ by a 2-D Gauss–Legendre × uniform-φ
    rule over θ ∈ [0, min(π/2, 10/√(n+1))] (no Bessel form), nodes at φ_j = 0.7."""
    top = min(np.pi / 2, 10 / np.sqrt(exponent + 1))
    x, w = np.polynomial.legendre.leggauss(400)
    theta, w_theta = (x + 1) * top / 2, w * top / 2
    phi = (np.arange(512) + 0.5) * 2 * np.pi / 512
    t, p = np.meshgrid(theta, phi, indexing="ij")
    grid = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    wts = (w_theta[:, None] * np.sin(t) * (exponent + 1) / (2 * np.pi) * np.cos(t) ** exponent
           * (2 * np.pi / 512)).ravel()
    mu = np.asarray(mu, dtype=np.float64)
    s = np.sqrt(1 - mu ** 2)
    at = np.stack([s * np.cos(0.7), s * np.sin(0.7), mu], -1)
    return np.exp((at @ grid.T - 1) / length_scale ** 2) @ wts


@pytest.mark.parametrize("exponent, length_scale", [(10.0, 0.3), (100.0, 0.1), (1024.0, 0.03)])
def test_lobe_kernel_mean_matches_brute_force(exponent, length_scale):
    """The glossy set's kernel mean: the Bessel form over the lobe's own
    θ rule against a 2-D rule (measured agreement < 1e-13)."""
    mu = np.cos(np.array([0.0, 0.3, 1.5]) / np.sqrt(exponent + 1))
    np.testing.assert_allclose(gq.kernel_mean(mu, length_scale, exponent),
                               brute_lobe_kernel_mean(mu, length_scale, exponent), rtol=1e-9)


def test_lobe_exponent_one_is_the_cosine_measure():
    """n = 1 is cos θ/π: the same kernel mean and weights as the cosine case."""
    mu = np.array([0.1, 0.6, 0.99])
    np.testing.assert_array_equal(gq.kernel_mean(mu, 0.4, 1.0), gq.kernel_mean(mu, 0.4))
    assert gq.kernel_mean_mean(0.4, 1.0) == gq.kernel_mean_mean(0.4)


def test_lobe_nodes_follow_the_lobe():
    """cos α = u^{1/(n+1)}: the nodes' mean of cos α is (n + 1)/(n + 2), the
    lobe's (midpoint rule in u: u^{1/31} is steep at 0)."""
    d = gq.lobe_directions(*gq.fibonacci_square(4096), 30.0)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, rtol=1e-14)
    assert d[:, 2].mean() == pytest.approx(31 / 32, rel=1e-4)


@pytest.mark.parametrize("sharpness", [4.0, 32.0])
@pytest.mark.parametrize("n", [8, 32])
def test_lobe_weights_beat_equal_weights_on_smooth_light(sharpness, n):
    """Spherical-Gaussian light of sharpness 4 and 32 whose axis lies within
    0.4 rad of a cos³⁰ lobe's, integrated against the lobe by the glossy
    set's weights (ℓ = 1 lobe width, σ_n²/σ² = 1e-3, 16 shifted sets × 8
    turns): squared error below 0.75× that of equal weights on the same
    nodes. Measured: 0.57 and 0.37 (sharpness 4, N = 8 and 32), 0.48 and
    0.22 (sharpness 32)."""
    exponent, ell = 30.0, np.sqrt(2 / 31)
    rng = np.random.default_rng(0)
    bmc, equal = [], []
    for _ in range(12):
        a, phi = 0.4 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        axis = np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
        u, v = gq.fibonacci_square(1 << 16, 0.0)
        truth = np.mean(np.exp(sharpness * (gq.lobe_directions(
            np.mod(u + 0.37, 1), np.mod(v + 0.11, 1), exponent) @ axis - 1)))
        for s in range(16):
            shift = gq.set_shift(s, 16, n)
            w = gq.weights(n, ell, 1e-3, "constant", "lobe", shift, exponent).weights
            u, v = gq.fibonacci_square(n, shift)
            for turn in np.arange(8) / 8:
                y = np.exp(sharpness * (gq.lobe_directions(u, np.mod(v + turn, 1), exponent)
                                        @ axis - 1))
                bmc.append((w @ y / truth - 1) ** 2)
                equal.append((y.mean() / truth - 1) ** 2)
    assert np.mean(bmc) < 0.75 * np.mean(equal), (np.mean(bmc), np.mean(equal))
