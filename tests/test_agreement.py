"""Every registered estimator agrees with Mitsuba's `path` at the same
max_depth, and the same test rejects known-biased answers.

Test: statistics.compare, per-pixel Welch t-tests whose variances come from
each side's own independent renders (batch means), Šidák over pixels, plus an
image-mean test; family-wise α = 0.01 per comparison; fixed seeds.

Budgets: a per-render variance is evidence only where every render of every
pixel sees the rare events that carry the signal. The Cornell box's small
light, seen from a corner pixel by a hemisphere estimator, is hit with
probability ~0.3 % per sample: 8² px × 2048 spp × 16 renders passed 8 of 8
seed sets (16² px × 256 spp failed 6 of 8: pixels with no hit in 16 renders).
In scalar_rgb: 2² px × 256 spp × 8 renders, looking through the light as
`path` does (8 of 8 passed).

Power, shown on broken twins (tests/twins.py) in the same module: in llvm
every estimator's weight twins (pdf 5 % high, BSDF- or emitter-sample weight
5 % low) on all three scenes, the glossy lobe dropped on probe_spheres, and a
local error (30 % dark in one 2×2 … 6×6 block, 1/16 of the image) which the
per-pixel test must find inside the block. In scalar_rgb the 5 %
twins are rejected on sky_sphere (6² px × 128 spp × 16 renders); the scalar
Cornell box (2² px, looking through the light) resolves only gross errors
(max_depth 2 against 1) and claims nothing finer.
"""

import functools

import numpy as np
import pytest

from mcillum.integrators.core import registry
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.validation.stats import statistics

import twins
from conftest import ALL_ESTIMATORS, VARIANTS, batch, small

ALPHA = 0.01
REFERENCE_SEED = 10_000  # reference renders use seeds disjoint from the estimator's

#: scene: (res, spp, renders per side) as (scalar_rgb, llvm), None where the
#: scene runs in llvm only, and integrator properties for scalar_rgb.
CASES = {
    # A 2x2 image has the light inside its top pixels; how many of 256 samples
    # land on it dominates the variance, so scalar looks through the light.
    "cornell_box": ((2, 8), (256, 2048), (8, 16), {"hide_emitters": True}),
    "sky_sphere": ((6, 24), (128, 32), (16, 16), {}),
    "probe_spheres": ((None, 8), (None, 512), (None, 16), {}),
}


def stacks(variant, case, integrator, max_depth, reference_depth=None, params=None,
           first_seed=0):
    res, spp, k, scalar_params = CASES[case]
    res, spp, k = small(variant, *res), small(variant, *spp), small(variant, *k)
    if variant.startswith("scalar"):
        params = {**scalar_params, **(params or {})}
    params = {"max_depth": max_depth, **(params or {})}
    if isinstance(integrator, str):
        integrator = renders.make_integrator(integrator, params)
    ref = reference(variant, case, tuple(sorted(
        {**params, "max_depth": reference_depth or max_depth}.items())), first_seed)
    return batch(_scene(variant, case, res), integrator, spp, k, first_seed=first_seed), ref


@functools.lru_cache(maxsize=None)
def _scene(variant, case, res):
    return renders.load_scene(scenes.path(case), res=res)


@functools.lru_cache(maxsize=None)
def reference(variant, case, params: tuple, first_seed=0):
    """K renders of `path` (seeds REFERENCE_SEED + first_seed …), rendered
    once per module run and shared by the estimators and their twins."""
    res, spp, k, _ = CASES[case]
    res, spp, k = small(variant, *res), small(variant, *spp), small(variant, *k)
    return batch(_scene(variant, case, res), renders.make_integrator("path", dict(params)),
                 spp, k, first_seed=REFERENCE_SEED + first_seed)


#: (variant, scene) pairs: every scene in llvm, those with a scalar budget in scalar.
VARIANT_CASES = [(v, c) for v in VARIANTS for c in CASES
                 if v.startswith("llvm") or CASES[c][0][0] is not None]


@pytest.mark.parametrize("max_depth", [2, -1])
@pytest.mark.parametrize("variant_name, case", VARIANT_CASES)
@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_agrees_with_path(name, variant_name, case, max_depth):
    variant = renders.set_variant(variant_name)
    est, ref = stacks(variant, case, name, max_depth)
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()


@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_agrees_with_path_hiding_emitters(llvm, name):
    """Against path hiding emitters; the twin that ignores the setting (shows
    the light) is rejected by the same test."""
    est, ref = stacks(llvm, "cornell_box", name, 3, params={"hide_emitters": True})
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()
    shown, _ = stacks(llvm, "cornell_box", renders.make_integrator(name, {"max_depth": 3}), 3,
                      params={"hide_emitters": True})
    assert not statistics.compare(shown, ref, ALPHA).passed, "the light shown was accepted"


#: Scenes with content a continuous hemisphere pdf cannot reach (scene
#: header "Contains:"), and their budgets (res, spp, renders per side).
DELTA_CASES = {"smooth_glass": ((8, 256, 16), -1), "point_light": ((8, 64, 16), 2)}
#: The twin that breaks the technique that reaches each (light through glass
#: comes from BSDF samples; a point light only from emitter samples).
DELTA_TWINS = {"smooth_glass": "bsdf_weight_low", "point_light": "emitter_weight_low"}


