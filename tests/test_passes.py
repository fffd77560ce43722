"""Renders beyond one 32-bit wavefront: W·H·spp > 2³² splits into passes.

Mitsuba 3.9.1 splits such renders itself only when spp divides evenly into its
pass count; otherwise it raises. mcillum's plugins (and ``renders.render`` for
Mitsuba's own integrators) plan the passes themselves (integrators/passes.py).
The split render is checked against the unsplit one with the wavefront limit
lowered, and once for real (marked slow: about 70 s per integrator here).
"""

import numpy as np
import pytest

import mitsuba as mi

from mcillum.integrators import passes
from mcillum.validation import renders, statistics
from mcillum.errors import root_cause

from conftest import SCENES


@pytest.mark.parametrize("pixels, spp, limit", [
    (4, 2**31, 2**32 - 1), (4, 2**30 + 1, 2**32 - 1), (64, 64, 640), (1, 7, 3),
    (1920 * 1080, 4096, 2**32 - 1), (5, 1, 5), (3, 10, 7)])
def test_plan_covers_spp_within_the_limit_evenly(pixels, spp, limit):
    plan = passes.plan_passes(pixels, spp, limit)
    assert sum(plan) == spp
    assert max(plan) * pixels <= limit
    assert max(plan) - min(plan) <= 1
    assert len(plan) == -(-spp // (limit // pixels))      # as few as possible


def test_plan_refuses_an_image_larger_than_one_wavefront():
    with pytest.raises(ValueError, match="crop"):
        passes.plan_passes(10, 1, 9)
    with pytest.raises(ValueError, match="at least one"):
        passes.plan_passes(4, 0)


def test_pass_seeds_keep_pass_zero_and_do_not_replay_other_seeds():
    assert passes.pass_seed(7, 0) == 7
    seeds = {passes.pass_seed(s, i) for s in range(64) for i in range(1, 64)}
    assert len(seeds) == 63 * 64                         # no collisions here
    assert not seeds & set(range(64))


def test_mitsubas_own_split_fails_when_spp_does_not_divide(llvm):
    # The upstream behaviour this module works around (pinned: if it is
    # fixed, renders.render may stop splitting Mitsuba's integrators).
    scene = _env_scene()
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 1}),
                  spp=2**31)
    assert "multiple of samples_per_wavefront" in str(root_cause(info.value))


def _env_scene(res=2):
    return mi.load_dict({
        "type": "scene", "env": {"type": "constant"},
        "sensor": {"type": "perspective", "film": {
            "type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}})


# (the split is one method of the shared base class: one hemisphere
# estimator, the NEE one, and Mitsuba's path through renders.render)
@pytest.mark.parametrize("name", ["cosine_hemisphere", "mis", "path"])
def test_split_render_matches_the_unsplit_one(llvm, name, monkeypatch):
    """Image means of 48 seeds, split (7 passes) against unsplit, on the
    furnace sphere: two-sample Welch test per channel, α = 0.001, Šidák over
    the 3 channels. A render whose later passes replayed the first or were
    weighted wrongly (e.g. summed) fails it."""
    scene = renders.load_scene(SCENES / "furnace_sphere.xml", res=8)
    integrator = renders.make_integrator(name, {"max_depth": 2})
    k, spp = 48, 64

    def means():
        return np.stack([renders.render(scene, integrator, spp, s).image.mean(axis=(0, 1))
                         for s in range(k)])

    whole = means()
    calls = []
    plan = passes.plan_passes

    def small_limit(pixels, spp_, limit=None):
        out = plan(pixels, spp_, 640)
        calls.append(out)
        return out

    monkeypatch.setattr(passes, "plan_passes", small_limit)
    split = means()
    assert calls and all(len(c) == 7 for c in calls)    # 64 px · 64 spp / 640
    _, p = statistics.welch(*statistics.batch_moments(whole), *statistics.batch_moments(split))
    alpha = 1 - (1 - 0.001) ** (1 / 3)
    assert (p > alpha).all(), (whole.mean(0), split.mean(0), p)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cosine_hemisphere", "path"])
def test_real_render_beyond_two_to_the_32_samples(llvm, name):
    """2×2 pixels × (2³⁰ + 1) spp = 4 294 967 300 samples > 2³²: renders (in
    two passes) and sees the unit environment as exactly 1."""
    result = renders.render(_env_scene(), renders.make_integrator(name, {"max_depth": 1}),
                            2**30 + 1)
    assert np.allclose(result.image, 1.0, rtol=1e-5)
