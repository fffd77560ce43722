"""The sun split of a scene comparison (stages/sun_split.py): what a real sun
leaves inconclusive is decided on the map without it and with it widened,
as in a heavy-tail failure case. A correct hemisphere estimator must not
fail there; a pdf 5 % off and a clamp that bites only the sun's hits must.
"""

from __future__ import annotations

import pytest

from mcillum.integrators.core import registry
from mcillum.validation import pipeline
from mcillum.validation.checks import scene as scene_checks
from mcillum.validation.checks.evidence import Decision
from mcillum.validation.plan import profiles
from mcillum.validation.results import SunSplit
from mcillum.validation.stages.context import Run

from twins import radiance_clamp_class, wrong_pdf_class

#: sun_sky at 16² px; its sun (0.0002 sr, 65 % of the map's power) is hit a
#: few times per pixel in the whole budget, so the real map cannot decide.
SUN_SKY = profiles.SceneRun(scene="sun_sky", res=16, ladder=(4, 16, 64, 256), renders=8,
                            max_depth=-1)


def _split(sunless: str, widened: str | None) -> SunSplit:
    return SunSplit(sun={"solid_angle": 2e-4}, sunless_passed=sunless != "fail",
                    sunless_test="t", sunless_reference_mean=0.05,
                    expected_sun_hits_per_pixel=0.5, sun_share_of_image=0.4,
                    sunless_outcome=sunless, sunless_reason=f"{sunless} without the sun",
                    widened={"solid_angle": 0.2} if widened else None,
                    widened_outcome=widened, widened_reason=f"{widened} on the disc")


@pytest.mark.parametrize("real, sunless, widened, expected", [
    ("inconclusive", "pass", "pass", "pass"),
    ("inconclusive", "pass", "fail", "fail"),
    ("inconclusive", "fail", None, "fail"),
    ("inconclusive", "pass", "inconclusive", "inconclusive"),
    ("inconclusive", "pass", None, "inconclusive"),      # (an estimator that samples the sun)
    ("fail", "pass", "pass", "fail"),                     # a confirmed rejection stands
    ("pass", "fail", None, "pass")])                      # (not split: never reached)
def test_the_split_decides_only_what_the_real_sun_left_open(real, sunless, widened, expected):
    """The rule of checks/scene.py: biased without the sun fails; the
    widened sun's pass or fail decides; anything else leaves the real map's
    decision as it was."""
    d = Decision(outcome=real, reason="real")
    got = scene_checks.split_decision(d, _split(sunless, widened), 4096)
    assert got.outcome == expected
    if expected != real:
        assert got.reason != "real" and "sun" in got.reason


@pytest.mark.slow
def test_a_scene_on_a_sun_map_is_decided_by_its_split(llvm, tmp_path):
    """sun_sky as a scene comparison at a budget of 64× the first look:
    cosine's test on the real map is inconclusive (its sun is hit too
    rarely); the split decides it, and never as a fail. The twins fail: the
    pdf 5 % off (on the map without the sun), and the clamp at radiance
    15 000, which leaves every other sample alone and darkens only the sun's
    hits (on the widened sun)."""
    twins = [wrong_pdf_class("cosine_hemisphere", 1.05), radiance_clamp_class(15000.0)]
    for c in twins:
        registry.register(c)
    run = Run(profiles.QUICK, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out"))
    run.budget = 64
    try:
        result, checks = pipeline.compare_scene(
            run, SUN_SKY, ["cosine_hemisphere", *[c.plugin_name for c in twins], "path"],
            speed_stage=False)
    finally:
        for c in twins:
            registry.unregister(c.plugin_name)
    est = {e.name: e.unbiasedness for e in result.estimators}
    unbiased = {c.id.split("/")[1]: c for c in checks if c.id.endswith("/unbiased")}
    cos = est["cosine_hemisphere"]
    assert cos.sun is not None and cos.sun.sunless_outcome == "pass"
    assert cos.sun.widened["solid_angle"] > 100 * cos.sun.sun["solid_angle"]
    assert unbiased["cosine_hemisphere"].outcome == "pass", unbiased["cosine_hemisphere"]
    assert "decided on the split map" in unbiased["cosine_hemisphere"].message
    wrong, clamp = (est[c.plugin_name] for c in twins)
    assert unbiased[twins[0].plugin_name].outcome == "fail"
    assert unbiased[twins[1].plugin_name].outcome == "fail"
    # each fails where the split shows it: without the sun or on the disc
    assert wrong.sun is None or wrong.sun.sunless_outcome == "fail"
    assert clamp.sun is not None and clamp.sun.widened_outcome == "fail"
    assert est["path"].sun is None and unbiased["path"].outcome == "pass"


def test_a_map_that_cannot_be_given_as_envmap_gets_a_note_not_a_split(llvm, tmp_path):
    """A user's scene whose map mcillum cannot give as $envmap (it declares
    $envmap for something else) cannot be split: where its map has a sun
    and an estimator is left open, a note of the scene says so and why; a
    map without a sun, or every estimator decided, adds none."""
    from types import SimpleNamespace

    import mitsuba as mi

    from mcillum.envmaps import catalog
    from mcillum.validation.checks.evidence import Evidence, Settled
    from mcillum.validation.stages import sun_split

    def ctx(map_name: str, outcome: str):
        path = catalog.resolve(map_name)[0]
        file = tmp_path / f"{map_name}.xml"
        file.write_text(f'<scene version="3.0.0"><default name="envmap" value="other.exr"/>'
                        f'<emitter type="envmap"><string name="filename" value="{path}"/>'
                        "</emitter></scene>")
        scene = mi.load_dict({"type": "scene", "sky": {"type": "envmap", "filename": path}})
        found = Evidence(comparison=object(), events=None, samples=0)
        found.settled = Settled(decision=Decision(outcome=outcome, reason=""), looks=1,
                                samples=0, budget=0)
        return SimpleNamespace(is_case=False, resolved={}, scene=scene, scene_notes=[],
                               estimators=["cosine_hemisphere", "path"],
                               evidence={"cosine_hemisphere": found}, defines={},
                               info=SimpleNamespace(path=str(file), bundled=False))

    open_sun = ctx("sun_sky", "inconclusive")
    sun_split.note_unsplit_sun(open_sun)
    (note,) = open_sun.scene_notes
    assert "rename that parameter" in note and "cosine_hemisphere" in note and "sr" in note
    for quiet in (ctx("sun_sky", "pass"), ctx("courtyard", "inconclusive")):
        sun_split.note_unsplit_sun(quiet)
        assert quiet.scene_notes == []
