"""fibonacci_hemisphere and bayesian_hemisphere: N directions per shading
point (integrators/core/direction_set.py).

Exact cases: under a constant environment a lone diffuse sphere reflects
ρL at every pixel; both estimators must return it to float precision (every
direction escapes, so any error is a wrong weight), bayesian_hemisphere's
posterior variance must be 0 there, and its zero prior mean must darken the
image by exactly Σ Q⁻¹z.

Statistical tests (α = 0.01 family-wise per comparison, Šidák over pixels,
statistics.compare as in test_agreement.py; fixed seeds):

* fibonacci_hemisphere agrees with `path` per pixel on the sky sphere
  (occlusion) and on phong_spheres (its diffuse/glossy split); the set
  never shifted (the same N directions everywhere), its weight twin and
  its glossy lobe dropped are rejected by the same test and budget;
* the shifted, mapped point set is distributed by cos θ/π (χ², one point of
  the set over many shifts); the unshifted set's points are not;
* bayesian_hemisphere, biased by design, is exact in a furnace (weights
  and measure), its noise-corrected bias shrinks from N = 16 to 256, and
  the calibration verdict follows a known error (checks/evidence.py's rule).
"""

import dataclasses
import os

import numpy as np
import pytest

import mcillum  # noqa: F401
import drjit as dr
import mitsuba as mi

from mcillum.integrators.core import registry
from mcillum.validation.plan import scenes

from mcillum.validation.run import renders, stacks

from mcillum.validation.stats import statistics

import twins
from conftest import VARIANTS, batch, small

ALPHA = 0.01
SETS = ("fibonacci_hemisphere", "bayesian_hemisphere")
REFERENCE_SEED = 10_000


def lone_sphere(res, envmap="constant"):
    return renders.load_scene(scenes.path("lone_sphere"), res=res, envmap=envmap)


def environment_radiance(scene) -> np.ndarray:
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(0, 0, -1)
    return np.array(scene.environment().eval(si), dtype=float).ravel()


# ------------------------------ Loading --------------------------------------

@pytest.mark.parametrize("variant_name", VARIANTS)
@pytest.mark.parametrize("name", SETS)
def test_loads_from_xml_and_python_and_is_exact_in_a_furnace(use_variant, variant_name, name):
    """Constant environment, lone diffuse sphere: ρL everywhere."""
    use_variant(variant_name)
    scene = lone_sphere(small(variant_name, 2, 8))
    expected = np.array([0.8, 0.6, 0.4]) * environment_radiance(scene)
    xml = mi.load_string(f'<integrator version="3.0.0" type="{name}">'
                         '<integer name="directions" value="16"/></integrator>')
    for integrator in (xml, mi.load_dict({"type": name, "directions": 16})):
        image = renders.render(scene, integrator, 2).image
        np.testing.assert_allclose(image, np.broadcast_to(expected, image.shape), rtol=2e-5)


@pytest.mark.parametrize("mapping", ["cosine", "uniform"])
def test_bayesian_nodes_of_either_mapping_are_exact_in_a_furnace(llvm, mapping):
    """Whatever the nodes' mapping, the weights integrate against cos θ/π:
    ρL exactly (a weight applied with the nodes' density instead of the
    measure would be off by a factor that varies with θ)."""
    scene = lone_sphere(8)
    expected = np.array([0.8, 0.6, 0.4]) * environment_radiance(scene)
    integ = renders.make_integrator("bayesian_hemisphere", {
        "directions": 16, "length_scale": 0.5, "mapping": mapping, "prior_mean": "zero",
        "sets": 1})
    from mcillum.integrators.quadrature import gp_quadrature as gq
    total = gq.weights(16, 0.5, 1e-3, "zero", mapping).weights.sum()
    image = renders.render(scene, integ, 2).image
    np.testing.assert_allclose(image, np.broadcast_to(total * expected, image.shape), rtol=2e-5)


def test_zero_prior_mean_darkens_by_the_weight_sum(llvm):
    """The zero mean pulls every estimate towards 0 by exactly Σ Q⁻¹z < 1
    (the constant mean removes it); the posterior variance is 0 with the
    constant mean (all samples equal) and positive with the zero mean."""
    from mcillum.integrators.quadrature import gp_quadrature as gq
    scene = lone_sphere(8)
    expected = np.array([0.8, 0.6, 0.4]) * environment_radiance(scene)
    out = {}
    for mean in ("constant", "zero"):
        integ = renders.make_integrator("bayesian_hemisphere", {
            "directions": 16, "length_scale": 0.5, "prior_mean": mean, "sets": 1})
        out[mean] = renders.render(scene, integ, 2)
    total = gq.weights(16, 0.5, 1e-3, "zero").weights.sum()
    assert total < 0.99
    np.testing.assert_allclose(out["zero"].image, np.broadcast_to(total * expected,
                                                                  out["zero"].image.shape),
                               rtol=2e-5)
    np.testing.assert_allclose(out["constant"].image, np.broadcast_to(
        expected, out["constant"].image.shape), rtol=2e-5)
    assert np.abs(out["constant"].aovs["posterior_std"]).max() < 1e-6 * expected.max()
    assert out["zero"].aovs["posterior_std"].min() > 1e-3 * expected.min()


# ------------------------------ Parameters -----------------------------------

@pytest.mark.parametrize("name", SETS)
@pytest.mark.parametrize("depth", [-1, 0, 3])
def test_other_depths_are_refused_saying_why(llvm, name, depth):
    with pytest.raises((ValueError, RuntimeError), match="direct illumination only"):
        mi.load_dict({"type": name, "max_depth": depth})


