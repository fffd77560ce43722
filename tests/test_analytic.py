"""Closed-form answers: the furnace sphere and the emitting interior furnace.

Bound: over K independent renders (seeds) the per-render mean over the tested
pixels has a Student-t confidence interval at α = 0.001 (two-sided); the exact
value must lie inside it, widened only by float32 rounding (1e-5 relative),
which is all that is left where an estimator has zero variance (the cosine
estimator on a diffuse surface: f cos/p = ρ exactly).

Power: each test has negative twins (tests/twins.py), every estimator with
its sample weight 5 % off (pdf, BSDF-sample or emitter-sample weight), which
the same check must fail: in llvm for every estimator, since the noisy ones
(uniform, emitter sampling, mis) are where a bound has to earn its width. In
scalar_rgb (6 tiny renders) the bound resolves 5 % only on the sphere and
only for the estimators with zero variance there, cosine and BSDF sampling
(20 of 20 seed sets); the scalar twins of the noisy ones were accepted (e.g.
uniform 0.729 ± 0.096 against 0.75) and the interior's in 10 of 20 sets, so
neither is claimed.
"""

import numpy as np
import pytest

from mcillum.validation.run import renders

from mcillum.validation.stats import statistics

import twins
from conftest import ALL_ESTIMATORS, SCENES, batch, small

ALPHA = 0.001
FLOAT_RTOL = 1e-5
ALBEDO, RADIANCE = 0.5, 1.5


def within_bound(values, exact):
    """Is ``exact`` inside the (1−α) interval of the mean of ``values``?"""
    mean, half = statistics.mean_interval(values, ALPHA)
    return abs(mean - exact) <= half + FLOAT_RTOL * abs(exact), (mean, half)


def disk_masks(res: int, half_width: float = 1.25, radius: float = 1.0):
    """Pixels whose whole footprint is inside / outside the sphere's disk
    (orthographic camera spanning [-half_width, half_width]^2)."""
    edges = np.linspace(-half_width, half_width, res + 1)
    x0, x1 = np.meshgrid(edges[:-1], edges[:-1]), np.meshgrid(edges[1:], edges[1:])
    corners = [np.hypot(a, b) for a in (x0[0], x1[0]) for b in (x0[1], x1[1])]
    inside = np.max(corners, axis=0) < radius
    nearest = np.hypot(np.clip(0, x0[0], x1[0]), np.clip(0, x0[1], x1[1]))
    outside = nearest > radius
    return inside, outside


def furnace_sphere(variant, integrator, max_depth, first_seed=0):
    res = small(variant, 8, 24)
    scene = renders.load_scene(SCENES / "furnace_sphere.xml", res=res,
                               albedo=ALBEDO, radiance=RADIANCE)
    k, spp = small(variant, 6, 12), small(variant, 4, 16)
    if isinstance(integrator, str):
        integrator = renders.make_integrator(integrator, {"max_depth": max_depth})
    images = batch(scene, integrator, spp, k, first_seed).mean(axis=-1)
    inside, outside = disk_masks(res)
    assert inside.sum() > 0 and outside.sum() > 0
    return images[:, inside].mean(axis=1), images[:, outside]


@pytest.mark.parametrize("max_depth", [2, 3, -1])
@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_furnace_sphere_is_albedo_times_radiance(variant, name, max_depth):
    sphere, background = furnace_sphere(variant, name, max_depth)
    ok, (mean, half) = within_bound(sphere, ALBEDO * RADIANCE)
    assert ok, f"sphere: {mean:.6f} ± {half:.2e}, exact {ALBEDO * RADIANCE}"
    # Background pixels see the environment directly: exactly L, every sample.
    np.testing.assert_allclose(background, RADIANCE, rtol=FLOAT_RTOL)


def twin_cases(scalar_names):
    """(variant, estimator, twin): every weight twin in llvm; in scalar those
    of ``scalar_names``."""
    return ([("llvm_ad_rgb", n, k) for n, k in twins.cases(ALL_ESTIMATORS)] +
            [("scalar_rgb", n, k) for n, k in twins.cases(scalar_names)])


@pytest.mark.parametrize("variant_name, name, kind",
                         twin_cases(["cosine_hemisphere", "bsdf_sampling"]))
