"""Renders beyond one 32-bit wavefront: W·H·spp > 2³² splits into passes.

Mitsuba 3.9.1 splits such renders itself only when spp divides evenly into its
pass count; otherwise it raises. mcillum's plugins (and ``renders.render`` for
Mitsuba's own integrators) plan the passes themselves (integrators/core/passes.py).
The split render is checked against the unsplit one with the wavefront limit
lowered, and once for real (marked slow: about 70 s per integrator here).
"""

import numpy as np
import pytest
from scipy import stats

import mitsuba as mi

from mcillum.integrators.core import passes
from mcillum.validation.run import renders
from mcillum.validation.stats import statistics
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
SPLIT = ("cosine_hemisphere", "mis", "path")
ALPHA = 0.001


def split_and_whole(name, monkeypatch, first_seed=0):
    """Image means of 48 seeds on the furnace sphere (8² px, 64 spp), unsplit
    and split into 7 passes by lowering the wavefront limit to 640 lanes."""
    scene = renders.load_scene(SCENES / "furnace_sphere.xml", res=8)
    integrator = renders.make_integrator(name, {"max_depth": 2})
    k, spp = 48, 64

    def means():
        return np.stack([renders.render(scene, integrator, spp, s).image.mean(axis=(0, 1))
                         for s in range(first_seed, first_seed + k)])

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
    return whole, split


def same_distribution(whole, split):
    """Per channel, a two-sample Welch test on the means and a two-sided F
    test on the variances of the 48 image means; α = 0.001 over the 6 tests
    (Šidák). Returns (agree?, p-values)."""
    _, p_mean = statistics.welch(*statistics.batch_moments(whole),
                                 *statistics.batch_moments(split))
    ratio = whole.var(axis=0, ddof=1) / split.var(axis=0, ddof=1)
    df = (len(whole) - 1, len(split) - 1)
    p_var = 2 * np.minimum(stats.f.cdf(ratio, *df), stats.f.sf(ratio, *df))
    p = np.concatenate([p_mean, p_var])
    return bool((p > 1 - (1 - ALPHA) ** (1 / p.size)).all()), p


@pytest.mark.parametrize("name", SPLIT)
def test_split_render_matches_the_unsplit_one(llvm, name, monkeypatch):
    """Split (7 passes) and unsplit renders have the same distribution of
    image means: same mean and same spread (:func:`same_distribution`). The
    twins below, passes that replay one seed (the spread grows: 9–10 spp
    repeated instead of 64 independent) and passes summed instead of averaged
    (the mean grows 7×), are rejected by the same test."""
    ok, p = same_distribution(*split_and_whole(name, monkeypatch))
    assert ok, p


def _replayed(seed, index):
    return seed                                        # every pass replays pass 0


def _summed(plan, seed, render_pass):
    image = None
    for i, n in enumerate(plan):
        part = render_pass(passes.pass_seed(seed, i), n)  # not weighted by n / spp
        image = part if image is None else image + part
    return image


@pytest.mark.parametrize("twin", ["replayed", "summed"])
@pytest.mark.parametrize("name", ["cosine_hemisphere", "path"])
def test_split_render_twins_are_rejected(llvm, name, twin, monkeypatch):
    if twin == "replayed":
        monkeypatch.setattr(passes, "pass_seed", _replayed)
    else:
        monkeypatch.setattr(passes, "render_in_passes", _summed)
    ok, p = same_distribution(*split_and_whole(name, monkeypatch))
    assert not ok, f"{twin} passes were accepted: p = {p}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cosine_hemisphere", "path"])
def test_real_render_beyond_two_to_the_32_samples(llvm, name):
    """2×2 pixels × (2³⁰ + 1) spp = 4 294 967 300 samples > 2³²: renders (in
    two passes) and sees the unit environment as exactly 1."""
    result = renders.render(_env_scene(), renders.make_integrator(name, {"max_depth": 1}),
                            2**30 + 1)
    assert np.allclose(result.image, 1.0, rtol=1e-5)
