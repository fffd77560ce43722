"""What an estimator refuses, and that it refuses nothing else.

A continuous pdf over the reflection hemisphere never samples a delta light, a
delta lobe or transmission. Each estimator declares in its registry facts
which of these it reaches anyway; on a scene holding any other it must raise
UnreachableContentError when the render starts, naming the object and a
remedy, unless the user opts into the biased image (allow_unreachable)."""

import numpy as np
import pytest

import mitsuba as mi

from mcillum.integrators import UnreachableContentError
from mcillum.integrators.core import registry
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.errors import root_cause

from conftest import ALL_ESTIMATORS, disk, render, tiny_scene


def refusal(scene, name) -> UnreachableContentError:
    with pytest.raises(Exception) as info:
        render(scene, name)
    cause = root_cause(info.value)  # mi.render wraps it in llvm variants
    assert isinstance(cause, UnreachableContentError), repr(cause)
    return cause


def missing(name: str, kinds) -> set:
    """The kinds among ``kinds`` that estimator ``name`` does not reach."""
    return set(kinds) - set(registry.facts(name).reaches)


def renders_finite(scene, name):
    image = render(scene, name).image
    assert np.isfinite(image).all() and (image >= 0).all()


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


@pytest.mark.parametrize("name", ALL_ESTIMATORS)
@pytest.mark.parametrize("kind", DELTA_EMITTERS)
def test_delta_emitters_are_refused_by_those_that_cannot_reach_them(variant, name, kind):
    scene = tiny_scene(floor=disk({"type": "diffuse"}), key_light=DELTA_EMITTERS[kind]())
    if not missing(name, {"delta_emitter"}):
        return renders_finite(scene, name)
    error = refusal(scene, name)
    assert [p.kind for p in error.problems] == ["delta_emitter"]
    assert "'key_light'" in str(error) and "area emitter" in str(error)
    assert f"'{name}'" in str(error) and "'path'" in str(error)


@pytest.mark.parametrize("name", ALL_ESTIMATORS)
@pytest.mark.parametrize("kind", UNREACHABLE_BSDFS)
def test_delta_and_transmissive_bsdfs_are_refused_by_those_that_cannot_reach_them(
        variant, name, kind):
    bsdf, expected = UNREACHABLE_BSDFS[kind]
    scene = tiny_scene(shiny=disk({**bsdf, "id": "shiny_bsdf"}), env=LIGHT)
    if not missing(name, expected):
        return renders_finite(scene, name)
    error = refusal(scene, name)
    assert {p.kind for p in error.problems} == missing(name, expected)
    assert "shape 'shiny'" in str(error) and "'shiny_bsdf'" in str(error)


def test_content_nested_in_instances_is_found(variant):
    scene = tiny_scene(
        group={"type": "shapegroup",
               "ball": {"type": "sphere", "bsdf": {"type": "dielectric", "id": "glass"}}},
        copy={"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
        env=LIGHT)
    refusing = [n for n in ALL_ESTIMATORS if missing(n, {"delta_bsdf", "transmission"})]
    assert refusing
    for name in refusing:
        error = refusal(scene, name)
        assert "shape 'ball' with BSDF 'glass' (SmoothDielectric)" in str(error)


@pytest.mark.parametrize("scene_name, culprit", [
    ("point_light", "'key_light' (PointLight)"),
    ("smooth_glass", "shape 'glass_ball'"),
])
def test_bundled_refusal_scenes(variant, scene_name, culprit):
    """Exactly the estimators whose facts lack a kind the scene header
    declares ("Contains:") refuse it, naming the culprit; path renders it."""
    info = scenes.index()[scene_name]
    scene = renders.load_scene(info.path, res=2)
    refusing = [n for n in ALL_ESTIMATORS if missing(n, info.contains)]
    assert refusing and len(refusing) < len(ALL_ESTIMATORS)
    for name in ALL_ESTIMATORS:
        if name in refusing:
            assert culprit in str(refusal(scene, name))
        else:
            renders_finite(scene, name)
    renders_finite(scene, "path")


@pytest.mark.parametrize("kind", REACHABLE_BSDFS)
def test_rough_and_diffuse_bsdfs_are_accepted(variant, kind):
    scene = tiny_scene(floor=disk(REACHABLE_BSDFS[kind]), env=LIGHT)
    for name in ALL_ESTIMATORS:
        renders_finite(scene, name)


# ------------------------- allow_unreachable opt-in --------------------------

POINT_LIGHT_REFUSERS = [n for n in ALL_ESTIMATORS if missing(n, {"delta_emitter"})]


@pytest.mark.parametrize("name", POINT_LIGHT_REFUSERS)
def test_refusal_names_the_opt_in(llvm, name):
    scene = tiny_scene(floor=disk({"type": "diffuse"}),
                       key_light=DELTA_EMITTERS["point"]())
    assert 'allow_unreachable" value="true"' in str(refusal(scene, name))


@pytest.mark.parametrize("name", POINT_LIGHT_REFUSERS)
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