@pytest.mark.parametrize("name", SETS)
def test_depth_one_shows_only_what_the_camera_sees(llvm, name):
    """max_depth 1: no reflected light (the lone sphere fills the view: black);
    the sky sphere's background equals path's at depth 1."""
    image = renders.render(lone_sphere(8), renders.make_integrator(name, {"max_depth": 1}),
                           4).image
    assert image.max() == 0
    sky = renders.load_scene(scenes.path("sky_sphere"), res=16)
    ours = renders.render(sky, renders.make_integrator(name, {"max_depth": 1}), 4, seed=3)
    ref = renders.render(sky, renders.make_integrator("path", {"max_depth": 1}), 4, seed=3)
    np.testing.assert_allclose(ours.image, ref.image, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("props, match", [
    ({"type": "fibonacci_hemisphere", "directions": 0}, "directions must be an integer >= 1"),
    ({"type": "fibonacci_hemisphere", "mapping": "spiral"}, "mapping must be one of"),
    ({"type": "bayesian_hemisphere", "length_scale": -1.0}, "length_scale must be"),
    ({"type": "bayesian_hemisphere", "length_scale": "wide"}, "length_scale must be"),
    ({"type": "bayesian_hemisphere", "noise": -1.0}, "noise must be a number >= 0"),
    ({"type": "bayesian_hemisphere", "prior_mean": "median"}, "prior_mean must be one of"),
    ({"type": "bayesian_hemisphere", "mapping": "spiral"}, "mapping must be one of"),
    ({"type": "bayesian_hemisphere", "noise": "some"}, "noise must be a number >= 0"),
    ({"type": "bayesian_hemisphere", "sets": 0}, "sets must be an integer >= 1"),
    ({"type": "bayesian_hemisphere", "sets": 2.5}, "sets must be an integer >= 1"),
])
def test_bad_parameters_are_refused(llvm, props, match):
    with pytest.raises((ValueError, RuntimeError), match=match):
        mi.load_dict(props)


def test_glossy_lobes_are_split_and_a_diffuse_only_estimator_refuses_them(llvm):
    """probe_spheres (rough gold and plastic): both estimators of N
    directions split their sets between the lobes and render it; an
    estimator declared diffuse_only refuses it, naming the object."""
    scene = renders.load_scene(scenes.path("probe_spheres"), res=4)
    for name in ("fibonacci_hemisphere", "bayesian_hemisphere"):
        integ = renders.make_integrator(name, {"max_depth": 2})
        image = renders.render(scene, integ, 1).image
        assert np.isfinite(image).all() and image[..., :3].max() > 0
    assert renders.make_integrator("bayesian_hemisphere", {"max_depth": 2}).lobe_directions
    base = type(mi.load_dict({"type": "cosine_hemisphere"}))
    diffuse_only = type("DiffuseOnly", (base,), {"diffuse_only": True})
    with pytest.raises(mcillum.integrators.UnreachableContentError) as err:
        diffuse_only(mi.Properties()).check_scene(scene)
    text = str(err.value)
    assert "glossy lobe" in text and "bayesian_hemisphere" in text and "'gold" in text


def _walked(value) -> int:
    """How many Python containers and records Dr.Jit walks in ``value``."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return 1 + sum(_walked(getattr(value, f.name)) for f in dataclasses.fields(value))
    if isinstance(value, (list, tuple)):
        return 1 + sum(_walked(v) for v in value)
    if isinstance(value, dict):
        return 1 + sum(_walked(v) for v in value.values())
    return 0


def test_the_weight_tables_stay_out_of_the_plugins_attributes(llvm):
    """Dr.Jit walks a Python plugin's attributes (lists, dicts, dataclasses)
    at every symbolic call it traces: the lobe tables' 656 records there made
    each launch on probe_spheres cost 0.2 s instead of 0.03 s. After a glossy
    render the weights live in Dr.Jit arrays only."""
    scene = renders.load_scene(scenes.path("probe_spheres"), res=4)
    integ = renders.make_integrator("bayesian_hemisphere", {"max_depth": 2})
    renders.render(scene, integ, 1)
    assert integ.glossy
    walked = {k: _walked(v) for k, v in vars(integ).items()}
    assert max(walked.values()) < 64, walked


@pytest.mark.parametrize("name", SETS)
def test_delta_lights_are_refused(llvm, name):
    scene = renders.load_scene(scenes.path("point_light"), res=4)
    with pytest.raises(mcillum.integrators.UnreachableContentError, match="delta emitter"):
        renders.make_integrator(name, {"max_depth": 2}).check_scene(scene)


# ------------------------- The shifted point set ------------------------------

def _chi2(sample, n_points=1 << 18):
    """mi.chi2's test of ``sample`` (u ∈ [0,1)² → direction) against cos θ/π."""
    from mcillum.integrators.quadrature import fibonacci_hemisphere as fh
    test = mi.chi2.ChiSquareTest(
        domain=mi.chi2.SphericalDomain(),
        sample_func=sample, pdf_func=lambda w: fh.cosine_polar_pdf(w),
        sample_dim=2, sample_count=n_points, res=32, ires=16, seed=7)
    return test.run(0.01)


@pytest.mark.parametrize("j, n", [(0, 16), (5, 16), (63, 64)])
def test_one_point_of_the_shifted_set_is_cosine_distributed(llvm, j, n):
    """Over shifts ξ ~ U[0,1)², point j of the mapped set has density cos θ/π
    (what makes the estimator unbiased); χ² at α = 0.01 (mi.chi2)."""
    from mcillum.integrators.quadrature import fibonacci_hemisphere as fh
    assert _chi2(lambda u: fh.sample_cosine_polar(fh.fibonacci_point(j, n, u)))


def test_the_unshifted_set_is_not_cosine_distributed(llvm):
    """Negative control: a random point of the set turned about the normal
    (u_j fixed, v shifted) has only n values of θ: χ² rejects it."""
    from mcillum.integrators.quadrature import fibonacci_hemisphere as fh
    n = 16

    def turned(u):
        j = dr.floor(u.x * n)
        return fh.sample_cosine_polar(fh.fibonacci_point(j, n, mi.Point2f(0.0, u.y)))

    assert not _chi2(turned)


def test_inverse_maps_back(llvm):
    from mcillum.integrators.quadrature import fibonacci_hemisphere as fh
    rng = np.random.default_rng(3)
    u = mi.Point2f(rng.random(1000), rng.random(1000))
    for fwd, inv in ((fh.sample_cosine_polar, fh.invert_cosine_polar),
                     (fh.sample_uniform_polar, fh.invert_uniform_polar)):
        back = inv(fwd(u))
        np.testing.assert_allclose(np.array(back), np.array(u), atol=2e-4)


# --------------------- Unbiased against path, per pixel ------------------------

#: scene → (res, camera spp per render, renders K, directions)
AGREEMENT = {"sky_sphere": (16, 8, 16, 16), "phong_spheres": (8, 64, 16, 16)}


def _stacks(case, integrator):
    res, spp, k, n = AGREEMENT[case]
    scene = renders.load_scene(scenes.path(case), res=res)
    est = batch(scene, integrator, spp, k)
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 2}), spp * n, k,
                first_seed=REFERENCE_SEED)
    return est, ref