def test_furnace_sphere_rejects_broken_twins(use_variant, variant_name, name, kind):
    variant = use_variant(variant_name)
    sphere, _ = furnace_sphere(variant, twins.integrator(kind, name, {"max_depth": -1}), -1)
    ok, (mean, half) = within_bound(sphere, ALBEDO * RADIANCE)
    assert not ok, f"{twins.TWINS[kind].bug} passed: {mean:.6f} ± {half:.2e}"


def interior_exact(max_depth: int, albedo: float, emission: float) -> float:
    """L = Le Σ_{k<d} a^k for max_depth d; Le / (1 − a) when unbounded."""
    if max_depth == -1:
        return emission / (1 - albedo)
    return emission * sum(albedo ** k for k in range(max_depth))


def furnace_interior(variant, integrator, max_depth, albedo, first_seed=0):
    scene = renders.load_scene(SCENES / "furnace_interior.xml", res=small(variant, 4, 16),
                               albedo=albedo, emission=RADIANCE)
    if isinstance(integrator, str):
        integrator = renders.make_integrator(integrator, {"max_depth": max_depth})
    k, spp = small(variant, 6, 12), small(variant, 8, 32)
    return batch(scene, integrator, spp, k, first_seed).mean(axis=(1, 2, 3))


@pytest.mark.parametrize("max_depth", [1, 2, 5, 8, -1])
@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_interior_furnace_closed_form(variant, name, max_depth):
    """Depth convention, recursion and Russian roulette (rr_depth 5) at once."""
    if twins.plugin_class(name).use_mis and max_depth != 1:
        pytest.skip(f"{name} weights emitter hits as Mitsuba's path does (mis reproduces it), "
                    "which misses this closed form by +0.11% (see "
                    "test_path_misses_the_interior_closed_form; guided_path +0.10-0.14%)")
    albedo = 0.6
    values = furnace_interior(variant, name, max_depth, albedo)
    exact = interior_exact(max_depth, albedo, RADIANCE)
    ok, (mean, half) = within_bound(values, exact)
    assert ok, f"{mean:.6f} ± {half:.2e}, exact {exact:.6f}"


# (scalar: 6 renders of 4² px resolve 5 % in the interior too rarely to
# claim it: the cosine twin was rejected in 10 of 20 seed sets. mis and
# guided_path: the correct ones miss this closed form too, see above, so
# their twins show no power here; test_agreement rejects them.)
@pytest.mark.parametrize("variant_name, name, kind",
                         [c for c in twin_cases([]) if not twins.plugin_class(c[1]).use_mis])
def test_interior_furnace_rejects_broken_twins(use_variant, variant_name, name, kind):
    variant = use_variant(variant_name)
    values = furnace_interior(variant, twins.integrator(kind, name, {"max_depth": -1}), -1, 0.6)
    ok, (mean, half) = within_bound(values, interior_exact(-1, 0.6, RADIANCE))
    assert not ok, f"{twins.TWINS[kind].bug} passed: {mean:.6f} ± {half:.2e}"


def test_mis_reproduces_path_in_the_interior_furnace(llvm):
    """Same seeds, same estimator: mis and Mitsuba's path agree to float
    rounding (not just statistically) in the emitting furnace."""
    a = furnace_interior(llvm, "mis", 5, 0.6)
    b = furnace_interior(llvm, "path", 5, 0.6)
    np.testing.assert_allclose(a, b, rtol=1e-5)


def test_path_misses_the_interior_closed_form(llvm):
    """Pinned upstream behaviour (Mitsuba 3.9.1): inside an emitting sphere,
    `path` (emitter sampling of the sphere from points on it, MIS) lands
    +0.11% above Le·Σ a^k at max_depth 2, far outside its standard error,
    while our emitter_sampling (no MIS) and the hemisphere estimators are
    exact. If this starts failing, upstream changed: re-enable mis above."""
    values = furnace_interior(llvm, "path", 2, 0.6)
    mean, half = statistics.mean_interval(values, ALPHA)
    exact = interior_exact(2, 0.6, RADIANCE)
    assert 5 * half < mean - exact < 5e-3 * exact, (mean, half, exact)
