"""Each estimator agrees with Mitsuba's `path` at the same max_depth.

Test: validation.statistics.compare — per-pixel Welch t-tests with each side's
variance taken from its own independent renders (batch means), Šidák-corrected
over pixels, plus a pooled image-mean test; family-wise α = 0.01 per
comparison. Seeds are fixed, so outcomes are reproducible. The same test must
reject a known-biased answer: `path` at another max_depth, and an estimator
whose pdf is off by 5%.

Budgets: the per-render variance is only evidence when every render of every
pixel sees the rare events that carry the signal. In the Cornell box a corner
pixel's hemisphere estimate finds the small light with probability ~0.3% per
sample; at 16² px × 256 spp × 16 renders some pixels had *no* hit in all 16
renders (zero sample variance, t → ∞) and 6 of 8 seed sets were falsely
rejected. At 8² px × 2048 spp × 16 renders 8 of 8 seed sets passed (worst
min-p 2.8× above the Šidák level), so the Cornell box uses that budget (and
2² px × 256 spp × 8 renders in scalar_rgb: 8 of 8 passed). The smooth sky needs
far less.
"""

import numpy as np
import pytest

from mcillum.validation import renders, statistics

from conftest import ESTIMATORS, SCENES, batch, small, wrong_pdf_integrator

ALPHA = 0.01
REFERENCE_SEED = 10_000  # reference renders use seeds disjoint from the estimator's

CASES = {
    # scene file: (res, spp, renders per side) as (scalar_rgb, vectorized),
    # integrator parameters for scalar_rgb
    "cornell_box": ("cornell_box.xml", (2, 8), (256, 2048), (8, 16),
                    # A 2x2 image has the light inside its top pixels; how many
                    # of 256 samples land on it dominates the variance, so the
                    # scalar case looks through the light (as `path` does).
                    {"hide_emitters": True}),
    "sky_sphere": ("sky_sphere.xml", (6, 24), (16, 32), (8, 16), {}),
}


def stacks(variant, case, integrator, max_depth, reference_depth=None, params=None):
    path, res, spp, k, scalar_params = CASES[case]
    res, spp, k = small(variant, *res), small(variant, *spp), small(variant, *k)
    if variant.startswith("scalar"):
        params = {**scalar_params, **(params or {})}
    scene = renders.load_scene(SCENES / path, res=res)
    params = {"max_depth": max_depth, **(params or {})}
    if isinstance(integrator, str):
        integrator = renders.make_integrator(integrator, params)
    reference = renders.make_integrator(
        "path", {**params, "max_depth": reference_depth or max_depth})
    return (batch(scene, integrator, spp, k),
            batch(scene, reference, spp, k, first_seed=REFERENCE_SEED))


@pytest.mark.parametrize("max_depth", [2, -1])
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", ESTIMATORS)
def test_agrees_with_path(variant, name, case, max_depth):
    est, ref = stacks(variant, case, name, max_depth)
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()


@pytest.mark.parametrize("name", ESTIMATORS)
def test_agrees_with_path_hiding_emitters(llvm, name):
    est, ref = stacks(llvm, "cornell_box", name, 3, params={"hide_emitters": True})
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()


@pytest.mark.parametrize("case", CASES)
def test_rejects_path_at_another_depth(variant, case):
    # Vectorized: one extra bounce (2 vs 3), a bias of a few to ~30% per pixel.
    # The scalar budget (Python per sample) resolves only gross bias: 2 vs 1.
    other = small(variant, 1, 3)
    est, ref = stacks(variant, case, "cosine_hemisphere", 2, reference_depth=other)
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, f"max_depth 2 vs {other} was accepted: " + result.summary()


@pytest.mark.parametrize("case", CASES)
def test_rejects_wrong_pdf(llvm, case):
    est, ref = stacks(llvm, case, wrong_pdf_integrator("cosine_hemisphere"), -1)
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, "pdf x1.05 was accepted: " + result.summary()


# ----------------------- The test itself, on synthetic data -----------------------

def synthetic(rng, shift=(1.0, 1.0, 1.0), k=16, shape=(8, 8, 3)):
    base = rng.normal(1.0, 0.01, (k, *shape))
    return base * np.asarray(shift)


def test_statistic_rejects_a_colour_shift_with_unchanged_mean():
    """R +3%, B −3%: the channel mean is unchanged; a mean-only test misses it."""
    rng = np.random.default_rng(1)
    rejected = sum(not statistics.compare(synthetic(rng, (1.03, 1, 0.97)),
                                          synthetic(rng)).passed for _ in range(20))
    assert rejected == 20


def test_statistic_false_rejection_rate_is_at_most_alpha():
    """Same distribution on both sides: rejections ≈ Binomial(200, ≤ α)."""
    rng = np.random.default_rng(2)
    rejected = sum(not statistics.compare(synthetic(rng), synthetic(rng)).passed
                   for _ in range(200))
    # P(Binomial(200, 0.01) >= 7) ≈ 0.005: fail only on a real excess
    assert rejected < 7


def test_statistic_refuses_empty_masks_and_nonfinite_input():
    rng = np.random.default_rng(3)
    a, b = synthetic(rng), synthetic(rng)
    with pytest.raises(ValueError, match="no pixels"):
        statistics.compare(a, b, mask=np.zeros((8, 8), bool))
    a[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        statistics.compare(a, b)


def test_pooled_moments_match_direct_moments_for_one_rung():
    rng = np.random.default_rng(4)
    x = rng.normal(2.0, 0.3, (12, 4, 4, 3))
    a, b = statistics.Moments.pooled({16: x}), statistics.Moments.of(x)
    np.testing.assert_allclose(a.mean, b.mean)
    np.testing.assert_allclose(a.var / a.n, b.var / b.n)


def test_pooled_moments_weight_rungs_by_samples():
    """Rung means with per-sample variance σ² at spp s have variance σ²/s; the
    pooled mean's variance must be σ²/Σ(spp·K)."""
    rng = np.random.default_rng(5)
    sigma, stacks = 0.5, {}
    for spp in (4, 16, 64):
        stacks[spp] = rng.normal(1.0, sigma / np.sqrt(spp), (2000, 1, 1, 1))
    m = statistics.Moments.pooled(stacks)
    np.testing.assert_allclose(m.var / m.n, sigma ** 2 / (2000 * 84), rtol=0.05)
