"""bayesian_importance: Bayesian cubature on a randomly shifted rank-1 lattice
pushed through the environment map's and the BSDF's sampling.

What is tested: the lattice (its generator is the Fibonacci lattice's where
that is known best); every node of the light's set is distributed by the
map's own pdf (χ², what makes the estimate unbiased) while an unshifted node
is not; unbiased per pixel against `path` under a sun, a sky with a ground
and glossy Phong lobes, and against the exact answer of a furnace in the
scalar and llvm variants; its broken twins (every weight 5 % low, the
lattice never shifted) are rejected by the same test and budget; the issue's
goal at equal rays against emitter_sampling under the sunrise and city
probes; what it refuses.
"""

from __future__ import annotations

import numpy as np
import pytest

import mcillum  # noqa: F401
import drjit as dr
import mitsuba as mi

from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.validation.stats import metrics, statistics

import twins
from conftest import VARIANTS, batch, small

NAME = "bayesian_importance"
ALPHA = 0.01
REFERENCE_SEED = 10_000


def lone_sphere(res, envmap="constant"):
    return renders.load_scene(scenes.path("lone_sphere"), res=res, envmap=envmap)


def _module():
    from mcillum.integrators.quadrature import bayesian_importance
    return bayesian_importance


# ------------------------------ The lattice ----------------------------------

def _gap(n, g):
    """The squared distance between the nearest two points of the lattice
    (1, g)/n on the torus, in units of 1/n."""
    j = np.arange(1, n)
    y = (j * g) % n
    return float(np.min(np.minimum(j, n - j) ** 2 + np.minimum(y, n - y) ** 2)) / n


@pytest.mark.parametrize("n, fibonacci", [(13, 8), (21, 13), (34, 21), (55, 34), (89, 55),
                                          (144, 89)])
def test_generator_spaces_points_at_least_as_the_fibonacci_lattice(llvm, n, fibonacci):
    """Where n is a Fibonacci number F_k the lattice (1, F_k-1)/n is the
    classic choice; the search over every g finds one at least as well
    spaced (equal for 13, 34, 89; wider for 55 and 144)."""
    g = _module().lattice_generator(n)
    assert np.gcd(g, n) == 1
    assert _gap(n, g) >= _gap(n, fibonacci) - 1e-12
    assert _gap(n, g) > _gap(n, 1)                     # (not the diagonal)


@pytest.mark.parametrize("n", [16, 48, 64, 100])
def test_lattice_holds_every_row_and_column_once(llvm, n):
    """A rank-1 lattice with g coprime to n: its n points fall in n distinct
    rows and n distinct columns of the n × n grid (a Latin square)."""
    b = _module()
    u = np.array(b.lattice_point(mi.UInt32(np.arange(n)), n, b.lattice_generator(n),
                                 mi.Point2f(0.0, 0.0)))
    for axis in (0, 1):
        assert len(set(np.floor(u[axis] * n + 1e-3).astype(int))) == n


def _chi2_light(env, j, n, shifted=True, n_points=1 << 18):
    """mi.chi2's test of node j of the light's n-point lattice, over random
    shifts, against the map's own pdf_direction."""
    b = _module()
    g = b.lattice_generator(n)
    it = dr.zeros(mi.Interaction3f)

    def sample(u):
        shift = u if shifted else mi.Point2f(0.0, u.y)   # (negative control: ξ₁ = 0)
        jj = j if shifted else dr.floor(u.x * n)
        return env.sample_direction(it, b.lattice_point(mi.UInt32(jj), n, g, shift))[0].d

    def pdf(w):
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = w
        return env.pdf_direction(it, ds)

    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=2, sample_count=n_points,
                                 res=32, ires=16, seed=7)
    return test.run(0.01)


@pytest.mark.parametrize("j, n", [(0, 16), (11, 16), (40, 64)])
def test_a_shifted_node_of_the_light_set_follows_the_maps_pdf(llvm, j, n):
    env = lone_sphere(4, envmap="gradient").environment()
    assert _chi2_light(env, j, n)


def test_an_unshifted_lattice_does_not_follow_the_maps_pdf(llvm):
    """Negative control: the lattice shifted along one axis only (a random
    node of it, ξ₁ = 0) puts the map's marginal on n values: χ² rejects it."""
    env = lone_sphere(4, envmap="gradient").environment()
    assert not _chi2_light(env, 0, 16, shifted=False)


# ---------------------- Unbiased: per pixel, and exactly ----------------------

#: case → (scene, defines, res, camera spp per render, renders K, directions)
AGREEMENT = {
    "lone_sphere_sunrise": ("lone_sphere", {"envmap": "sunrise"}, 16, 4, 16, 16),
    "sky_sphere": ("sky_sphere", {}, 16, 8, 16, 16),
    "phong_spheres": ("phong_spheres", {}, 8, 64, 16, 16),
}


