"""The rules of evidence (validation/checks/evidence.py) on synthetic renders whose
truth is known: a correct heavy-tailed estimator is never called biased more
often than the test's α, and three real biases on the same heavy-tailed
"scene" — a pdf 5 % off, a firefly clamp, a missing light — are not passed.

The synthetic scene: P pixels, each the sum of a smooth part (mean 1, noise
σ per sample) and a rare bright source hit with probability ``P_HIT`` per
sample, worth ``TAIL`` of the pixel's mean (a sun that K renders of spp
samples see about 0.1 times per pixel). A render is the mean of spp samples;
the reference is the exact mean with a tiny variance. Each test states its
α (statistics.ALPHA = 0.01, family-wise per check) and its bound.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mcillum.validation.checks import convergence, evidence
from mcillum.validation.stages import common, sequential
from mcillum.validation.stats import replication, statistics, tails

P, K, SPP, SIGMA = 16, 64, 16, 0.5
P_HIT, TAIL = 1e-4, 0.5              # the rare source carries 0.5 of a pixel's 1.5
ALPHA = statistics.ALPHA
TRIALS = 150


def renders(rng, scale=1.0, clamp=None, tail=True, spp=SPP, k=K):
    """K renders (K, P, P, 3) of the synthetic estimator at ``spp``: ``scale``
    multiplies every sample (a pdf off by 1/scale), ``clamp`` caps each
    sample, ``tail`` False leaves the source out (a missing light)."""
    body = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
    hits = rng.binomial(spp, P_HIT, (k, P, P, 1)) if tail else np.zeros((k, P, P, 1))
    value = TAIL / P_HIT                                  # one hit's radiance
    if clamp is not None:
        value = min(value, clamp)
    x = scale * (body + hits * value / spp)
    return np.repeat(x, 3, axis=-1)


def fixed(mean, var=1e-6, image_var=1e-8):
    """A reference of known ``mean`` (P, P, 3), as :class:`statistics.
    Moments` of 10 000 renders of per-pixel variance ``var`` (the image
    mean's: ``image_var``)."""
    return statistics.Moments(mean, np.full((P, P, 3), var), 10_000,
                              mean.mean(axis=(0, 1)), np.full(3, image_var))


def reference():
    mean = np.full((P, P, 3), 1.0 + TAIL)
    return fixed(mean), mean


def reader(mean):
    """The rules of evidence at a look, with every batch's fireflies."""
    def read(c, batches, look):
        spps, xs = [s for s, _ in batches], [x for _, x in batches]
        events, n, carried = tails.tail_events(xs, mean, spps)
        return evidence.bias_outcome(c, events, n, sequential.samples(batches), carried,
                                     event_value=tails.largest_event(xs, mean, spps))
    return read


def outcome(x, ref, mean):
    """The first look alone (no further batch)."""
    c = statistics.compare(x, ref)
    return reader(mean)(c, [(SPP, x)], 0).outcome


#: The budget of the sequential tests below (× the first look's 1024
#: samples per pixel) and their ε: the failure cases' (plan/plans.py).
GROWTH, EPSILON = 1024, 0.05


def settled(rng, ref, mean, growth=GROWTH, **twin):
    """The sequential test's decision on the synthetic estimator (``twin``:
    renders()'s arguments), each batch drawn afresh."""
    more = lambda look, spp, k: (spp, renders(rng, spp=spp, k=k, **twin))   # noqa: E731
    got, _ = sequential.settle([(SPP, renders(rng, **twin))], ref, reader(mean), more,
                               EPSILON, growth)
    return got


def test_a_correct_heavy_tailed_estimator_fails_at_most_alpha_and_is_decided():
    """150 seeds of a correct estimator whose tail most renders miss: the
    per-pixel Welch test alone rejects most of them; the first look under
    the rules cannot decide most of them; the sequential test fails at most
    as often as α allows (one-sided binomial bound at 0.001: at most 6 of
    150 at α = 0.01) and is inconclusive in at most 2 % (the budget spent)."""
    rng = np.random.default_rng(1)
    ref, mean = reference()
    plain = sum(not statistics.compare(renders(rng), ref).passed for _ in range(30))
    assert plain >= 15                     # the problem: a bare test calls it biased
    first = [outcome(renders(rng), ref, mean) for _ in range(30)]
    assert first.count("pass") < 15, first
    got = [settled(rng, ref, mean) for _ in range(TRIALS)]
    outcomes = [d.decision.outcome for d in got]
    assert outcomes.count("fail") <= stats.binom.ppf(0.999, TRIALS, ALPHA), outcomes
    assert outcomes.count("inconclusive") <= 0.02 * TRIALS, outcomes
    assert all(d.looks > 1 for d in got)           # it had to render on
    for d in got:
        if d.decision.outcome == "pass":
            assert d.decision.half_width + max(map(abs, d.decision.relative_bias)) <= EPSILON


#: Clamps that leave fireflies (one clamped hit still lifts a 16-spp render's
#: pixel past 10× the reference) and remove 30 %, 17 % and 6.7 % of the image
#: mean; and one clamp below the firefly threshold (32 %).
CLAMPS = [500.0, 2500.0, 4000.0, 50.0]


@pytest.mark.parametrize("clamp", CLAMPS)
def test_clamps_that_leave_fireflies_fail(clamp):
    """Each clamp fails in at least 95 % of 30 seeds (the issue's power goal)
    and never passes; with fireflies, no rule may excuse a deficit the
    fireflies seen cannot carry."""
    rng = np.random.default_rng(2)
    ref, mean = reference()
    removed = TAIL * (1 - clamp / (TAIL / P_HIT)) / (1 + TAIL)
    assert removed >= 0.05
    got = [settled(rng, ref, mean, clamp=clamp).decision.outcome for _ in range(30)]
    assert got.count("fail") >= 29 and "pass" not in got, got


def test_the_clamp_tests_fail_if_a_tail_excused_everything(monkeypatch):
    """If the tail rules always said "a tail can carry it", the clamp with
    fireflies would never fail: the tests above would catch that."""
    monkeypatch.setattr(evidence, "tail_can_carry",
                        lambda c, *a: np.ones(np.shape(c.pooled_t), bool))
    monkeypatch.setattr(evidence, "pixel_tail_can_carry",
                        lambda c, *a: np.ones(np.shape(c.pixel_p), bool))
    rng = np.random.default_rng(2)
    ref, mean = reference()
    got = [settled(rng, ref, mean, clamp=2500.0, growth=64).decision.outcome
           for _ in range(5)]
    assert "fail" not in got, got


@pytest.mark.parametrize("bias", ["source missing", "pdf 5% off, no tail"])
def test_real_biases_fail_at_the_first_look(bias):
    """Biases without fireflies: each fails at the first look in at least
    90 % of 30 seeds."""
    rng = np.random.default_rng(2)
    ref, mean = reference()
    make = {"source missing": lambda: renders(rng, tail=False),
            "pdf 5% off, no tail": lambda: renders(rng, scale=1 / 1.05, tail=False)}[bias]
    if bias == "pdf 5% off, no tail":       # the truth of a tail-free scene
        ref, mean = fixed(np.ones((P, P, 3))), np.ones((P, P, 3))
    got = [outcome(make(), ref, mean) for _ in range(30)]
    assert got.count("fail") >= 27, got


def test_a_pdf_off_on_a_heavy_tailed_estimator_fails():
    """A pdf 5 % off on the heavy-tailed scene (every sample, tail included,
    5 % low): the first look cannot tell it from the tail; the sequential
    test renders until it can, and fails in at least 95 % of 20 seeds."""
    rng = np.random.default_rng(3)
    ref, mean = reference()
    got = [settled(rng, ref, mean, scale=1 / 1.05).decision.outcome for _ in range(20)]
    assert got.count("fail") >= 19 and "pass" not in got, got


def test_a_region_darkened_on_a_heavy_tailed_estimator_fails():
    """A local error under a heavy tail: every sample × 0.7 in one 4×4 block
    (1/16 of the image, the ``region_dark`` twin) of the heavy-tailed
    estimator. The first look cannot tell it from the tail at those pixels;
    the sequential test fails it in at least 17 of 20 seeds (measured: 18).
    The other two *pass*: the image mean is 1.9 % low, inside ±5 %, and the
    region's pixels are not yet resolved at 65 536 samples (t ≈ 2.3). ε
    bounds the image mean, not each tile: a local error that small under a
    heavy tail can pass (docs/method.md says so)."""
    rng = np.random.default_rng(7)
    ref, mean = reference()

    def dark(spp=SPP, k=K):
        x = renders(rng, spp=spp, k=k)
        x[:, :4, :4] *= 0.7
        return x

    more = lambda look, spp, k: (spp, dark(spp, k))   # noqa: E731
    got = [sequential.settle([(SPP, dark())], ref, reader(mean), more, EPSILON,
                             GROWTH)[0].decision.outcome for _ in range(20)]
    assert got.count("fail") >= 17, got


def one_tail_pixel(rng, spp=SPP, k=K, tail=True):
    """K renders (K, P, P, 3) of an image with no tail but at one pixel,
    whose light (0.3 of its 1.3) comes in rare hits, 5·10⁻⁴ per sample, each
    worth 600: a firefly in a render of 16 spp (37 ≫ 13), none in one of 256
    (2.3). ``tail`` False: that light is missing (a bias)."""
    x = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
    if tail:
        x[:, 0, 0] += rng.binomial(spp, 5e-4, (k, 1)) * 600.0 / spp
    return np.repeat(x, 3, axis=-1)


def test_a_tail_no_render_showed_as_a_firefly_is_confirmed_where_it_would(monkeypatch):
    """"No firefly, no tail" is what lets a darker pixel count: here the
    first 64 renders of 16 spp miss the pixel's hits in 60 % of seeds, and
    it is 23 % dark with no firefly anywhere. A confirming batch at higher
    spp averages a hit below the firefly threshold and confirms the fail
    whenever it misses the hits too; the confirming batch at the first
    look's spp (sequential.confirming_batch: CONFIRM_UNSEEN × the samples)
    shows them as fireflies. 100 seeds of the correct estimator fail at
    most as often as α allows (one-sided binomial bound at 0.001; measured:
    0); confirmed the old way (4× the samples in 16 renders) they fail at
    least 3 times (measured: 7); with the light really missing, all 20
    fail."""
    mean = np.ones((P, P, 3))
    mean[0, 0] = 1.3
    ref = fixed(mean)

    def run(rng, trials, tail=True):
        more = lambda look, spp, k: (spp, one_tail_pixel(rng, spp, k, tail))   # noqa: E731
        return [sequential.settle([(SPP, one_tail_pixel(rng, tail=tail))], ref, reader(mean),
                                  more, EPSILON, 16)[0].decision.outcome
                for _ in range(trials)]

    got = run(np.random.default_rng(8), 100)
    assert got.count("fail") <= stats.binom.ppf(0.999, 100, ALPHA), got
    missing = run(np.random.default_rng(9), 20, tail=False)
    assert missing.count("fail") == 20, missing
    monkeypatch.setattr(sequential, "confirming_batch", lambda d, batches, k: (
        math.ceil(sequential.CONFIRM * sequential.samples(batches) / k), k))
    got = run(np.random.default_rng(8), 100)
    assert got.count("fail") >= 3, got


def test_a_tail_seen_at_no_spp_of_the_first_look_is_confirmed_at_fewer(monkeypatch):
    """A sun split's first look is one rung of high spp: here 16 renders of
    1 024 spp. One dark pixel (0.01) takes 30 % of its light in hits of
    2·10⁻⁵ per sample whose sizes are Pareto (shape 1.3, from 50): most
    lift a render of 1 024 spp by less than the firefly threshold, and a
    batch of that spp misses the big ones. The confirming batch of a darker
    pixel with no firefly, at the fewest spp a seed block holds (263),
    shows them as fireflies; at the first look's 1 024 spp it confirmed
    such a fail whenever the big hits stayed away (cosine sampling's glossy
    hits at a silhouette pixel of glossy_phong, seed set 218). 100 seeds of
    the correct estimator fail at most as often as α allows (one-sided
    binomial bound at 0.001; measured: 0); confirmed at the first look's
    spp they fail at least 8 times (measured: 18); with the light really
    missing, all 20 fail."""
    hit, smallest, shape, spp0 = 2e-5, 50.0, 1.3, 1024
    mean = np.ones((P, P, 3))
    mean[0, 0] = 0.01 + hit * shape * smallest / (shape - 1)
    ref = fixed(mean)

    def pixel(rng, spp, k, tail=True):
        x = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
        x[:, 0, 0] = 0.01 + rng.normal(0, 0.005 / np.sqrt(spp), (k, 1))
        if tail:
            n = rng.binomial(spp, hit, k)
            sizes = smallest * (1 - rng.random(n.sum())) ** (-1 / shape)
            x[:, 0, 0, 0] += np.bincount(np.repeat(np.arange(k), n), weights=sizes,
                                         minlength=k) / spp
        return np.repeat(x, 3, axis=-1)

    def run(rng, trials, tail=True):
        more = lambda look, spp, k: (spp, pixel(rng, spp, k, tail))   # noqa: E731
        return [sequential.settle([(spp0, pixel(rng, spp0, 16, tail))], ref, reader(mean),
                                  more, 0.02, 16)[0].decision.outcome
                for _ in range(trials)]

    got = run(np.random.default_rng(21), 100)
    assert got.count("fail") <= stats.binom.ppf(0.999, 100, ALPHA), got
    missing = run(np.random.default_rng(22), 20, tail=False)
    assert missing.count("fail") == 20, missing
    new = sequential.confirming_batch

    def at_first_spp(d, batches, k):
        if d.tail_events or d.counted_up or (d.pooled is not None and np.any(d.pooled)):
            return new(d, batches, k)
        return spp0, math.ceil(sequential.CONFIRM_UNSEEN * sequential.samples(batches) / spp0)

    monkeypatch.setattr(sequential, "confirming_batch", at_first_spp)
    old = run(np.random.default_rng(21), 100)
    assert old.count("fail") >= 8, old


def test_added_light_fails_even_with_a_tail():
    """A tail cannot make a mean look too high: an estimator that adds light
    to a 4×4 region (an emitter counted twice there) fails although it is
    heavy-tailed and darker everywhere else."""
    rng = np.random.default_rng(4)
    ref, mean = reference()

    def brighter():
        x = renders(rng)
        x[:, :4, :4] += 1.0
        return x

    got = [outcome(brighter(), ref, mean) for _ in range(30)]
    assert got.count("fail") >= 27, got


def test_a_fail_of_one_biased_by_design_renders_no_confirming_batch():
    """``confirm=False`` (an estimator biased by design): a fail stands at the
    look that reads it, says so, and no batch is rendered for it; the same
    renders with confirmation render one (the test can fail)."""
    rng = np.random.default_rng(5)
    ref, mean = reference()
    x = renders(rng, tail=False)                       # the source missing: fails
    asked = []

    def more(look, spp, k):
        asked.append((look, spp, k))
        return spp, renders(rng, spp=spp, k=k, tail=False)

    got, _ = sequential.settle([(SPP, x)], ref, reader(mean), more, EPSILON, GROWTH,
                               confirm=False)
    assert (got.decision.outcome, got.looks, asked) == ("fail", 1, [])
    assert "not confirmed: biased by design" in got.decision.reason
    confirmed, _ = sequential.settle([(SPP, x)], ref, reader(mean), more, EPSILON, GROWTH)
    assert confirmed.decision.outcome == "fail" and len(asked) == 1 and confirmed.replicated


def test_a_test_the_sun_split_follows_stops_where_its_budget_cannot_decide():
    """``split_follows`` (the sun split will test the estimator without the
    sun and with it widened): a reading that needs more than
    BEYOND_BUDGET × the budget stops at once, says what would decide, and
    renders no batch; the same renders without a split render on to the
    budget and stay inconclusive. A missing source still fails at once
    (a fail is never stopped)."""
    rng = np.random.default_rng(7)
    ref, mean = reference()
    asked = []

    def more(look, spp, k, **twin):
        asked.append(look)
        return spp, renders(rng, spp=spp, k=k, **twin)

    x = renders(rng)
    stopped, _ = sequential.settle([(SPP, x)], ref, reader(mean), more, EPSILON, 16,
                                   split_follows=True)
    d = stopped.decision
    assert (d.outcome, stopped.looks, asked) == ("inconclusive", 1, [])
    assert d.samples_needed > sequential.BEYOND_BUDGET * stopped.budget
    assert f"the budget of {stopped.budget}" in d.reason and "budget spent" not in d.reason
    # (the samples that would decide are named once, by the tail's reading)
    assert "would decide" in d.reason and d.reason.count(f"{d.samples_needed:.2g}") == 1
    on, _ = sequential.settle([(SPP, x)], ref, reader(mean), more, EPSILON, 16)
    assert on.decision.outcome == "inconclusive" and on.looks > 1 and asked
    assert "budget spent" in on.decision.reason
    n = on.decision.samples_needed
    assert n is None or on.decision.reason.count(f"{n:.2g}") == 1
    missing, _ = sequential.settle([(SPP, renders(rng, tail=False))], ref, reader(mean),
                                   lambda look, spp, k: more(look, spp, k, tail=False),
                                   EPSILON, 16, split_follows=True)
    assert missing.decision.outcome == "fail" and missing.replicated


def test_looks_spend_alpha_and_a_light_tailed_estimator_fails_at_most_alpha():
    """Σ α_j over any number of looks stays below α; 300 sequential tests of a
    correct light-tailed estimator with a tight ε (so that most render on)
    fail at most as often as α allows."""
    assert sum(sequential.level(ALPHA, j) for j in range(10_000)) <= ALPHA
    rng = np.random.default_rng(6)
    ref, mean = fixed(np.ones((P, P, 3))), np.ones((P, P, 3))
    more = lambda look, spp, k: (spp, renders(rng, spp=spp, k=k, tail=False))   # noqa: E731
    got = [sequential.settle([(4, renders(rng, spp=4, k=8, tail=False))], ref, reader(mean),
                             more, 0.002, 64)[0] for _ in range(300)]
    assert sum(d.decision.outcome == "fail" for d in got) <= stats.binom.ppf(0.999, 300, ALPHA)
    assert np.mean([d.looks for d in got]) > 1.5


def conv(slope, low, high, exact=False):
    from mcillum.validation.results import Convergence
    return Convergence(slope=slope, low=low, high=high, exact=exact,
                       consistent_with_mc=low <= -1 <= high, passed=high < 0)


@pytest.mark.parametrize("interval, resolved, expected", [
    ((-1.0, -1.1, -0.9), True, "pass"),
    ((-1.0, -1.0, -0.99), True, "pass"),        # Monte Carlo, measured very precisely
    ((-0.87, -0.93, -0.80), True, "pass"),      # within the tolerance (a bent ladder)
    ((-1.5, -1.7, -1.3), True, "inconclusive"), # faster than 1/N: not Monte Carlo's
    ((-0.77, -1.74, 0.20), True, "inconclusive"),   # too wide
    ((-0.48, -0.90, -0.05), True, "inconclusive"),  # excludes −1, far from it, not above
    ((-0.3, -0.8, 0.2), True, "fail"),          # wholly above −0.85, narrow (1.0) enough
    ((0.3, -0.8, 1.4), True, "inconclusive"),   # above −1 but too wide (2.2) to mean it
    ((-0.2, -0.4, 0.0), True, "fail"),          # narrow, flat: a bias floor
    ((-0.5, -0.7, -0.3), True, "fail"),
    ((-0.5, -0.7, -0.3), False, "inconclusive"),    # a tail not yet resolved
    ((-0.9, -1.2, 0.01), True, "inconclusive"),     # reaches 0
])
def test_convergence_outcomes(interval, resolved, expected):
    assert convergence.convergence_outcome(conv(*interval), resolved)[0] == expected


def test_a_slope_too_wide_on_a_short_ladder_asks_for_more_rungs():
    """3 rungs leave the line one degree of freedom (t = 12.7): a user's
    guided_path, whose error falls a little faster as it learns, read
    1.08 wide there and 0.42 on 5 rungs. The message says a longer ladder
    would narrow it; on 4 or 5 rungs, or unknown, it does not."""
    wide = conv(-1.07, -1.61, -0.53)
    assert "a longer ladder" in convergence.convergence_outcome(wide, True, 3)[1]
    for rungs in (4, 5):        # (4: a heavy tail's rung variance may widen it instead)
        assert "a longer ladder" not in convergence.convergence_outcome(wide, True, rungs)[1]
    assert "a longer ladder" not in convergence.convergence_outcome(wide, True)[1]


def test_a_fail_after_more_looks_reads_the_level_spent_on_that_look():
    """The sequential fit (stages/scene.py: settle_convergence) may look
    again; a fail at look j reads its interval at α_j (Σ α_j = α): a slope
    slower than −0.85 at 95 % whose interval at α_j reaches the band is not
    yet a fail, and one above it at α_j is."""
    from dataclasses import replace
    slow = conv(-0.5, -0.7, -0.3)
    assert convergence.convergence_outcome(replace(slow, low_spent=-0.75), True)[0] == "fail"
    outcome, text = convergence.convergence_outcome(replace(slow, low_spent=-0.9), True)
    assert outcome == "inconclusive" and "not at the level a fail" in text, text


def test_a_fit_more_renders_may_decide_says_when_its_budget_is_spent():
    """More renders per rung may decide a fit that is too wide or far from
    −1; not one with fewer than 3 rungs above the reference's share, nor one
    wholly steeper than −1.15 (the reference's noise), nor an exact one. An
    undecided fit whose budget is spent says so, and how many renders it
    read."""
    from dataclasses import replace
    nan, inf = float("nan"), float("inf")
    wide = conv(-0.77, -1.74, 0.20)
    assert convergence.more_renders_decide(wide)
    assert convergence.more_renders_decide(conv(-0.48, -0.90, -0.05))
    assert not convergence.more_renders_decide(conv(nan, -inf, inf))
    assert not convergence.more_renders_decide(conv(-1.6, -1.8, -1.4))
    assert not convergence.more_renders_decide(conv(nan, nan, nan, True))
    spent = replace(wide, looks=2, renders=64, budget_renders=64)
    outcome, text = convergence.convergence_outcome(spent, True)
    assert outcome == "inconclusive" and "budget spent: 64 renders per rung" in text, text
    assert "after 2 more looks" in text
    assert "budget" not in convergence.convergence_outcome(wide, True)[1]
    assert "about 2.4e+02 would narrow it to 1.0" in text       # 64 × 1.94²
    assert "budget" not in convergence.convergence_outcome(replace(spent, renders=32), True)[1]
    far = replace(conv(-0.48, -0.90, -0.05), renders=16, budget_renders=16)
    assert "twice this one's renders twice as many" in convergence.convergence_outcome(
        far, True)[1]
    assert convergence.renders_to_decide(far) == 0


def test_convergence_of_exact_and_unmeasurable_estimators():
    nan, inf = float("nan"), float("inf")
    assert convergence.convergence_outcome(conv(nan, nan, nan, True), False)[0] == "pass"
    assert convergence.convergence_outcome(conv(nan, -inf, inf), False)[0] == "inconclusive"


def replicated(x, fresh, ref, mean):
    read = reader(mean)
    return replication.replicated_compare(x, ref, fresh, ALPHA,
                                         lambda c, y: read(c, [(SPP, y)], 0))


def test_replication_tests_only_the_rejections_that_counted():
    """A correct heavy-tailed estimator with one pixel too bright by chance:
    the upward pixel counts, but in fresh (correct) renders it comes back
    with probability about α, and the downward tail pixels, which did not
    count, are not replicated (they would come back: the same tail is missed
    again). A real upward bias comes back. Bound: binomial at 0.001 for
    α = 0.01 over 60 trials."""
    rng = np.random.default_rng(5)
    ref, mean = reference()
    flukes = []
    for _ in range(60):
        x = renders(rng)
        x[:, 0, 0] += 0.6                       # one pixel off by chance
        t = replicated(x, lambda: renders(rng), ref, mean)
        flukes.append(t.outcome == "fail" and t.replicated)
    assert sum(flukes) <= stats.binom.ppf(0.999, 60, ALPHA), sum(flukes)

    def biased():
        x = renders(rng)
        x[:, :4, :4] += 1.0
        return x

    real = [replicated(biased(), biased, ref, mean) for _ in range(20)]
    assert sum(t.outcome == "fail" and bool(t.replicated) for t in real) >= 19, \
        [(t.outcome, t.replicated) for t in real]


def test_a_reference_off_at_a_pixel_is_not_the_estimators_fail():
    """A reference 2 % high at one pixel, 10 of its own standard errors (a
    rare event it caught, which its variance does not show): a correct
    estimator without a tail reads darker there, and its confirming batch,
    tested against the same reference, confirms it whatever its size. With
    path rendered on the confirming batch's seeds (``control``), path is as
    dark there: no seed fails, and those undecided say why; an estimator
    10 % dark at that pixel, which path's renders are not, still fails in
    every seed. (The fresh renders are tested against path's there:
    replication.against_fresh_path.)"""
    mean = np.ones((P, P, 3))
    ref_mean = mean.copy()
    ref_mean[0, 0] = 1.02
    ref = fixed(ref_mean, var=4e-6 * 10_000)

    def run(seed, control, dark=1.0, trials=30):
        rng = np.random.default_rng(seed)

        def draw(spp, k, scale=1.0):
            x = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
            x[:, 0, 0] *= scale
            return np.repeat(x, 3, axis=-1)
        more = lambda look, spp, k: (spp, draw(spp, k, dark))   # noqa: E731
        path = (lambda look, spp, k, *_: (spp, draw(spp, k))) if control else None   # noqa: E731
        return [sequential.settle([(1024, draw(1024, K, dark))], ref, reader(mean), more,
                                  EPSILON, 16, control=path)[0].decision
                for _ in range(trials)]

    without = [d.outcome for d in run(10, control=False)]
    assert without.count("fail") >= 20, without            # measured: 30
    beside = run(10, control=True)
    assert [d.outcome for d in beside].count("fail") <= stats.binom.ppf(0.999, 30, ALPHA)
    assert all(replication.FRESH_EXCUSE in d.reason for d in beside
               if d.outcome != "pass")
    assert [d.outcome for d in run(11, control=True, dark=0.9)].count("fail") == 30


def test_a_reference_pixel_off_by_chance_is_not_confirmed_against_itself():
    """A reference pixel 6 of its own standard errors high, its variance
    honest (a chance outlier of path, 16× noisier per sample than the
    estimator: seed set 877's lone_sphere_studio, bayesian_importance, read
    4.6 of them). A correct estimator reads darker there and its first look
    rejects; fresh renders tested against the same reference confirm it in
    most seeds, and so does path on the confirming batch's seeds at that
    batch's samples (too noisy to see the reference off). Tested against
    path on fresh seeds with the reference's samples
    (replication.against_fresh_path), at most α of the seeds fail (binomial
    bound at 0.001). An estimator 2 % dark at that pixel, the reference
    right, still fails in every seed, confirmed."""
    sigma_path, ref_se = 16 * SIGMA, 0.002
    reference_spp = round((sigma_path / ref_se) ** 2)

    def run(seed, outlier, dark=1.0, control=True, trials=30):
        rng = np.random.default_rng(seed)
        ref_mean = np.ones((P, P, 3))
        ref_mean[0, 0] += outlier * ref_se
        # (the image mean's variance, the pixels' over P²: it holds the outlier)
        ref = fixed(ref_mean, var=ref_se ** 2 * 10_000, image_var=ref_se ** 2 * 10_000 / P ** 2)

        def draw(spp, k, sigma=SIGMA, scale=1.0):
            x = 1.0 + rng.normal(0, sigma / np.sqrt(spp), (k, P, P, 1))
            x[:, 0, 0] *= scale
            return np.repeat(x, 3, axis=-1)
        more = lambda look, spp, k: (spp, draw(spp, k, scale=dark))       # noqa: E731
        path = (lambda look, spp, k, *_: (spp, draw(spp, k, sigma_path))) \
            if control else None                                          # noqa: E731
        return [sequential.settle([(4096, draw(4096, K, scale=dark))], ref, reader(ref_mean),
                                  more, EPSILON, 16, reference_spp=reference_spp,
                                  control=path)[0]
                for _ in range(trials)]

    alone = [s.decision.outcome for s in run(30, outlier=6, control=False)]
    assert alone.count("fail") >= 20, alone                   # measured: 30
    fresh = run(31, outlier=6)
    outcomes = [s.decision.outcome for s in fresh]
    assert outcomes.count("fail") <= stats.binom.ppf(0.999, 30, ALPHA), outcomes
    assert any(replication.FRESH_EXCUSE in s.replication for s in fresh), \
        [s.replication for s in fresh]
    biased = run(32, outlier=0, dark=0.98)
    assert all(s.decision.outcome == "fail" and s.replicated for s in biased), \
        [(s.decision.outcome, s.replication) for s in biased]


def test_far_past_the_reference_path_is_asked_before_the_confirming_batch():
    """A reference 2 % dark at one pixel (a rare event it missed, which its
    variance does not show), read at 16× its samples per pixel
    (sequential.PATH_FIRST): a correct estimator reads brighter there, and
    path in windows on the confirming seeds reads it too, so the
    estimator's confirming batch (4× the samples so far) is never rendered,
    and no seed fails. An estimator 10 % bright there, which path is not,
    still fails in every seed, confirmed on its batch. Read below
    PATH_FIRST, the fail is confirmed on the estimator's batch first, as
    before."""
    mean = np.ones((P, P, 3))
    ref_mean = mean.copy()
    ref_mean[0, 0] = 0.98
    ref = fixed(ref_mean, var=4e-6 * 10_000)
    first_spp = 1024

    def run(seed, bright=1.0, lead=sequential.PATH_FIRST, trials=30):
        rng = np.random.default_rng(seed)

        def draw(spp, k, scale=1.0):
            x = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
            x[:, 0, 0] *= scale
            return np.repeat(x, 3, axis=-1)
        out = []
        for _ in range(trials):
            asked = []

            def more(look, spp, k):
                asked.append(spp * k)
                return spp, draw(spp, k, bright)

            def path(look, spp, k, *_):
                return spp, draw(spp, k)
            settled = sequential.settle(
                [(first_spp, draw(first_spp, K, bright))], ref, reader(mean), more, EPSILON,
                16, control=path, reference_spp=first_spp * K // lead)[0]
            out.append((settled, asked))
        return out

    start = first_spp * K
    correct = run(20)
    outcomes = [s.decision.outcome for s, _ in correct]
    assert outcomes.count("fail") <= stats.binom.ppf(0.999, 30, ALPHA), outcomes
    asked_first = [a for s, a in correct if "path in" in s.replication]
    assert asked_first and all(sequential.CONFIRM * start not in a for a in asked_first)
    bright = run(21, bright=1.1)
    assert all(s.decision.outcome == "fail" and s.replicated for s, _ in bright), bright
    assert all(sequential.CONFIRM * start in a for _, a in bright)
    below = run(22, lead=sequential.PATH_FIRST // 2, trials=10)
    assert all(a[0] == sequential.CONFIRM * start for _, a in below), below


def test_the_control_is_rendered_only_where_a_rejection_came_back():
    """path beside a confirming batch is read only at what came back in it:
    a first look 10 % dark at one pixel whose confirming batch is not
    renders no control (f91's full run: 20 s of controls nothing read);
    an estimator dark there throughout renders it at every confirmation."""
    mean = np.ones((P, P, 3))
    ref = fixed(mean, var=4e-6 * 10_000)
    rng = np.random.default_rng(12)

    def draw(spp, k, scale):
        x = 1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1))
        x[:, 0, 0] *= scale
        return np.repeat(x, 3, axis=-1)

    def run(later):
        calls = []

        def control(look, spp, k, *_):
            calls.append(look)
            return spp, draw(spp, k, 1.0)
        d = sequential.settle([(1024, draw(1024, K, 0.9))], ref, reader(mean),
                              lambda look, spp, k: (spp, draw(spp, k, later)), EPSILON, 16,
                              control=control)[0]
        return d, calls

    fluke, calls = run(later=1.0)
    assert "not replicated" in fluke.replication and calls == [], (fluke, calls)
    real, calls = run(later=0.9)
    assert real.decision.outcome == "fail" and real.replicated and calls == [1], (real, calls)


# ------------------------- path's own renders as the control -------------------------

def rare_pixel(rng, k=8, spp=256, q=0.003, hits=None, scale=1.0):
    """K renders (k, P, P, 3) of a smooth scene with one pixel, (0, 0), whose
    value rests on rare sub-pixel hits (probability ``q`` per sample, 0.8
    each: a sliver of a bright edge). ``hits`` (k,) are that pixel's hit
    counts, shared by every estimator on a rung (same seeds, same pixel
    samples); ``scale`` multiplies the smooth part (a biased estimator)."""
    x = scale * (1.0 + rng.normal(0, SIGMA / np.sqrt(spp), (k, P, P, 1)))
    x[:, 0, 0, 0] = hits * 0.8 / spp
    return np.repeat(x, 3, axis=-1)


def rare_reference(q=0.003):
    mean = np.full((P, P, 3), 1.0)
    mean[0, 0] = 0.8 * q
    return fixed(mean, var=1e-8, image_var=1e-10), mean


def judged(x, path, ref, mean, spp=256, **given):
    c, cp = statistics.compare(x, ref), statistics.compare(path, ref)
    events, n, carried = tails.tail_events([x], mean)
    return evidence.bias_outcome(c, events, n, spp * n, carried,
                                 control=evidence.control_pixels(cp), **given)


def test_a_pixel_path_misses_as_much_on_the_same_samples_is_not_counted():
    """The estimator and path saw no hit where six were expected: both are
    darker there, with no firefly. Without the control the estimator fails;
    with it, that pixel is path's as much (inconclusive, saying so), and a
    darker pixel that path does not share still fails."""
    rng = np.random.default_rng(3)
    ref, mean = rare_reference()
    hits = np.zeros(8, int)
    x, path = rare_pixel(rng, hits=hits), rare_pixel(rng, hits=hits)
    c = statistics.compare(x, ref)
    events, n, carried = tails.tail_events([x], mean)
    assert evidence.bias_outcome(c, events, n, 256 * n, carried).outcome == "fail"
    d = judged(x, path, ref, mean)
    assert d.outcome == "inconclusive" and "path's own renders" in d.reason, d.reason
    assert d.rejected_down == 1
    x[:, 5, 5] -= 0.3                       # a bias at a pixel path does not share
    assert judged(x, path, ref, mean).outcome == "fail"


def test_path_against_its_own_reference_fails_only_on_the_image_mean():
    rng = np.random.default_rng(4)
    ref, mean = rare_reference()
    hits = np.zeros(8, int)
    path = rare_pixel(rng, hits=hits)
    assert judged(path, path, ref, mean, is_control=True).outcome == "inconclusive"
    shifted = rare_pixel(rng, hits=hits, scale=0.98)     # a reference of other settings
    assert judged(shifted, shifted, ref, mean, is_control=True).outcome == "fail"


LADDER = (4, 16, 64, 256)


def ladder_outcomes(rng, q, scale=1.0):
    """(without the control, with it): the outcomes of one estimator's
    pooled ladder (8 renders per rung) on the rare-pixel scene, hits drawn
    per render and shared with path's ladder."""
    ref, mean = rare_reference(q)
    hits = {s: rng.binomial(s, q, 8) for s in LADDER}
    xs = {s: rare_pixel(rng, hits=hits[s], spp=s, q=q, scale=scale) for s in LADDER}
    ps = {s: rare_pixel(rng, hits=hits[s], spp=s, q=q) for s in LADDER}
    c = statistics.compare(statistics.Moments.pooled(xs), ref)
    control = evidence.control_pixels(statistics.compare(statistics.Moments.pooled(ps), ref))
    events, n, carried = tails.tail_events(list(xs.values()), mean, list(xs))
    samples = sum(8 * s for s in LADDER)
    return tuple(evidence.bias_outcome(c, events, n, samples, carried, control=cp).outcome
                 for cp in (None, control))


def test_the_control_keeps_false_fails_at_alpha_and_the_power_on_a_twin():
    """300 trials of a correct estimator's ladder on the rare-pixel scene
    (one hit per 1000 samples; the pooled ladder expects 2.7 in all): without
    the control the rare pixel fails it far more often than α (about 8 %);
    with it, at most α (binomial bound at 0.001). A twin 2 % too dark is
    still caught every time (its image mean, and pixels path does not share)."""
    rng = np.random.default_rng(11)
    found = [ladder_outcomes(rng, 0.001) for _ in range(300)]
    plain = sum(a == "fail" for a, _ in found)
    controlled = sum(b == "fail" for _, b in found)
    assert plain > stats.binom.ppf(0.999, 300, ALPHA), plain
    assert controlled <= stats.binom.ppf(0.999, 300, ALPHA), controlled
    twins = [ladder_outcomes(rng, 0.001, scale=0.98)[1] for _ in range(30)]
    assert twins.count("fail") == 30, twins


def test_scenes_and_cases_render_no_batch_to_confirm_a_bias_by_design(monkeypatch):
    """The stages' wiring of ``confirm``: in a scene comparison an estimator
    biased by design (bayesian_hemisphere) reads its first look only and
    confirms nothing; in a failure case it goes on where undecided but
    confirms nothing; Monte Carlo estimators keep both (their settle calls
    are the same but for these two arguments). On the real map of a sun,
    the tests of the estimators that do not sample the emitters stop where
    their budget cannot decide (the sun split follows); none other does."""
    import types

    from mcillum.validation.stages import scene, sun_split

    calls = {}

    def spy(first, reference, read, more, epsilon, growth, looks=sequential.LOOKS, **kw):
        calls[name] = (looks, kw["confirm"], kw["control"] is not None, kw["split_follows"])
        d = evidence.Decision(outcome="pass", reason="")
        c = types.SimpleNamespace(passed=True, pass_fraction=1.0, min_p=1.0, pooled_p=[1.0],
                                  alpha_pixel=0.01, summary=lambda: "")
        return evidence.Settled(decision=d, looks=1, samples=1, budget=1), c

    monkeypatch.setattr(sequential, "settle", spy)
    ref, mean = reference()
    ref.mean, ref.spp = mean, 10_000
    ref.moments = lambda: ref
    x = renders(np.random.default_rng(6), k=4)
    names = ("bayesian_hemisphere", "cosine_hemisphere")
    run = types.SimpleNamespace(sequential=types.SimpleNamespace(
        scene_epsilon=0.02, scene_budget=16), growth=lambda b: b)
    ctx = types.SimpleNamespace(
        reference=ref, run=run, plan=types.SimpleNamespace(ladder=[SPP]), sun=None,
        resolved={}, disc=False,
        integrators=dict.fromkeys((*names, "path")),
        stacks={SPP: {n: types.SimpleNamespace(images=x) for n in names}},
        evidence={n: evidence.Evidence(comparison=object(), events=np.zeros((P, P)),
                                       samples=SPP * 4) for n in names})
    for name in names:                               # the spy reads `name`
        scene.settle(types.SimpleNamespace(**{**vars(ctx), "evidence": {
            name: ctx.evidence[name]}}))
    assert calls == {"bayesian_hemisphere": (1, False, False, False),
                     "cosine_hemisphere": (20, True, True, False)}
    monkeypatch.setattr(sun_split, "terms", lambda ctx: (0.05, 1024))
    monkeypatch.setattr(sun_split, "_reader", lambda ctx, name: None)
    monkeypatch.setattr(sun_split.common, "first_look", lambda ctx: (SPP, 4))
    case = types.SimpleNamespace(reference=ref, integrators=ctx.integrators, sun=None,
                                 disc=False)
    monkeypatch.setattr(sun_split, "BatchTest", lambda **kw: kw)
    for name in names:
        sun_split.settled_test(case, name, x)
    assert calls == {"bayesian_hemisphere": (20, False, False, False),
                     "cosine_hemisphere": (20, True, True, False)}
    sunny = types.SimpleNamespace(**{**vars(case), "sun": {"texels": 6}})
    for name in (*names, "mis"):
        sun_split.settled_test(sunny, name, x)
    assert {n: c[3] for n, c in calls.items()} == {
        "bayesian_hemisphere": True, "cosine_hemisphere": True, "mis": False}
    widened = types.SimpleNamespace(**{**vars(sunny), "disc": True})
    for name in names:
        sun_split.settled_test(widened, name, x)
    assert not any(c[3] for c in calls.values())


def test_the_windows_around_the_pixels_read_merge_clip_and_give_up():
    """Each pixel with ``border`` pixels around it, clipped to the film;
    overlapping windows merged; more than WINDOWS, or half the film: the
    whole film (None)."""
    px = np.zeros((32, 32), bool)
    px[0, 0] = True                                      # clipped at the corner
    assert common.windows(px, 2) == [(0, 0, 3, 3)]
    px[3, 3] = True                                      # overlaps the first
    assert common.windows(px, 2) == [(0, 0, 6, 6)]
    px[20, 25] = True
    assert common.windows(px, 0) == [(0, 0, 1, 1), (3, 3, 1, 1), (25, 20, 1, 1)]
    many = np.zeros((32, 32), bool)
    many[::8, ::8] = True                                # 16 pixels, 8 apart
    assert len(common.windows(many[:16, :16], 1)) == 4
    assert common.windows(many, 1) is None
    assert common.windows(np.ones((4, 4), bool)) is None
    assert common.windows(np.zeros((4, 4), bool)) is None


def test_black_renders_against_a_black_reference_fail_as_nothing_tested():
    """An estimator's renders and the reference identically zero where it is
    tested: the test finds no rejection, and the pass would be vacuous, so
    the decision is a fail that says nothing was tested (no further batch
    is rendered for it). The same renders lit against a lit reference pass."""
    black = np.zeros((K, P, P, 3))
    ref = statistics.Moments(np.zeros((P, P, 3)), np.zeros((P, P, 3)), 10_000, np.zeros(3),
                             np.zeros(3))

    def more(look, spp, k):
        raise AssertionError("a vacuous pass is not rendered on")

    got, _ = sequential.settle([(SPP, black)], ref, reader(np.zeros((P, P, 3))), more,
                               EPSILON, GROWTH)
    assert got.decision.outcome == "fail" and "nothing tested" in got.decision.reason
    rng = np.random.default_rng(3)
    lit = 1.0 + rng.normal(0, 0.01, (K, P, P, 3))
    mean = np.ones((P, P, 3))
    passed, _ = sequential.settle([(SPP, lit)], fixed(mean), reader(mean), more, EPSILON,
                                  GROWTH)
    assert passed.decision.outcome == "pass", passed.decision.reason
