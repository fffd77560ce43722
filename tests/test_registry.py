"""The estimator registry: every plugin declares its facts, and the registry
alone tells profiles, charts, the failures group, scene selection and the
tests which estimators exist. A throw-away estimator class, registered and
nothing else, appears in all of them."""

import math
import re

import pytest

import drjit as dr
import mitsuba as mi

from mcillum.integrators.core import registry
from mcillum.integrators.core.scene_checks import KINDS
from mcillum.validation import pipeline, results
from mcillum.validation.plan import profiles, scenes
from mcillum.validation.report import charts
from mcillum.validation.stages import sun_split

import conftest
import twins


def test_every_estimator_declares_its_facts(llvm):
    names = registry.names()
    assert names == ["uniform_hemisphere", "cosine_hemisphere", "bsdf_sampling",
                     "emitter_sampling", "mis", "guided_path", "fibonacci_hemisphere",
                     "bayesian_hemisphere", "bayesian_importance"]
    colours = [registry.facts(n).colour for n in names] + [registry.PATH.colour]
    assert all(re.fullmatch(r"#[0-9a-f]{6}", c) for c in colours)
    assert len(set(colours)) == len(colours), "two estimators share a colour"
    for n in names:
        f = registry.facts(n)
        assert f.display_name and f.display_name != n
        assert set(f.reachable) <= set(KINDS) and "medium" in f.unreachable
    # the estimators of N directions: direct light only; the GP quadrature
    # is biased by design (the lattice cubature is unbiased: equal weights,
    # randomly shifted); every one reaches glossy lobes
    assert [registry.facts(n).depths for n in names] == [None] * 6 + [(1, 2)] * 3
    assert [registry.facts(n).unbiased for n in names] == [True] * 7 + [False, True]
    assert not any("glossy_bsdf" in registry.facts(n).unreachable for n in names)


def test_largest_direction_pdfs_are_the_strategies_own(llvm):
    """p(ω) = 1/2π (uniform), at most 1/π (cosine); None where the BSDF or
    next-event estimation decides."""
    assert registry.facts("uniform_hemisphere").max_direction_pdf == pytest.approx(
        1 / (2 * math.pi))
    assert registry.facts("cosine_hemisphere").max_direction_pdf == pytest.approx(1 / math.pi)
    for n in ("bsdf_sampling", "emitter_sampling", "mis", "guided_path"):
        assert registry.facts(n).max_direction_pdf is None


def test_scenes_are_rendered_by_exactly_the_estimators_that_reach_them(llvm):
    """point_light holds a delta light, smooth_glass delta lobes and
    transmission: the facts pick the estimators that render each."""
    index = scenes.index()

    def rendering(scene):
        return [n for n in [*registry.names(), "path"]
                if registry.facts(n).renders(index[scene].contains)]

    assert rendering("point_light") == ["emitter_sampling", "mis", "guided_path", "path"]
    assert rendering("smooth_glass") == ["bsdf_sampling", "mis", "guided_path", "path"]
    assert rendering("cornell_box") == [*registry.names(), "path"]
    assert rendering("probe_spheres") == [*registry.names(), "path"]   # glossy lobes


@pytest.fixture
def throwaway(llvm):
    """A new estimator, added the way a plugin file adds one."""
    base = type(mi.load_dict({"type": "cosine_hemisphere"}))

    class Throwaway(base):
        plugin_name = "throwaway_estimator"
        display_name = "a throw-away estimator"
        colour = "#123456"
        reachable = frozenset({"delta_emitter"})
        max_direction_pdf = 0.25
        listing_order = 25

    registry.register(Throwaway)
    yield "throwaway_estimator"
    registry.unregister("throwaway_estimator")


def test_a_new_estimator_appears_everywhere_without_other_edits(throwaway):
    # profiles: every profile compares it, in its listing order, before path
    for profile in profiles.PROFILES.values():
        names = profile.estimator_names()
        assert throwaway in names and names[-1] == "path"
        assert names.index(throwaway) == names.index("cosine_hemisphere") + 1
    # tests: the lists they parametrise over
    assert throwaway in conftest.estimators()
    assert throwaway in conftest.hemisphere_estimators()
    # broken twins: those its strategy admits, and they build and load
    assert twins.cases([throwaway], tuple(twins.TWINS)) == [
        (throwaway, k) for k in ("pdf_high", "glossy_dropped", "region_dark", "black")]
    w = mi.Vector3f(0.6, 0.0, 0.8)
    assert dr.allclose(twins.integrator("pdf_high", throwaway).pdf_local(w),
                       1.05 * twins.plugin_class(throwaway).pdf_local(w))
    # scenes: it renders the point light (it reaches delta lights), unlike
    # the estimator it derives from
    contains = scenes.index()["point_light"].contains
    assert registry.facts(throwaway).renders(contains)
    assert not registry.facts("cosine_hemisphere").renders(contains)
    # failures group: its bound on direct sun hits, N·Ω·max p
    assert sun_split.expected_sun_hits(throwaway, 1000, 0.01) == pytest.approx(1000 * 0.01 * 0.25)
    # results and report: the run records its facts, the charts take its colour
    facts = pipeline.estimator_facts([throwaway, "path"])
    assert facts[throwaway].colour == "#123456"
    assert facts[throwaway].unreachable == ["delta_bsdf", "transmission", "medium"]
    row = results.SweepRow(name=throwaway, relmse=[1.0], seconds=[1.0], growth=None,
                           nonfinite_values=0, images={}, verdict="fine")
    case = results.CaseResult(id="failures.glossy.x", group="glossy", label="x", scene="x",
                              defines={}, res=8, spp=16, seeds=4, max_depth=-1, summary="",
                              estimators=[row])
    run = results.Results(created="t", profile="quick", variant="llvm_ad_rgb",
                          mitsuba_version="3.9", drjit_version="1.5", machine={}, alpha=0.01,
                          reference_fraction=0.1, wall_seconds=1.0, scenes=[], checks=[],
                          failures=[case], estimator_facts=facts)
    assert charts.palette(run) == {throwaway: "#123456"}
    # Mitsuba loads it by name, from Python and from XML
    scene = mi.load_string(f"""<scene version="3.0.0">
        <integrator type="{throwaway}"/>
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="2"/>
            <integer name="height" value="2"/></film></sensor>
        <emitter type="constant"/></scene>""")
    assert scene.integrator().plugin_name == throwaway