def _stacks(case, integrator):
    name, defines, res, spp, k, n = AGREEMENT[case]
    scene = renders.load_scene(scenes.path(name), res=res, **defines)
    est = batch(scene, integrator, spp, k)
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 2}), spp * n, k,
                first_seed=REFERENCE_SEED)
    return est, ref


@pytest.mark.parametrize("case", AGREEMENT)
def test_agrees_with_path_per_pixel(llvm, case):
    n = AGREEMENT[case][-1]
    est, ref = _stacks(case, renders.make_integrator(NAME, {"directions": n}))
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()


@pytest.mark.parametrize("case", AGREEMENT)
@pytest.mark.parametrize("kind", ["set_weight_low", "unshifted_set"])
def test_twins_are_rejected(llvm, case, kind):
    """Every direction's weight 5 % low, and the lattices never shifted (the
    same directions at every shading point): the same test and budget reject
    both."""
    n = AGREEMENT[case][-1]
    est, ref = _stacks(case, twins.integrator(kind, NAME, {"directions": n}))
    result = statistics.compare(est, ref, ALPHA)
    assert not result.passed, f"{twins.TWINS[kind].bug} was accepted: " + result.summary()


@pytest.mark.parametrize("variant_name", VARIANTS)
def test_furnace_mean_is_rho_L_in_every_variant(use_variant, variant_name):
    """Constant map, lone diffuse sphere: the answer is ρL at every pixel;
    each render's image mean, over K renders, is within 4 standard errors of
    it (the estimate is not exact here: the mixture pdf is not ∝ cos θ)."""
    use_variant(variant_name)
    scene = lone_sphere(small(variant_name, 2, 8))
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = mi.Vector3f(0, 0, -1)
    expected = np.array([0.8, 0.6, 0.4]) * np.array(scene.environment().eval(si)).ravel()
    xml = mi.load_string(f'<integrator version="3.0.0" type="{NAME}">'
                         '<integer name="directions" value="8"/></integrator>')
    means = np.array([renders.render(scene, xml, 4, seed=s).image[..., :3].mean(axis=(0, 1))
                      for s in range(6)])
    se = means.std(axis=0, ddof=1) / np.sqrt(len(means))
    assert np.all(np.abs(means.mean(axis=0) - expected) < 4 * se + 1e-6 * expected), \
        (means.mean(axis=0), expected, se)
    assert np.all(se > 0)           # (an estimate, not a copy of the answer)


# --------------------- The goal: a sun at equal rays ---------------------

def _equal_ray_ratio(scene, own, other) -> float:
    """relMSE of 6 renders of ``own`` over that of ``other`` (each a
    (name, params, spp)), each less the reference's own noise (the suite's
    metrics; reference: `path`, 8 × 4096 spp)."""
    path = batch(scene, renders.make_integrator("path", {"max_depth": 2}), 4096, 8,
                 first_seed=REFERENCE_SEED)
    ref = path.mean(axis=0)
    floor = metrics.reference_relmse(ref, path.var(axis=0, ddof=1) / len(path))

    def relmse(name, params, spp):
        images = batch(scene, renders.make_integrator(name, params), spp, 6)
        return float(metrics.per_render_relmse(images, ref).mean()) - floor

    return relmse(*own) / relmse(*other)

@pytest.mark.parametrize("envmap", ["sunrise", "city"])
def test_beats_emitter_sampling_at_equal_rays_under_a_sun(llvm, envmap):
    """Lone sphere, direct light, N = 16 directions × 4 spp against
    emitter_sampling at 64 spp: relMSE (less the reference's noise) ≤ 0.7×.
    Measured at 32² px, 8 renders: 0.27 (sunrise), 0.24 (city)."""
    scene = lone_sphere(16, envmap=envmap)
    ratio = _equal_ray_ratio(scene, (NAME, {"directions": 16}, 4),
                             ("emitter_sampling", {"max_depth": 2}, 64))
    assert ratio < 0.7, ratio


# ------------------------------- Refusals ------------------------------------

@pytest.mark.parametrize("props, match", [
    ({"light_fraction": 1.5}, "light_fraction must be a number in"),
    ({"light_fraction": "half"}, "light_fraction must be a number in"),
    ({"directions": 0}, "directions must be an integer"),
    ({"max_depth": 3}, "max_depth = 3 is not supported"),
    ({"directions": 65536}, "the largest lattice whose j·g fits 32 bits"),
])
def test_bad_parameters_are_refused(llvm, props, match):
    with pytest.raises(Exception, match=match):
        mi.load_dict({"type": NAME, **props})