@pytest.mark.parametrize("case", AGREEMENT)
@pytest.mark.parametrize("mapping", ["cosine", "uniform"])
def test_fibonacci_agrees_with_path_per_pixel(llvm, case, mapping):
    n = AGREEMENT[case][3]
    est, ref = _stacks(case, renders.make_integrator(
        "fibonacci_hemisphere", {"directions": n, "mapping": mapping}))
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()


@pytest.mark.parametrize("case", AGREEMENT)
@pytest.mark.parametrize("kind", ["unshifted_set", "set_weight_low"])
def test_fibonacci_twins_are_rejected(llvm, case, kind):
    """The set never shifted (the same N directions at every point: biased)
    and every direction's weight 5 % low: the same test and budget reject
    both."""
    n = AGREEMENT[case][3]
    est, ref = _stacks(case, twins.integrator(kind, "fibonacci_hemisphere", {"directions": n}))
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, f"{twins.TWINS[kind].bug} was accepted: " + result.summary()


def test_fibonacci_glossy_split_matters(llvm):
    """Negative control of the Phong split: with the glossy lobe dropped
    from every BSDF call the image is rejected."""
    est, ref = _stacks("phong_spheres", twins.integrator(
        "glossy_dropped", "fibonacci_hemisphere", {"directions": 16}))
    assert not statistics.compare(est, ref, ALPHA).passed


# ------------------- bayesian_hemisphere: bias and error bars -------------------

def _stack(images, std=None):
    from mcillum.validation.run import stacks
    return stacks.Stack("bayesian_hemisphere", 4, np.asarray(images, np.float32),
                        [0.0] * len(images), {} if std is None else {"posterior_std": std})


class _Reference:
    def __init__(self, mean, variance_of_mean):
        self.mean, self.variance_of_mean = mean, variance_of_mean


@pytest.mark.parametrize("scale, verdict", [(1.0, "calibrated"), (0.1, "over-confident"),
                                            (10.0, "under-confident")])
def test_calibration_verdict_follows_the_error(scale, verdict):
    """Renders scattered by a known std around the reference: a predicted std
    equal to it is calibrated; one 10× too small is over-confident, 10× too
    large under-confident (the rule of checks.convergence.CALIBRATED)."""
    from mcillum.validation.stages import quadrature
    rng = np.random.default_rng(5)
    ref = np.full((8, 8, 3), 2.0)
    sigma = rng.uniform(0.05, 0.5, size=(8, 8, 3))
    images = ref + sigma * rng.standard_normal((32, 8, 8, 3))
    std = np.broadcast_to(scale * sigma, (32, 8, 8, 3))
    c = quadrature._calibration(_stack(images, std), _Reference(ref, np.zeros_like(ref)))
    assert c.verdict == verdict, c


@pytest.mark.parametrize("se_at_8, renders", [(0.002, [8, 8]), (0.008, [8, 8, 16, 16])])
def test_the_bias_against_n_renders_the_plans_k_where_eight_cannot_decide(
        monkeypatch, se_at_8, renders):
    """The N other than the default are read from BIAS_RENDERS renders; where
    that leaves bias_shrinks undecided (rms 0.5 % + 2 × 0.8 % against 2 %),
    they are rendered again with the plan's K."""
    import types

    from mcillum.validation.results import BiasAtN
    from mcillum.validation.stages import quadrature
    asked = []
    monkeypatch.setattr(quadrature, "_renders", lambda ctx, name, params, spp, k, block:
                        asked.append(k) or types.SimpleNamespace(k=k))
    monkeypatch.setattr(quadrature, "_bias", lambda stack, ref, n: BiasAtN(
        directions=n, rms_bias=0.005, rms_bias_se=se_at_8 if stack.k == 8 else 0.002,
        mean_bias=0.0, renders=stack.k))
    ctx = types.SimpleNamespace(integrators={"b": types.SimpleNamespace(
        made=types.SimpleNamespace(directions=64))})
    rows = quadrature._bias_against_n(ctx, "b", types.SimpleNamespace(spp=256, k=16), None,
                                      16, 0)
    assert asked == renders and [r.directions for r in rows] == [16, 64, 256]
    assert rows[-1].renders == renders[-1]


