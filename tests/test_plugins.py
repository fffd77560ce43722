"""Plugin behaviour: registration, XML use, parameters, refusals, variants."""

import numpy as np
import pytest

import mitsuba as mi

from mcillum import integrators
from mcillum.integrators.scene_checks import UnreachableContentError
from mcillum.validation import renders, statistics

from conftest import ESTIMATORS, SCENES


def tiny_scene(**items):
    """A 2x2 camera looking down at whatever ``items`` add."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=[0, 3, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 2, "height": 2,
                            "rfilter": {"type": "box"}}},
        **items,
    })


def disk(bsdf):
    return {"type": "disk", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),
            "bsdf": bsdf}


def render(scene, name, **params):
    return renders.render(scene, renders.make_integrator(name, params), spp=2)


def refusal(scene, name) -> UnreachableContentError:
    with pytest.raises(Exception) as info:
        render(scene, name)
    cause = renders.root_cause(info.value)  # mi.render wraps it in llvm variants
    assert isinstance(cause, UnreachableContentError), repr(cause)
    return cause


# ----------------------------- Registration ---------------------------------

def test_import_registers_for_current_variant_and_follows_switches(variant):
    for name in ESTIMATORS:
        integrator = mi.load_dict({"type": name})
        assert isinstance(integrator, mi.SamplingIntegrator)  # this variant's base
    assert integrators.register() == variant  # idempotent


def test_register_without_variant_callback_after_switch():
    renders.set_variant("scalar_rgb")
    mi.detail.remove_variant_callback(integrators._on_variant_change)
    try:
        mi.set_variant("llvm_ad_rgb")
        integrators.register()
        assert isinstance(mi.load_dict({"type": "cosine_hemisphere"}), mi.SamplingIntegrator)
    finally:
        mi.detail.add_variant_callback(integrators._on_variant_change)


def test_plain_mitsuba_xml(variant):
    scene = mi.load_string("""
        <scene version="3.0.0">
            <integrator type="cosine_hemisphere">
                <integer name="max_depth" value="2"/>
            </integrator>
            <sensor type="perspective">
                <film type="hdrfilm"><integer name="width" value="2"/>
                    <integer name="height" value="2"/></film>
            </sensor>
            <emitter type="constant"><float name="radiance" value="1"/></emitter>
        </scene>""")
    integrator = scene.integrator()
    assert integrator.max_depth == 2 and "max_depth=2" in integrator.to_string()
    image = np.array(mi.render(scene, spp=1))
    np.testing.assert_allclose(image, 1.0, rtol=1e-6)  # only the environment


@pytest.mark.parametrize("name", ESTIMATORS)
def test_defaults_follow_path(variant, name):
    integrator = mi.load_dict({"type": name})
    assert integrator.max_depth == 0xFFFFFFFF and integrator.rr_depth == 5
    assert integrator.hide_emitters is False


# ---------------------------- Bad parameters --------------------------------

@pytest.mark.parametrize("name", ESTIMATORS)
@pytest.mark.parametrize("params, message", [
    ({"foo": 3}, "foo"),
    ({"max_depth": -2}, "max_depth = -2 is invalid"),
    ({"rr_depth": 0}, "rr_depth = 0 is invalid"),
    ({"rr_depth": -1}, "rr_depth = -1 is invalid"),
    ({"max_depth": "two"}, "max_depth"),
])
def test_bad_parameters_are_load_errors(variant, name, params, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": name, **params})


@pytest.mark.parametrize("name", ESTIMATORS)
def test_max_depth_zero_is_black_like_path(variant, name):
    scene = tiny_scene(env={"type": "constant"})
    assert np.all(render(scene, name, max_depth=0).image == 0)
    assert np.all(render(scene, "path", max_depth=0).image == 0)


# ------------------------------- Refusals -----------------------------------

LIGHT = {"type": "constant"}
DELTA_EMITTERS = {  # (built lazily: transforms need the current variant)
    "point": lambda: {"type": "point", "position": [0, 1, 0]},
    "spot": lambda: {"type": "spot", "to_world": mi.ScalarTransform4f().look_at(
        origin=[0, 2, 0], target=[0, 0, 0], up=[0, 0, 1])},
    "directional": lambda: {"type": "directional", "direction": [0, -1, 0]},
}
UNREACHABLE_BSDFS = {
    # BSDF → problem kinds it must trigger
    "conductor": ({"type": "conductor"}, {"delta_bsdf"}),
    "dielectric": ({"type": "dielectric"}, {"delta_bsdf", "transmission"}),
    "thindielectric": ({"type": "thindielectric"}, {"delta_bsdf", "transmission"}),
    "plastic": ({"type": "plastic"}, {"delta_bsdf"}),
    "roughdielectric": ({"type": "roughdielectric", "alpha": 0.3}, {"transmission"}),
    "mask": ({"type": "mask", "opacity": 0.5, "bsdf": {"type": "diffuse"}}, {"transmission"}),
    "twosided conductor": ({"type": "twosided", "bsdf": {"type": "conductor"}}, {"delta_bsdf"}),
    # near-delta: Mitsuba clamps alpha=0 to 1e-4 and sets no Delta flag
    "roughconductor alpha 0": ({"type": "roughconductor", "alpha": 0.0}, {"delta_bsdf"}),
    "twosided roughconductor alpha 1e-3": (
        {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 1e-3}}, {"delta_bsdf"}),
    "principled roughness 0": ({"type": "principled", "roughness": 0.0}, {"delta_bsdf"}),
    "principled glossy clearcoat": ({"type": "principled", "roughness": 0.5, "clearcoat": 1.0,
                                     "clearcoat_gloss": 1.0}, {"delta_bsdf"}),
}
REACHABLE_BSDFS = {
    "diffuse": {"type": "diffuse"},
    "roughconductor": {"type": "roughconductor", "alpha": 0.2},
    "roughplastic": {"type": "roughplastic", "alpha": 0.2},
    "twosided diffuse": {"type": "twosided", "bsdf": {"type": "diffuse"}},
    "roughconductor alpha 0.01": {"type": "roughconductor", "alpha": 0.01},
    "principled": {"type": "principled", "roughness": 0.3, "metallic": 0.5},
}


@pytest.mark.parametrize("name", ESTIMATORS)
@pytest.mark.parametrize("kind", DELTA_EMITTERS)
def test_refuses_delta_emitters(variant, name, kind):
    scene = tiny_scene(floor=disk({"type": "diffuse"}), key_light=DELTA_EMITTERS[kind]())
    error = refusal(scene, name)
    assert [p.kind for p in error.problems] == ["delta_emitter"]
    assert "'key_light'" in str(error) and "area emitter" in str(error)
    assert f"'{name}'" in str(error) and "'path'" in str(error)


@pytest.mark.parametrize("name", ESTIMATORS)
@pytest.mark.parametrize("kind", UNREACHABLE_BSDFS)
def test_refuses_delta_and_transmissive_bsdfs(variant, name, kind):
    bsdf, expected = UNREACHABLE_BSDFS[kind]
    scene = tiny_scene(shiny=disk({**bsdf, "id": "shiny_bsdf"}), env=LIGHT)
    error = refusal(scene, name)
    assert {p.kind for p in error.problems} == expected
    assert "shape 'shiny'" in str(error) and "'shiny_bsdf'" in str(error)


def test_refuses_content_nested_in_instances(variant):
    scene = tiny_scene(
        group={"type": "shapegroup",
               "ball": {"type": "sphere", "bsdf": {"type": "dielectric", "id": "glass"}}},
        copy={"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
        env=LIGHT)
    for name in ESTIMATORS:
        error = refusal(scene, name)
        assert "shape 'ball' with BSDF 'glass' (SmoothDielectric)" in str(error)


@pytest.mark.parametrize("scene_file, culprit", [
    ("point_light.xml", "'key_light' (PointLight)"),
    ("smooth_glass.xml", "shape 'glass_ball'"),
])
def test_bundled_refusal_scenes(variant, scene_file, culprit):
    scene = renders.load_scene(SCENES / scene_file, res=2)
    for name in ESTIMATORS:
        assert culprit in str(refusal(scene, name))
    assert np.isfinite(render(scene, "path").image).all()  # path renders it


@pytest.mark.parametrize("kind", REACHABLE_BSDFS)
def test_accepts_rough_and_diffuse_bsdfs(variant, kind):
    scene = tiny_scene(floor=disk(REACHABLE_BSDFS[kind]), env=LIGHT)
    for name in ESTIMATORS:
        image = render(scene, name).image
        assert np.isfinite(image).all() and (image >= 0).all()


# ------------------------------- Variants -----------------------------------

@pytest.mark.parametrize("other", ["llvm_ad_spectral", "llvm_ad_mono"])
def test_spectral_and_mono_variants_render_the_furnace(other):
    """Furnace sphere in other colour modes: sphere = ρ × background.

    Spectral renders sample wavelengths at random, so even the cosine
    estimator is noisy there; per render d = mean(sphere) − ρ·mean(background),
    and 0 must lie in the 99.9% Student-t interval of d over 8 renders.
    """
    from test_analytic import disk_masks

    albedo = 0.5
    renders.set_variant(other)
    try:
        scene = renders.load_scene(SCENES / "furnace_sphere.xml", res=8, albedo=albedo)
        inside, outside = disk_masks(8)
        for name in ESTIMATORS:
            integrator = renders.make_integrator(name)
            d = []
            for seed in range(8):
                image = renders.render(scene, integrator, 64, seed).image.mean(axis=-1)
                assert np.isfinite(image).all() and (image >= 0).all()
                d.append(image[inside].mean() - albedo * image[outside].mean())
            mean, half = statistics.mean_interval(np.array(d), 0.001)
            assert abs(mean) <= half + 1e-5, f"{name}: {mean:.2e} ± {half:.2e}"
    finally:
        renders.set_variant("llvm_ad_rgb")


def test_polarized_variant_is_refused_clearly():
    renders.set_variant("llvm_ad_mono_polarized")
    try:
        for name in ESTIMATORS:
            with pytest.raises(Exception, match="does not track polarization"):
                mi.load_dict({"type": name})
    finally:
        renders.set_variant("llvm_ad_rgb")


# ------------------------- allow_unreachable opt-in --------------------------

@pytest.mark.parametrize("name", ESTIMATORS)
def test_refusal_names_the_opt_in(llvm, name):
    scene = tiny_scene(floor=disk({"type": "diffuse"}),
                       key_light=DELTA_EMITTERS["point"]())
    assert 'allow_unreachable" value="true"' in str(refusal(scene, name))


@pytest.mark.parametrize("name", ESTIMATORS)
def test_allow_unreachable_renders_the_biased_image_and_says_what_it_lacks(llvm, name):
    # A diffuse disk under a point light and a dim environment: the opt-in
    # image holds only the environment's share, measurably below path's.
    dim = {"type": "constant", "radiance": {"type": "rgb", "value": 0.1}}
    scene = tiny_scene(floor=disk({"type": "diffuse"}), env=dim,
                       key_light={**DELTA_EMITTERS["point"](), "intensity": 10.0})
    integrator = renders.make_integrator(name, {"allow_unreachable": True, "max_depth": 2})
    biased = renders.render(scene, integrator, 256).image
    unbiased = renders.render(scene, renders.make_integrator("path", {"max_depth": 2}),
                              256).image
    assert np.isfinite(biased).all() and biased.min() >= 0
    assert [p.kind for p in integrator.unreachable] == ["delta_emitter"]
    assert "'key_light'" in integrator.unreachable[0].what
    assert biased.mean() < 0.8 * unbiased.mean()
    # and a scene it can reach leaves the list empty again
    renders.render(tiny_scene(floor=disk({"type": "diffuse"}), env=LIGHT), integrator, 1)
    assert integrator.unreachable == []


def test_allow_unreachable_must_be_a_boolean(llvm):
    with pytest.raises(Exception, match="allow_unreachable must be a boolean"):
        renders.make_integrator("cosine_hemisphere", {"allow_unreachable": "yes"})


@pytest.mark.slow
def test_scalar_variant_survives_a_zero_pdf_direction():
    """A sampled direction exactly on the horizon has pdf 0; scalar variants
    divide Python floats, which raised ZeroDivisionError (cornell_box, 128²,
    64 spp, seed 0 hit one)."""
    renders.set_variant("scalar_rgb")
    scene = renders.load_scene(SCENES / "cornell_box.xml", res=128)
    image = renders.render(scene, renders.make_integrator("cosine_hemisphere"), 64, 0).image
    assert np.isfinite(image).all()