def test_delta_lights_are_refused(llvm):
    scene = renders.load_scene(scenes.path("point_light"), res=4)
    with pytest.raises(mcillum.integrators.UnreachableContentError, match="delta emitter"):
        renders.make_integrator(NAME, {"max_depth": 2}).check_scene(scene)


def test_all_of_n_on_the_map_is_refused_where_area_lights_shine(llvm):
    scene = mi.load_dict({
        "type": "scene", "sphere": {"type": "sphere"},
        "light": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 3]),
                  "emitter": {"type": "area"}},
        "sky": {"type": "constant"},
        "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4,
                                                     "height": 4}}})
    one = renders.make_integrator(NAME, {"light_fraction": 1.0})
    with pytest.raises(ValueError, match="only the BSDF's set finds"):
        one.check_scene(scene)
    half = renders.make_integrator(NAME, {})
    half.check_scene(scene)
    assert (half.n_light, half.n_bsdf) == (32, 32)


def test_without_a_map_every_direction_follows_the_bsdf(llvm):
    scene = renders.load_scene(scenes.path("cornell_box"), res=4)
    est = renders.make_integrator(NAME, {"directions": 16, "max_depth": 2})
    est.check_scene(scene)
    assert (est.n_light, est.n_bsdf) == (0, 16)


# ------------------------- In the quadrature stage ----------------------------

def test_the_quadrature_stage_compares_it_with_emitter_sampling(llvm, tmp_path):
    """The scene-comparison stages on the lone sphere under sunrise: the
    equal-ray pair is against its facts' baseline, emitter_sampling (both
    sample the light), and the point set wins it; the report names the
    baseline per row. fibonacci_hemisphere keeps cosine_hemisphere."""
    from mcillum.integrators.core import registry
    from mcillum.validation import pipeline
    from mcillum.validation.plan import profiles
    from mcillum.validation.report import scenes as report_scenes
    from mcillum.validation.stages import common
    from mcillum.validation.stages.context import Context, Run

    assert registry.facts(NAME).equal_rays_baseline == "emitter_sampling"
    assert registry.facts("fibonacci_hemisphere").equal_rays_baseline == "cosine_hemisphere"
    profile = profiles.Profile(name="quick", runs=(), reference_max_seconds=30.0)
    plan = profiles.SceneRun(scene="lone_sphere", res=8, ladder=(4,), renders=4, max_depth=2,
                             defines={"envmap": "sunrise"})
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out")),
                  plan, "lone_sphere", [NAME, "path"])
    common.load(ctx)
    common.choose_estimators(ctx)
    for stage in (pipeline.scene.render_ladder, common.build_reference,
                  pipeline.quadrature.measure):
        stage(ctx)
    rays = ctx.quadrature[NAME].equal_rays
    assert rays.baseline == "emitter_sampling" and rays.baseline_spp == 64 * 4
    assert rays.ratio_high < 1.0, rays

    class _Scene:
        quadrature = [ctx.quadrature[NAME]]
    html = report_scenes._quadrature_section(_Scene, {NAME: "#393b79"})
    assert "<code>emitter_sampling</code>" in html


# ------------------ Glossy lobes: against the Fibonacci sets -------------------

@pytest.mark.parametrize("envmap, exponent", [("sg", 10), ("courtyard", 100)])
def test_beats_fibonacci_on_a_phong_sphere_at_equal_rays(llvm, envmap, exponent):
    """The issue's glossy goal, on lone_phong_sphere at N = 16 (both at
    4 spp): relMSE (less the reference's noise) ≤ 0.7× fibonacci_hemisphere's.
    Measured at 32² px, 8 renders: 0.19–0.22 for exponents 10, 30, 100
    under sg and courtyard at 4 and 64 spp."""
    scene = renders.load_scene(scenes.path("lone_phong_sphere"), res=16, envmap=envmap,
                               exponent=exponent)
    ratio = _equal_ray_ratio(scene, (NAME, {"directions": 16}, 4),
                             ("fibonacci_hemisphere", {"directions": 16}, 4))
    assert ratio < 0.7, ratio


def test_keeps_no_emitter_after_rendering(llvm):
    """An integrator that held the scene's map after rendering kept that
    emitter in Dr.Jit's registry: every later kernel's virtual calls then
    dispatched over it too, and in the default test group one of them hit
    Dr.Jit 1.5's duplicated-callable abort ("invalid redefinition of
    function"). Nothing of the scene stays on the integrator."""
    scene = lone_sphere(4, envmap="gradient")
    integ = renders.make_integrator(NAME, {"directions": 4})
    renders.render(scene, integ, 1)
    held = [k for k, v in vars(integ).items() if isinstance(v, (mi.Emitter, mi.Scene, mi.Shape))]
    assert not held, held