def test_bias_estimate_is_corrected_for_noise():
    """Pure noise around the reference reads as (nearly) no bias; a 5 % offset
    under the same noise reads as 5 % ± its se."""
    from mcillum.validation.stages import quadrature
    rng = np.random.default_rng(6)
    ref = np.full((16, 16, 3), 1.0)
    noise = 0.2 * rng.standard_normal((16, 16, 16, 3))
    zero = quadrature._bias(_stack(ref + noise), _Reference(ref, np.zeros_like(ref)), 16)
    assert zero.rms_bias < 3 * zero.rms_bias_se + 0.01
    off = quadrature._bias(_stack(1.05 * ref + noise), _Reference(ref, np.zeros_like(ref)), 16)
    assert abs(off.rms_bias - 0.05) < 3 * off.rms_bias_se + 0.005, off
    assert off.mean_bias == pytest.approx(0.05, abs=0.01)


def test_the_bias_se_stays_bounded_near_zero():
    """Near a bias of 0 the delta method's se(B)/(2√B) grows without bound
    (pure noise: up to 6.8× the median se in 200 draws); the se is held to
    √se(B), so a bias of 0.01 % cannot read ± 2.5 % (the quick furnace,
    seed set 102)."""
    from mcillum.validation.stages import quadrature
    ref = np.full((8, 8, 3), 1.0)
    found = []
    for seed in range(200):
        x = ref + 0.05 * np.random.default_rng(seed).standard_normal((8, 8, 8, 3))
        found.append(quadrature._bias(_stack(x), _Reference(ref, np.zeros_like(ref)), 256))
    se = np.array([b.rms_bias_se for b in found])
    assert any(b.rms_bias > 0 for b in found) and se.max() < 1.5 * np.median(se), se.max()


def test_bayesian_bias_shrinks_with_n(llvm):
    """On the lone sphere under the smooth `sg` map one node set's
    noise-corrected rms bias at N = 256 is below that at N = 16 by more than
    3 se (measured: 7.4 % ± 0.05 % → 0.2 % ± 0.03 %); the check is the
    validation's bias_shrinks."""
    from mcillum.validation.stages import quadrature
    scene = renders.load_scene(scenes.path("lone_sphere"), res=8, envmap="sg")
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 4096, 8,
                 first_seed=REFERENCE_SEED)
    ref = _Reference(path.mean(axis=0), path.var(axis=0, ddof=1) / len(path))
    rows = {}
    for n in (16, 256):
        integ = renders.make_integrator("bayesian_hemisphere", {
            "directions": n, "length_scale": 0.5, "noise": 1e-3, "mapping": "cosine",
            "sets": 1})
        rows[n] = quadrature._bias(_stack(batch(scene, integ, 16, 8)), ref, n)
    lo, hi = rows[16], rows[256]
    assert lo.rms_bias - hi.rms_bias > 3 * np.hypot(lo.rms_bias_se, hi.rms_bias_se), rows


def phong_sphere(res, envmap="sg", exponent=30):
    return renders.load_scene(scenes.path("lone_phong_sphere"), res=res, envmap=envmap,
                              exponent=exponent)


@pytest.mark.parametrize("variant_name", VARIANTS)
def test_glossy_split_renders_in_every_variant(use_variant, variant_name):
    """A Phong sphere (k_d 0.2, k_s 0.6) in a constant environment: the
    diffuse set's integrand is constant there, the lobe set's is
    f_s cos/p_n. The image mean is path's within 1.5 % (measured: +0.3 %
    in llvm at 8² px), and the posterior variance of every pixel is finite
    and ≥ 0."""
    use_variant(variant_name)
    res, spp = small(variant_name, 2, 8), small(variant_name, 4, 16)
    scene = phong_sphere(res, envmap="constant")
    ref = renders.render(scene, renders.make_integrator("path", {"max_depth": 2}),
                         small(variant_name, 1024, 8192), REFERENCE_SEED).image[..., :3]
    out = renders.render(scene, renders.make_integrator(
        "bayesian_hemisphere", {"directions": 16}), spp, 1)
    assert out.image[..., :3].mean() == pytest.approx(ref.mean(), rel=0.015)
    var = out.aovs["posterior_var"]
    assert np.isfinite(var).all() and (var >= 0).all() and var.max() > 0


def test_bayesian_bias_on_a_glossy_lobe_and_its_weight_twin(llvm):
    """lone_phong_sphere (exponent 30) under `sg`, 8² px, 8 renders of 64 spp
    against `path` at 8 × 65 536 spp: the glossy split's image bias at N = 64
    is within ±0.5 % (measured −0.12 %; −0.24 % at N = 16) and bias_limit
    does not fail it (measured rms bias 2.1 % ± 0.7 at N = 16, 0.9 % ± 0.8
    at 64); its twin with every weight × 0.95 fails bias_limit (about −5 %)."""
    got = _bias_limit_with_weight_twin(phong_sphere(8), 65536, {}, 64, (16, 64))
    outcome, rows = got["bayesian_hemisphere"]
    assert abs(rows[1].mean_bias) < 0.005 and outcome != "fail", got
    outcome, rows = got["twin"]
    assert outcome == "fail" and rows[1].mean_bias == pytest.approx(-0.05, abs=0.01), got