@pytest.mark.parametrize("name, case", [
    (n, c) for c in DELTA_CASES for n in ALL_ESTIMATORS
    if registry.facts(n).renders(scenes.index()[c].contains)])
def test_delta_content_is_reached_by_those_that_declare_it(llvm, name, case):
    """Delta lights, delta lobes and transmission: an estimator whose facts
    say it reaches them renders the scene unbiased (the others refuse it:
    test_refusals.py)."""
    depth = DELTA_CASES[case][1]
    result = delta_comparison(case, renders.make_integrator(name, {"max_depth": depth}))
    assert result.passed, result.summary()


@functools.lru_cache(maxsize=None)
def delta_reference(case):
    """K renders of `path` for a delta case, shared by estimators and twins."""
    (res, spp, k), depth = DELTA_CASES[case]
    return batch(_scene("llvm_ad_rgb", case, res),
                 renders.make_integrator("path", {"max_depth": depth}), spp, k,
                 first_seed=REFERENCE_SEED)


def delta_comparison(case, integrator):
    (res, spp, k), _ = DELTA_CASES[case]
    est = batch(_scene("llvm_ad_rgb", case, res), integrator, spp, k)
    return statistics.compare(est, delta_reference(case), ALPHA)


@pytest.mark.parametrize("name, case", [
    (n, c) for c in DELTA_CASES for n in ALL_ESTIMATORS
    if registry.facts(n).renders(scenes.index()[c].contains)
    and twins.TWINS[DELTA_TWINS[c]].applies(twins.plugin_class(n))])
def test_delta_content_rejects_a_broken_twin(llvm, name, case):
    """The same test and budget reject the technique that reaches the delta
    content with its weight 5 % low."""
    kind, depth = DELTA_TWINS[case], DELTA_CASES[case][1]
    result = delta_comparison(case, twins.integrator(kind, name, {"max_depth": depth}))
    assert not result.passed, f"{twins.TWINS[kind].bug} was accepted: " + result.summary()


# ------------------------- The test rejects biased answers ------------------------

@pytest.mark.parametrize("case", ["cornell_box", "sky_sphere"])
def test_rejects_path_at_another_depth(variant, case):
    # llvm: one extra bounce (2 vs 3), a bias of a few to ~30% per pixel.
    # The scalar budget (Python per sample) resolves only gross bias: 2 vs 1.
    other = small(variant, 1, 3)
    est, ref = stacks(variant, case, "cosine_hemisphere", 2, reference_depth=other)
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, f"max_depth 2 vs {other} was accepted: " + result.summary()


#: (scene, twin kinds) of the broken-twin tests, per variant family.
TWIN_CASES = {
    "llvm": [(c, twins.WEIGHT_TWINS) for c in CASES] + [("probe_spheres", ("glossy_dropped",))],
    "scalar": [("sky_sphere", twins.WEIGHT_TWINS)],
}
#: Not claimed: mis gives one technique little weight where the other is
#: good (the probe's envmap is importance-sampled; the scalar sky's BSDF
#: samples), so a 5 % error in it was rejected in only 7 (probe, llvm) and
#: 8 (sky, scalar) of 10 seed sets.
UNRESOLVED = {("llvm", "probe_spheres", "mis", "bsdf_weight_low"),
              ("scalar", "sky_sphere", "mis", "emitter_weight_low")}


def twin_cases(family):
    return [(family, case, name, kind) for case, kinds in TWIN_CASES[family]
            for name, kind in twins.cases(ALL_ESTIMATORS, kinds)
            if (family, case, name, kind) not in UNRESOLVED]


@pytest.mark.parametrize("family, case, name, kind",
                         twin_cases("llvm") + twin_cases("scalar"))
def test_rejects_a_broken_twin(use_variant, family, case, name, kind):
    """Each estimator's broken twins (a weight 5 % off, the glossy lobe
    dropped): the test that passes the estimator rejects them."""
    variant = use_variant(f"{family}_rgb" if family == "scalar" else "llvm_ad_rgb")
    params = {"max_depth": -1}
    if variant.startswith("scalar"):
        params.update(CASES[case][3])
    est, ref = stacks(variant, case, twins.integrator(kind, name, params), -1)
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, f"{twins.TWINS[kind].bug} was accepted: " + result.summary()


@pytest.mark.parametrize("case", ["sky_sphere", "probe_spheres"])
@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_finds_a_local_error_per_pixel(llvm, name, case):
    """A bug confined to one block of the image (1/16 of it, 30 % dark): the
    per-pixel test rejects a pixel inside the block (10 of 10 seed sets for
    every estimator on both scenes). At 15 % dark it did so in only 3–10 of
    10 (emitter sampling on sky_sphere and uniform on probe_spheres 3/10), and
    on the Cornell box at 8² px the uniform estimator's per-pixel noise hides
    15 % in its 2×2 block (p 2.7e-5 against 2.6e-5): neither is claimed."""
    est, ref = stacks(llvm, case, twins.integrator("region_dark", name, {"max_depth": -1}), -1)
    result = statistics.compare(est, ref, ALPHA)
    inside = twins.region_mask(*result.pixel_p.shape)
    assert np.nanmin(result.pixel_p[inside]) < result.alpha_pixel, (
        "a 30 % local error was not found per pixel: " + result.summary())