def _bias_limit_with_weight_twin(scene, reference_spp, params, spp, ns) -> dict:
    """{"bayesian_hemisphere" and "twin" (every weight × 0.95): (bias_limit
    outcome, the quadrature stage's bias rows at ``ns``)}, from 8 renders of
    ``spp`` against 8 of `path` at ``reference_spp``."""
    from mcillum.validation.checks import convergence
    from mcillum.validation.stages import quadrature
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), reference_spp, 8,
                 first_seed=REFERENCE_SEED)
    ref = _Reference(path.mean(axis=0), path.var(axis=0, ddof=1) / len(path))
    twin = twins.set_weight_class("bayesian_hemisphere", 0.95)
    registry.register(twin)
    try:
        got = {}
        for key, name in (("bayesian_hemisphere", "bayesian_hemisphere"),
                          ("twin", twin.plugin_name)):
            rows = [quadrature._bias(_stack(batch(scene, renders.make_integrator(
                name, {"directions": n, **params}), spp, 8)), ref, n) for n in ns]
            got[key] = convergence.bias_limit_outcome(*rows)[0], rows
    finally:
        registry.unregister(twin.plugin_name)
    return got


@pytest.mark.slow
def test_shifted_sets_lower_the_error_where_a_pixel_sees_one_normal(llvm):
    """One fixed node set errs the same way at every turn about a normal;
    where a pixel's footprint is small against the map's detail (studio's
    small lights, 32² px) spp cannot average that away, and drawing among
    16 shifted sets can. Measured at N = 16, 64 spp, same ℓ and noise:
    relMSE × 0.87 at 32² px, × 0.82 at 64² (× 0.97 at 16², where the
    footprint already mixes normals; × 0.98 under courtyard at 64²)."""
    scene = lone_sphere(32, envmap="studio")
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 4096, 8,
                 first_seed=REFERENCE_SEED)
    ref, noise = path.mean(axis=0)[..., :3], (path.var(axis=0, ddof=1) / 8)[..., :3]
    floor = float(np.mean(noise / ref ** 2))
    got = {}
    for sets in (1, 16):
        images = batch(scene, renders.make_integrator("bayesian_hemisphere", {
            "directions": 16, "length_scale": 0.318, "noise": 0.1, "mapping": "cosine",
            "sets": sets}), 64, 8)
        got[sets] = float(np.mean((images[..., :3] - ref) ** 2 / ref ** 2)) - floor
    assert got[16] < 0.95 * got[1], got


def test_bayesian_weight_twin_fails_and_the_estimator_passes_the_bias_limit(llvm):
    """bias_shrinks tests the limit, not only the trend: the Bayesian
    estimator's bias at N = 256 is within convergence.BIAS_LIMIT (pass); its
    twin with every weight × 0.95 keeps about 5 % (fail), though its bias
    falls from N = 16 to 256 too (the old rule passed it)."""
    got = _bias_limit_with_weight_twin(lone_sphere(8, envmap="sg"), 4096,
                                       {"length_scale": 0.5}, 16, (16, 256))
    assert got["bayesian_hemisphere"][0] == "pass", got
    assert got["twin"][0] == "fail", got


def test_fibonacci_glossy_set_lowers_the_variance(llvm):
    """The glossy set is there for a reason: with N_b = 0 (every direction
    from the diffuse set; unbiased too) the Phong spheres' per-pixel
    variance, averaged over 16² px from 16 renders, is higher. Measured: the
    split has 0.53× the variance; asserted: below 0.75× (the estimate of a
    mean over 256 pixels × 15 dof moves by a few % between seed sets)."""
    cls = twins.plugin_class("fibonacci_hemisphere")

    class NoGlossySet(cls):
        plugin_name = "fibonacci_no_glossy_set"

        def draw_set(self, sampler, si, bsdf, ctx, active):
            a, b, c, _ = super().draw_set(sampler, si, bsdf, ctx, active)
            return a, b, c, mi.UInt32(0)

    mi.register_integrator(NoGlossySet.plugin_name, lambda props: NoGlossySet(props))
    scene = renders.load_scene(scenes.path("phong_spheres"), res=16)
    variance = {}
    for name in ("fibonacci_hemisphere", NoGlossySet.plugin_name):
        stack = batch(scene, renders.make_integrator(name, {"directions": 16}), 4, 16)
        variance[name] = stack.var(axis=0, ddof=1).mean()
    ratio = variance["fibonacci_hemisphere"] / variance[NoGlossySet.plugin_name]
    assert ratio < 0.75, variance


# ------------- bayesian_hemisphere: settings chosen for the quadrature -------------

def test_held_out_truth_is_the_map_integrated_about_each_normal(llvm):
    """The known answers the settings are scored on: against a brute-force
    sum over 2^18 directions of the courtyard map (agreement measured ~1e-3,
    the brute force's own error)."""
    from mcillum.integrators.quadrature import gp_scene as bh
    scene = lone_sphere(4, envmap="courtyard")
    env = scene.environment()
    normals = bh.sphere_directions(6)
    d = bh.sphere_directions(1 << 18)
    brute = np.maximum(normals @ d.T, 0) @ bh.environment_values(env, d) * 4 / len(d)
    np.testing.assert_allclose(bh.held_out_truth(env, normals), brute, rtol=5e-3)


def test_held_out_lobes_are_the_same_in_scalar_and_llvm(use_variant):
    """probe_spheres, where some film rays miss every surface: scalar_rgb
    finds the same held-out lobes as llvm_ad_rgb (axes, exponents, origins;
    float32 round-off apart). The first version's scalar branch failed to
    unpack a missed ray's result."""
    from mcillum.integrators.quadrature import gp_scene
    got = {}
    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        use_variant(variant)
        scene = renders.load_scene(scenes.path("probe_spheres"), res=4, max_depth=2)
        got[variant] = gp_scene.held_out_lobes(scene)
    (axes, exponents, origins), (axes_s, exponents_s, origins_s) = got.values()
    assert len(axes) == 64 and axes.shape == axes_s.shape
    np.testing.assert_allclose(axes_s, axes, atol=1e-4)
    np.testing.assert_allclose(exponents_s, exponents, rtol=1e-3)
    np.testing.assert_allclose(origins_s, origins, atol=1e-4)


def test_held_out_integrals_see_what_occludes_them(llvm):
    """The known answers count only light that reaches the surface: under a
    sphere of radius 1 whose centre is 2 above a floor point, a cone of
    half-angle 30° is blocked, sin²30° = ¼ of the cosine-weighted
    hemisphere, so a constant map of radiance 1 gives 0.75 there (1 without
    the scene); the node values are 0 exactly where a ray hits the sphere."""
    from mcillum.integrators.quadrature import gp_scene as bh
    from mcillum.integrators.quadrature import gp_settings
    scene = mi.load_dict({"type": "scene", "sky": {"type": "constant"},
                          "ball": {"type": "sphere", "center": [0, 0, 2], "radius": 1.0}})
    env, up = scene.environment(), np.array([[0.0, 0.0, 1.0]])
    origin = bh.off_surface(np.zeros((1, 3)), up)
    assert bh.held_out_truth(env, up)[0] == pytest.approx(1.0, rel=1e-3)
    assert bh.held_out_truth(env, up, scene=scene, origins=origin)[0] == \
        pytest.approx(0.75, rel=5e-3)
    values = bh.held_out_values(env, up, 64, "cosine", 1, scene, origin)
    d = gp_settings.held_out_directions(up, 64, "cosine", 1, 64)
    blocked = d[..., 2] > np.cos(np.pi / 6)
    assert blocked.any() and (values[blocked] == 0).all() and (values[~blocked] == 1).all()


def test_held_out_normals_are_those_the_camera_sees(llvm):
    """On the lone sphere seen from +z the held-out normals are the visible
    ones, under the view's square of half-width 0.7 (z ≥ √(1 − 2·0.7²) =
    0.14, none beyond the square); where the camera sees no
    surface, directions over the whole sphere stand in."""
    from mcillum.integrators.quadrature import gp_scene as bh
    normals = bh.held_out_normals(lone_sphere(4, envmap="sg"))
    assert len(normals) == bh.HELD_OUT_NORMALS
    assert normals[:, 2].min() > 0.14 and np.abs(normals[:, :2]).max() < 0.7
    empty = mi.load_dict({"type": "scene", "sky": {"type": "constant"},
                          "sensor": {"type": "perspective",
                                     "film": {"type": "hdrfilm", "width": 4, "height": 4}}})
    assert bh.held_out_normals(empty)[:, 2].min() < -0.9


def test_bayesian_agrees_with_path_on_each_glossy_sphere_of_probe_spheres(llvm):
    """probe_spheres at max_depth 2 (rough gold and plastic on a ground,
    courtyard), N = 256: the mean over each sphere's pixels within 3 % of
    path's. With the settings chosen there the diffuse set of a glossy
    point (cosine nodes) differs from the other points' (uniform): nodes
    mapped by the wrong one put the plastic sphere 15 % off (measured
    before the fix: −14.6 %; after: +0.4 %)."""
    scene = renders.load_scene(scenes.path("probe_spheres"), res=16, max_depth=2)
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 8192, 2,
                first_seed=REFERENCE_SEED).mean(axis=0)[..., :3]
    integ = renders.make_integrator("bayesian_hemisphere", {"directions": 256, "max_depth": 2})
    got = batch(scene, integ, 128, 2).mean(axis=0)[..., :3]
    sensor = scene.sensors()[0]
    g = (np.arange(16) + 0.5) / 16
    x, y = [a.ravel() for a in np.meshgrid(g, g)]
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    flags = np.array(si.bsdf(ray).flags(), dtype=np.int64).reshape(16, 16)
    glossy = (flags & int(mi.BSDFFlags.Glossy)) != 0
    diffuse = (flags & int(mi.BSDFFlags.Diffuse)) != 0
    for name, on in (("gold (glossy only)", glossy & ~diffuse),
                     ("plastic (glossy and diffuse)", glossy & diffuse)):
        assert on.sum() > 8, name
        assert got[on].mean() == pytest.approx(ref[on].mean(), rel=0.03), name


def test_held_out_lobes_are_mirror_directions_with_the_bsdfs_exponent(llvm):
    """On lone_phong_sphere (orthographic along −z, exponent 30) each held-out
    axis is the camera ray mirrored about the sphere's normal, and the
    exponent read off the glossy density is the BSDF's own; under a constant
    map the lobe's held-out integral is that constant."""
    from mcillum.integrators.quadrature import gp_scene
    scene = phong_sphere(16, envmap="constant", exponent=30)
    axes, exponents, _ = gp_scene.held_out_lobes(scene)
    assert len(axes) == 64
    np.testing.assert_allclose(exponents, 30.0, rtol=1e-3)
    # r = d − 2(d·n)n for d = −z: the normal halves −d and r. The film spans
    # [−0.7, 0.7]² of the unit sphere, so the normals' x spreads as a uniform
    # grid there does (std 0.7/√3); a normal or a view direction returned
    # for r would give half of it or none.
    normals = (axes + [0, 0, 1]) / np.linalg.norm(axes + [0, 0, 1], axis=1, keepdims=True)
    assert normals[:, 0].std() == pytest.approx(0.7 / np.sqrt(3), rel=0.1)
    assert abs(normals[:, 0].mean()) < 0.05 and (normals[:, 2] > 0).all()
    truth = gp_scene.held_out_lobe_truth(scene.environment(), axes, 32.0)
    np.testing.assert_allclose(truth, environment_radiance(scene).mean(), rtol=1e-5)


@pytest.mark.parametrize("envmap, n, bound", [("sg", 16, 0.5), ("courtyard", 64, 1.0)])
def test_bayesian_defaults_beat_fibonacci_at_equal_rays(llvm, envmap, n, bound):
    """The issue's goal, on the lone sphere at equal rays: with the settings
    its rule chooses, bayesian_hemisphere's relMSE (less the reference's
    noise) over fibonacci_hemisphere's is below 0.5 under sg at N = 16 and
    below 1 under courtyard at N = 64, where maximum likelihood's ℓ = 0.10
    made it 18× worse at 64 spp. Measured at 16² px, 16 spp, 6 renders:
    0.21 under sg (3.3 with the maximum-likelihood ℓ, one fixed set) and
    0.90 under courtyard (4.8)."""
    scene = lone_sphere(16, envmap=envmap)
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 4096, 8,
                 first_seed=REFERENCE_SEED)
    ref, noise = path.mean(axis=0)[..., :3], (path.var(axis=0, ddof=1) / 8)[..., :3]
    floor = float(np.mean(noise / ref ** 2))

    def relmse(name):
        images = batch(scene, renders.make_integrator(name, {"directions": n}), 16, 6)
        return float(np.mean((images[..., :3] - ref) ** 2 / ref ** 2)) - floor

    ratio = relmse("bayesian_hemisphere") / relmse("fibonacci_hemisphere")
    assert ratio < bound, ratio


def test_the_settings_chosen_reach_results_and_report(llvm):
    """The quadrature stage records how bayesian_hemisphere chose its
    settings for the scene (every candidate scored, the choice among them);
    results.json keeps them within the schema, and the report draws the
    held-out error against ℓ with the choice marked. Settings given by the
    user are recorded as given, without candidates or chart."""
    import json
    import types

    import jsonschema

    from mcillum.validation import results
    from mcillum.validation.report import scenes as report_scenes
    from mcillum.validation.results import json_io
    from mcillum.validation.run import jobs
    from mcillum.validation.stages import quadrature

    scene = lone_sphere(8, envmap="gradient")
    ctx = types.SimpleNamespace(scene=scene, integrators={
        "auto": jobs.make("bayesian_hemisphere", {"directions": 16}),
        "given": jobs.make("bayesian_hemisphere", {"directions": 16, "length_scale": 0.5,
                                                   "noise": 0.01, "mapping": "uniform"})})
    auto, given = quadrature._settings(ctx, "auto", 64), quadrature._settings(ctx, "given", 64)
    assert auto.spp == 64 and "normals the camera sees" in auto.source
    scored = {(c.mapping, c.noise, c.length_scale): c.relmse for c in auto.candidates}
    assert len(scored) > 10 and (auto.mapping, auto.noise, auto.length_scale) in scored
    assert (given.source, given.mapping, given.noise, given.length_scale, given.candidates) \
        == ("given", "uniform", 0.01, 0.5, None)

    q = results.Quadrature(name="bayesian_hemisphere", directions=16, spp=64, renders=4,
                           settings=auto)
    item = json.loads(json.dumps(json_io.to_json(q), allow_nan=False, default=str))
    schema = json.load(open(results.SCHEMA_FILE))
    quad = schema["properties"]["scenes"]["items"]["properties"]["quadrature"]["items"]
    jsonschema.validate(item, quad)
    assert json_io.from_json(results.Quadrature, item).settings == auto
    html = report_scenes._settings(q, {"bayesian_hemisphere": "#8c564b"})
    assert "<svg" in html and f"ℓ = {auto.length_scale:.3g}" in html
    q.settings = given
    assert "<svg" not in report_scenes._settings(q, {"bayesian_hemisphere": "#8c564b"})
    assert auto.glossy is None and "glossy" not in item["settings"]


def test_the_glossy_sets_settings_reach_results_and_report(llvm):
    """On a glossy scene the settings of a glossy point's two sets are
    recorded too (the diffuse set's for its N − N_b nodes, the lobe set's
    in lobe widths with the exponent scored at), kept within the schema and
    read back, and the report says them."""
    import json
    import types

    import jsonschema

    from mcillum.integrators.quadrature import gp_settings
    from mcillum.validation import results
    from mcillum.validation.report import scenes as report_scenes
    from mcillum.validation.results import json_io
    from mcillum.validation.run import jobs
    from mcillum.validation.stages import quadrature

    ctx = types.SimpleNamespace(scene=phong_sphere(8, envmap="gradient", exponent=30),
                                integrators={"auto": jobs.make("bayesian_hemisphere",
                                                               {"directions": 16})})
    st = quadrature._settings(ctx, "auto", 16)
    g = st.glossy
    assert g.lobe_directions == 8 and g.lobe_exponent == pytest.approx(2 ** (20 / 4))
    assert g.lobe_length_scale in gp_settings.LOBE_LENGTH_SCALES and g.lobe_calibration > 0
    q = results.Quadrature(name="bayesian_hemisphere", directions=16, spp=16, renders=4,
                           settings=st)
    item = json.loads(json.dumps(json_io.to_json(q), allow_nan=False, default=str))
    schema = json.load(open(results.SCHEMA_FILE))
    jsonschema.validate(item, schema["properties"]["scenes"]["items"]["properties"]
                        ["quadrature"]["items"])
    assert json_io.from_json(results.Quadrature, item).settings.glossy == g
    html = report_scenes._settings(q, {"bayesian_hemisphere": "#8c564b"})
    assert "8 about the mirror direction" in html and "lobe widths" in html


def _calibration_medians(envmap: str) -> dict[int, float]:
    """spp → median over pixels of RMSE / predicted std, 6 renders of
    bayesian_hemisphere on the lone sphere at 16² px."""
    import types

    from mcillum.validation.stages import quadrature
    scene = lone_sphere(16, envmap=envmap)
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 4096, 8,
                 first_seed=REFERENCE_SEED)
    ref = types.SimpleNamespace(mean=path.mean(axis=0),
                                variance_of_mean=path.var(axis=0, ddof=1) / len(path))
    integ = renders.make_integrator("bayesian_hemisphere", {})
    medians = {}
    for spp in (16, 256):
        outs = [renders.render(scene, integ, spp, seed) for seed in range(6)]
        stack = stacks.Stack("bayesian_hemisphere", spp, np.array([o.image for o in outs]),
                             aovs={"posterior_std": np.array([o.aovs["posterior_std"]
                                                              for o in outs])})
        medians[spp] = quadrature._calibration(stack, ref).median
    return medians


@pytest.mark.parametrize("envmap", ["gradient", "courtyard"])
def test_bayesian_error_bars_are_calibrated_at_two_spp_16x_apart(llvm, envmap):
    """The posterior std predicts the error, whatever the spp: per pixel the
    RMSE of 6 renders over the predicted std has its median within
    [2/3, 3/2] at 16 and at 256 spp (the GP's own variance, before it was
    scaled on the held-out integrals: medians 0.49 under gradient, 0.51
    under courtyard in the full profile; measured now at 16² px: 0.90 and
    0.72 under gradient, 0.92 and 0.80 under courtyard. The bars widen
    relative to the error as spp grows: the held-out bias they are fitted
    to is that of one normal, a pixel's footprint averages a little of it).

    Measured in a fresh process: late in the test group this kernel (a
    camera-hit and a loop call site of the same virtual method) hit Dr.Jit
    1.5's duplicated-callable abort, "invalid redefinition of function",
    depending on which other objects the process still held."""
    import json
    import subprocess
    import sys
    here = os.path.dirname(os.path.abspath(__file__))
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import test_direction_sets as t; "
            "print(json.dumps(t._calibration_medians(sys.argv[2])))")
    done = subprocess.run([sys.executable, "-c", code, here, envmap], capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    medians = json.loads(done.stdout.strip().splitlines()[-1])
    assert all(2 / 3 <= m <= 3 / 2 for m in medians.values()), medians


@pytest.mark.slow
@pytest.mark.parametrize("alpha, sky", [
    (0.3, "courtyard"), (0.3, "constant"),
    pytest.param(0.1, "constant", marks=pytest.mark.xfail(strict=True, reason=(
        "a narrow GGX lobe under a constant map: -4.1 % at N = 256 (+2.9 % at 64, -21 % "
        "at 16): one Phong lobe cannot both hold its sharp peak and cover its tails "
        "(docs/measurements.md#2026-12-04-convergence-fit-ladder-cannot); under courtyard "
        "-1.6 %")))])
def test_bayesian_hemisphere_bias_goes_to_zero_on_a_ggx_lobe(llvm, alpha, sky):
    """A rough conductor with GGX's power-law tails, as a user's scene holds
    one: at N = 256 the image mean lies within convergence.BIAS_LIMIT (2 %)
    of `path`'s. With the lobe set's exponent read at the peak alone it did
    not (α 0.3: −6.6 % under courtyard, −7.1 % under a constant map); the
    exponent now covers the lobe's tails (phong.covering_exponent)."""
    from mcillum import envmaps
    from mcillum.validation.checks import convergence
    emitter = ({"type": "envmap", "filename": str(envmaps.resolve(sky)[0])} if sky != "constant"
               else {"type": "constant", "radiance": {"type": "rgb", "value": 0.8}})
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8,
                            "rfilter": {"type": "box"}}},
        "sphere": {"type": "sphere", "bsdf": {"type": "roughconductor", "distribution": "ggx",
                                              "alpha": alpha}},
        "sky": emitter})
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 2048, 8,
                first_seed=REFERENCE_SEED).mean(axis=0)[..., :3]
    x = batch(scene, renders.make_integrator("bayesian_hemisphere",
                                             {"directions": 256, "max_depth": 2}),
              16, 8).mean(axis=0)[..., :3]
    bias = float((x - ref).mean() / ref.mean())
    assert abs(bias) < convergence.BIAS_LIMIT, f"image mean {bias:+.2%} of path's"


def test_a_phong_lobe_covers_itself_and_a_ggx_lobe_is_widened(llvm):
    """phong.covering_exponent: for a Phong lobe the exponent its peak
    gives (its tails fall as cosⁿ exactly); for a GGX lobe of the same peak
    a smaller one (its tails fall as a power); a Beckmann lobe between."""
    from mcillum.integrators.bsdfs import phong
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.n, si.sh_frame = mi.Normal3f(0, 0, 1), mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(0, 0, 1)
    ctx, r = mi.BSDFContext(), mi.Vector3f(0, 0, 1)
    read = {}
    for name, props in (("phong", {"type": "phong", "exponent": 40.0,
                                   "diffuse_reflectance": 0.0, "specular_reflectance": 1.0}),
                        ("ggx", {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2}),
                        ("beckmann", {"type": "roughconductor", "alpha": 0.2})):
        bsdf = mi.load_dict(props)
        peak = bsdf.pdf(ctx, si, r)
        n = phong.covering_exponent(lambda w: bsdf.pdf(ctx, si, w), r, peak)
        read[name] = (float(dr.two_pi * peak[0] - 1.0), float(n[0]))
    assert read["phong"][1] == pytest.approx(read["phong"][0], rel=1e-4), read
    assert read["ggx"][1] < 0.5 * read["ggx"][0], read
    assert read["ggx"][1] / read["ggx"][0] < read["beckmann"][1] / read["beckmann"][0] < 1, read
