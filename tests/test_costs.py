"""The cost model and the equal-time numbers (validation/stats/costs.py) on
synthetic timings and errors whose truth is known: the intervals cover it
as often as they claim, exclude a wrong value, and the ranking ties only
what it cannot tell apart. No rendering."""

import math

import numpy as np
import pytest
from scipy import stats

from mcillum.validation.results import Interval
from mcillum.validation.run.stacks import Stack
from mcillum.validation.stages import budgets, speed
from mcillum.validation.stats import costs, metrics, tails

from conftest import disagreements

A, B = 4e-3, 2.5e-3                     # 4 ms per render, 2.5 ms per spp


def timings(rng, spp=(16, 64), repeats=5, noise=0.03):
    """Warm render times t = A + B·spp with multiplicative noise."""
    return {s: list((A + B * s) * rng.lognormal(0, noise, repeats)) for s in spp}


def coverage_floor(trials: int, level: float = 0.95, alpha: float = 0.01) -> int:
    """The fewest covering intervals out of ``trials`` that a correct level-
    ``level`` interval reaches with probability 1 − α (binomial lower
    quantile): below it, the interval is too narrow."""
    return int(stats.binom.ppf(alpha, trials, level))


def test_fit_recovers_a_and_b():
    model = costs.fit_cost(timings(np.random.default_rng(0), noise=0.0))
    assert model.fixed_s == pytest.approx(A) and model.per_spp_s == pytest.approx(B)
    assert model.fixed_s_ci.low == pytest.approx(A) and model.per_spp_s_ci.high == \
        pytest.approx(B)                                     # no noise, no width
    assert costs.spp_for(model, costs.seconds_at(model, 37)) == 37
    assert costs.spp_for(model, A / 2) == 1                  # 1 spp already exceeds it
    assert costs.overhead_share(model, costs.seconds_at(model, 16)) == pytest.approx(
        A / (A + 16 * B))


def test_a_negative_fitted_fixed_cost_predicts_no_negative_time():
    """A fit on a loaded machine once gave a = −2.2 s, and a budget of −2 s."""
    model = costs.fit_cost({1: [0.5, 0.6], 16: [0.4, 0.45], 64: [0.3, 0.35]})
    assert model.per_spp_s < 0
    assert costs.seconds_at(model, 16) == pytest.approx(max(model.fixed_s, 0))
    steep = costs.fit_cost({4: [0.01], 1024: [3.0]})
    assert steep.fixed_s < 0 < costs.seconds_at(steep, 4) == pytest.approx(4 * steep.per_spp_s)


def test_fit_needs_two_spp_values():
    with pytest.raises(ValueError, match="two spp values"):
        costs.fit_cost({16: [0.1, 0.1, 0.1]})


def test_bootstrap_intervals_cover_the_truth_and_exclude_a_wrong_b():
    """α = 0.01 on the coverage count (binomial, one-sided), 200 data sets of
    5 repeats at two spp values; the same intervals must exclude a b 20 %
    too large in nearly every data set (power). Plain percentile intervals
    failed the coverage floor (169 of 200 for b, floor 182; these: 187)."""
    rng = np.random.default_rng(1)
    trials = 200
    models = [costs.fit_cost(timings(rng), seed=i) for i in range(trials)]
    covered_b = sum(m.per_spp_s_ci.low <= B <= m.per_spp_s_ci.high for m in models)
    covered_a = sum(m.fixed_s_ci.low <= A <= m.fixed_s_ci.high for m in models)
    floor = coverage_floor(trials)
    assert covered_b >= floor and covered_a >= floor, (covered_a, covered_b, floor)
    wrong = sum(m.per_spp_s_ci.low <= 1.2 * B <= m.per_spp_s_ci.high for m in models)
    assert wrong <= trials // 20, wrong


def test_relmse_interval_is_student_t():
    values = [1.0, 2.0, 3.0, 4.0]
    mean, ci = costs.relmse_interval(values)
    half = stats.t.ppf(0.975, 3) * np.std(values, ddof=1) / 2
    assert mean == 2.5 and ci == pytest.approx((2.5 - half, 2.5 + half))
    assert costs.relmse_interval([0.1, 0.1, 0.1, 9.0])[1].low == 0.0   # clipped: relMSE ≥ 0


def test_efficiency_ratio_interval_covers_the_true_ratio():
    """Two estimators whose per-render relMSE and time are lognormal with
    known means: the ratio of efficiencies is known. K = 4 renders each, as
    the quick profile renders; α = 0.01 on the coverage count of 300 trials.
    The interval of an estimator 30 % less efficient excludes 1 most of the
    time when its renders vary by 5 % (power)."""
    rng = np.random.default_rng(2)
    trials, k, spread = 300, 4, 0.05
    truth = 0.7
    covered = excluded_one = 0
    for _ in range(trials):
        rel = 0.1 / truth * rng.lognormal(-spread ** 2 / 2, spread, k)
        base = 0.1 * rng.lognormal(-spread ** 2 / 2, spread, k)
        t = 0.05 * rng.lognormal(-0.0002, 0.02, k)
        t0 = 0.05 * rng.lognormal(-0.0002, 0.02, k)
        ratio, ci = costs.ratio_interval(rel, t, base, t0)
        covered += ci.low <= truth <= ci.high
        excluded_one += ci.high < 1.0
    assert covered >= coverage_floor(trials), covered
    assert excluded_one >= 0.9 * trials, excluded_one


def test_ranking_ties_only_overlapping_intervals():
    ranked = costs.ranking({"a": (10.0, Interval(9.0, 11.0)),
                            "b": (8.5, Interval(7.0, 9.5)),     # overlaps a and c
                            "c": (6.0, Interval(5.0, 7.5)),     # below a
                            "d": (1.0, Interval(0.5, 1.5))})
    assert [p.estimator for p in ranked] == ["a", "b", "c", "d"]
    assert [p.rank for p in ranked] == [1, 1, 2, 4]
    assert ranked[1].tied_with == ["a", "c"] and ranked[2].tied_with == ["b"]
    assert ranked[3].tied_with == []


def test_budgets_grow_until_the_fixed_cost_is_a_tenth():
    """budgets.budget_spp: `path`'s spp values grow by one factor until every
    estimator's fixed cost is at most 10 % of the largest budget (where
    efficiency is read), keeping their ratios, up to MAX_SCALE."""
    path = costs.fit_cost({4: [A + B * 4] * 3, 16: [A + B * 16] * 3})
    slow_start = costs.fit_cost({4: [0.04 + B * 4] * 3, 16: [0.04 + B * 16] * 3})
    spp = budgets.budget_spp({"path": path, "other": slow_start}, (4, 8, 16))
    assert spp[1] == 2 * spp[0] and spp[2] == 4 * spp[0]
    assert costs.seconds_at(path, spp[2]) >= 10 * 0.04 > costs.seconds_at(path, spp[2] - 4)
    # an estimator whose sample costs 80× path's: at least MIN_SPP of them fit
    # in the largest budget, where efficiency is read; the smaller one, a
    # quarter of it, has no room for them and does not render it (fits)
    slow = costs.fit_cost({4: [0.003 + 80 * B * 4] * 3, 16: [0.003 + 80 * B * 16] * 3})
    spp = budgets.budget_spp({"path": path, "other": slow}, (4, 16))
    def samples(seconds):
        return (seconds - slow.fixed_s) / slow.per_spp_s
    assert samples(costs.seconds_at(path, spp[-1])) >= budgets.MIN_SPP - 1e-9
    assert samples(costs.seconds_at(path, spp[-1] - 4)) < budgets.MIN_SPP
    assert budgets.fits(slow, costs.seconds_at(path, spp[-1]))
    assert not budgets.fits(slow, costs.seconds_at(path, spp[0]))
    assert budgets.fits(path, costs.seconds_at(path, spp[0]))
    cheap = costs.fit_cost({4: [5e-4 + 8 * B * 4] * 3, 16: [5e-4 + 8 * B * 16] * 3})
    assert budgets.budget_spp({"path": cheap}, (4, 8)) == [4, 8]  # already ≤ 10 %: as given
    # the smallest budget is at least MIN_BUDGET, whatever the fixed costs
    spp = budgets.budget_spp({"path": path}, (4, 8))
    assert costs.seconds_at(path, spp[0]) >= budgets.MIN_BUDGET \
        > costs.seconds_at(path, spp[0] - 1)
    # an estimator that learns (guided_path) gets MIN_LEARNER_SPP at the
    # largest; the same costs under a name that does not learn, no more
    learner = costs.fit_cost({4: [0.003 + 3 * B * 4] * 3, 16: [0.003 + 3 * B * 16] * 3})
    spp = budgets.budget_spp({"path": path, "guided_path": learner}, (4, 16))
    def trained(seconds):
        return (seconds - learner.fixed_s) / learner.per_spp_s
    assert trained(costs.seconds_at(path, spp[-1])) >= budgets.MIN_LEARNER_SPP - 1e-9
    assert trained(costs.seconds_at(path, spp[-1] - 4)) < budgets.MIN_LEARNER_SPP
    assert budgets.budget_spp({"path": path, "mis": learner}, (4, 16))[-1] < spp[-1]
    hopeless = costs.fit_cost({4: [10.0 + 1e-9 * 4] * 3, 16: [10.0 + 1e-9 * 16] * 3})
    assert budgets.budget_spp({"path": path, "other": hopeless}, (4,)) == [4 * budgets.MAX_SCALE]
    # path's model with a fixed cost fitted below 0 (times that grow faster
    # than spp): the budgets are path's times as costs.seconds_at reads
    # them, a counted as 0, so the learner's MIN_LEARNER_SPP is met by the
    # smallest whole factor, not by one 20 ms larger
    below = costs.fit_cost({16: [0.02] * 3, 64: [0.14] * 3})
    assert below.fixed_s < 0
    spp = budgets.budget_spp({"path": below, "guided_path": learner}, (4, 16))
    assert trained(costs.seconds_at(below, spp[-1])) >= budgets.MIN_LEARNER_SPP - 1e-9
    assert trained(costs.seconds_at(below, spp[-1] - 4)) < budgets.MIN_LEARNER_SPP

def test_two_runs_are_compared_on_ratios_and_reversed_pairs():
    from mcillum.validation.results import Placement, Ratio
    first = {"a": Ratio(ratio=2.0, ci=Interval(1.8, 2.2)),
             "b": Ratio(ratio=0.5, ci=Interval(0.46, 0.54)),
             "path": Ratio(ratio=1.0, ci=Interval(0.9, 1.1))}
    ranked = [Placement(estimator="a", rank=1, tied_with=[]),
              Placement(estimator="path", rank=2, tied_with=["b"]),
              Placement(estimator="b", rank=2, tied_with=["path"])]
    assert costs.separated(ranked) == {("a", "path"), ("a", "b")}
    assert disagreements(first, first, ranked, ranked) == []
    drifted = {**first, "b": Ratio(ratio=0.59, ci=Interval(0.54, 0.64))}        # +18 %
    reversed_ = [Placement(estimator="b", rank=1, tied_with=[]),
                 Placement(estimator="a", rank=2, tied_with=[]),
                 Placement(estimator="path", rank=3, tied_with=[])]
    found = disagreements(first, drifted, ranked, reversed_)
    assert len(found) == 2 and "b: efficiency" in found[0] and "a beat b" in found[1]
    # a run that states an interval wider than ±15 % claims no such agreement,
    # nor does a figure the reference's noise bounds (a lower bound)
    vague = {**first, "b": Ratio(ratio=0.59, ci=Interval(0.45, 0.77))}
    bound = {**first, "b": Ratio(ratio=0.59, ci=Interval(0.55, 0.63),
                                 kind="reference_limited")}
    assert disagreements(first, vague, ranked, ranked) == []
    assert disagreements(first, bound, ranked, ranked) == []


def test_a_missed_budget_is_corrected_toward_it_in_bounded_steps():
    """budgets.corrected: the next try's spp from the last try's median and
    the model's fixed cost; none where the median is within ±10 % or 1 spp
    is already too slow; a step is at most ×2 either way, so one try slowed
    by the machine's load cannot send an estimator to 1 spp."""
    from mcillum.validation.results import Try
    model = costs.fit_cost({4: [A + B * 4] * 3, 16: [A + B * 16] * 3})
    budget = A + B * 40

    def at(spp, factor=1.0):
        return Try(spp=spp, wall_seconds=[(A + B * spp) * factor] * 4)

    assert budgets.corrected(model, [at(40)], budget) is None
    assert budgets.corrected(model, [at(40, 1.05)], budget) is None
    slow = budgets.corrected(model, [at(40, 1.3)], budget)
    assert slow < 40 and abs((A + B * slow) * 1.3 - budget) <= 0.1 * budget
    assert budgets.corrected(model, [at(40, 0.2)], budget) == 80           # at most ×2
    assert budgets.corrected(model, [at(40, 8.0)], budget) == 20           # at most ÷2
    assert budgets.corrected(model, [at(1, 1.0)], A / 2) is None          # 1 spp too slow
    # never the spp that just missed: a slow first try steepened the line,
    # which rounds back to 4 spp; 5 is tried (bayesian_importance at 256²)
    coarse = costs.fit_cost({1: [0.01 + 0.105] * 3, 16: [0.01 + 0.105 * 16] * 3})
    tries = [Try(spp=6, wall_seconds=[0.827] * 4), Try(spp=4, wall_seconds=[0.503] * 4)]
    assert budgets.corrected(coarse, tries, 0.603) == 5
    fast = [Try(spp=2, wall_seconds=[0.20] * 4), Try(spp=4, wall_seconds=[0.503] * 4)]
    assert budgets.corrected(coarse, fast, 0.44) == 3                      # and downward


def test_a_budget_no_whole_spp_meets_is_named_and_not_chased():
    """budgets.unreachable: tries at n and n + 1 spp whose medians fall
    outside ±10 % on both sides of the budget (a learner's time jumps where
    it adds a training pass: guided_path at 128², 11 spp 127 ms, 12 spp
    165 ms against 144 ms) name the pair, and corrected() stops there for
    an estimator that learns instead of alternating; a pair within the
    tolerance, a pair on one side or one not adjacent is no such gap."""
    from mcillum.validation.results import Try
    model = costs.fit_cost({1: [0.02 + 0.009] * 3, 16: [0.02 + 0.009 * 16] * 3})

    def at(spp, ms):
        return Try(spp=spp, wall_seconds=[ms / 1e3] * 4)

    jump = [at(11, 126.8), at(12, 165.1)]
    assert budgets.unreachable(jump, 0.1436) == (11, 12)
    assert budgets.unreachable(jump[::-1], 0.1436) == (11, 12)
    assert budgets.corrected(model, jump, 0.1436, learns=True) is None
    assert budgets.corrected(model, jump, 0.1436) is not None       # (a load swing: again)
    assert budgets.corrected(model, jump[:1], 0.1436) > 11          # (before the gap is seen)
    assert budgets.unreachable([at(11, 126.8), at(12, 150.0)], 0.1436) is None
    assert budgets.unreachable([at(10, 110.0), at(11, 126.8)], 0.1436) is None
    assert budgets.unreachable([at(10, 110.0), at(12, 165.1)], 0.1436) is None
    # a second try at 11 that met the budget: the jump was the load's
    assert budgets.unreachable(jump + [at(11, 135.0)], 0.1436) is None


def test_efficiency_interval_covers_under_skewed_errors_and_drifting_timings():
    """Per-render relMSE lognormal with σ = 0.3 (three times the spread of
    any estimator's renders in the quick profile,
    docs/measurements.md#2026-12-02-speed-axis-net-efficiency) and timings that
    drift 30 % over the K renders with one in five 30 % slower (a shared
    machine): the ratio's interval keeps its coverage (α = 0.01 on the count of
    600 trials), the reference's share subtracted from both."""
    rng = np.random.default_rng(11)
    trials, k, truth, share = 600, 4, 0.5, costs.Share(0.004, 0.001)

    def renders(mean, spread):
        return share.value + mean * rng.lognormal(-spread ** 2 / 2, spread, k)

    def times():
        drift = 1 + 0.3 * rng.permutation(np.linspace(0, 1, k))
        return 0.05 * drift * rng.choice([1.0, 1.3], k, p=[0.8, 0.2])

    covered = 0
    for _ in range(trials):
        ratio, ci = costs.ratio_interval(renders(0.1 / truth, 0.3), times(),
                                         renders(0.1, 0.05), times(), share)
        covered += ci.low <= truth <= ci.high
    assert covered >= coverage_floor(trials), covered


def test_a_loaded_machine_widens_the_interval_by_its_share():
    """Load that comes and goes on longer time scales than a render set
    slows each set by its own factor, which the set's scatter cannot show:
    here log-normal with σ = 0.05 per set, and other processes using 0.7 of
    2 cores (a busy loop on one of them, as the slow speed test runs;
    efficiency ÷ path then moved by a log-SD of 0.06 from a quiet run's,
    docs/measurements.md#2026-12-05-loaded-machine-intervals). With the load's
    term (costs.load_log_se) the ratio's interval covers the quiet truth as
    often as it claims (α = 0.01 on 600 trials); without it, it does not. A
    quiet machine's term is 0, and it grows with the share used."""
    rng = np.random.default_rng(12)
    trials, k, truth = 600, 4, 0.7
    load = costs.load_log_se(0.7, 2)
    assert costs.load_log_se(None, 2) == costs.load_log_se(0.0, 2) == 0.0
    assert 0 < costs.load_log_se(0.2, 2) < load < costs.load_log_se(1.5, 2)

    def renders(mean):
        return mean * rng.lognormal(-0.05 ** 2 / 2, 0.05, k)

    def times():
        return 0.05 * rng.lognormal(0, 0.05) * rng.lognormal(0, 0.02, k)

    covered = {0.0: 0, load: 0}
    for _ in range(trials):
        rel, t, base, t0 = renders(0.1 / truth), times(), renders(0.1), times()
        for se in covered:
            ratio, ci = costs.ratio_interval(rel, t, base, t0, load_se=se, base_load_se=se)
            covered[se] += ci.low <= truth <= ci.high
    assert covered[load] >= coverage_floor(trials), covered
    assert covered[0.0] < coverage_floor(trials), covered


def test_an_error_at_the_reference_noise_gives_a_lower_bound():
    """An estimator whose renders differ from the reference only by the
    reference's own noise (relMSE ≈ its share): its efficiency is a lower
    bound, with an upper end of +inf, not a figure that moves with that noise."""
    share = costs.Share(0.01, 0.002)
    exact = [0.0101, 0.0099, 0.0102, 0.0098]
    path = [0.2, 0.21, 0.19, 0.2]
    t = [0.05] * 4
    ratio, ci = costs.ratio_interval(exact, t, path, t, share)
    assert ci.high == np.inf and 0 < ci.low
    e = costs.efficiency(path, t, share)
    assert e.resolved and e.value == pytest.approx(1 / ((0.2 - 0.01) * 0.05))


def test_a_learner_is_noted_with_its_figure_at_every_budget():
    """speed.learner_notes: an estimator that learns gets its efficiency ÷
    path at each budget, smallest first (the figure rises as the budget
    amortises its training); one that does not learn gets none, nor does a
    stage of one budget."""
    from mcillum.validation.results import Budget, BudgetRun

    def run(relmse, seconds, spp):
        v = relmse * (1 + 0.01 * np.arange(6))
        return BudgetRun(spp=spp, wall_seconds=[seconds] * 6, relmse=float(v.mean()),
                         relmse_ci=Interval(float(v.min()), float(v.max())),
                         relmse_per_render=list(v), on_budget=True)

    found = [Budget(seconds=0.03, path_spp=4, reference_relmse=0.0, estimators={
                 "path": run(0.1, 0.03, 4), "mis": run(0.05, 0.03, 8),
                 "guided_path": run(0.1 / 0.7, 0.03, 20)}),
             Budget(seconds=0.12, path_spp=16, reference_relmse=0.0, estimators={
                 "path": run(0.025, 0.12, 16), "mis": run(0.0125, 0.12, 32),
                 "guided_path": run(0.025 / 0.9, 0.12, 60)})]
    notes = speed.learner_notes(found)
    assert len(notes) == 1 and notes[0].startswith("guided_path"), notes
    assert notes[0].index("0.7 [") < notes[0].index("0.9 [") and "at 30 ms (20 spp)" in notes[0]
    assert speed.learner_notes(found[1:]) == []


def _firefly_renders(rng, shape: float, rate: float, k: int = 6, res: int = 64):
    """K renders of a flat image (reference 1) with Gaussian noise (σ = 0.3)
    and, at ``rate`` of the pixels, a firefly 10 + 5·Y with Y generalized
    Pareto of shape ``shape``: its squared error's tail has shape 2·shape.
    Returns (renders, reference, the true mean relMSE)."""
    x = 1 + 0.3 * rng.standard_normal((k, res, res, 1))
    hit = rng.random(x.shape) < rate
    x = np.where(hit, 10 + 5 * stats.genpareto.rvs(shape, size=x.shape, random_state=rng), x)
    # E(x − 1)² of a firefly: (9 + 5Y)², E Y = 1/(1 − ξ), E Y² = 2/((1 − ξ)(1 − 2ξ))
    ey, ey2 = 1 / (1 - shape), 2 / ((1 - shape) * (1 - 2 * shape))
    truth = ((1 - rate) * 0.09 + rate * (81 + 90 * ey + 25 * ey2)) / (1 + metrics.EPSILON)
    return np.repeat(x, 3, axis=-1), np.ones((res, res, 3)), truth


@pytest.mark.parametrize("shape, flagged_at_most, flagged_at_least", [
    (-0.2, 10, 0),          # bounded fireflies (squared error's tail −0.4): the t-interval holds
    (0.4, 100, 95),         # squared error's tail 0.8: finite mean, no finite variance
])
def test_fireflies_whose_error_renders_cannot_bound_make_the_efficiency_an_upper_bound(
        shape, flagged_at_most, flagged_at_least):
    """Fireflies at 2 % of 64² pixels over K = 6 renders (about 490 of them),
    100 trials on a seed the rule's thresholds were not tried on
    (docs/measurements.md#2026-12-05-efficiency-under-heavy-tails, "Efficiency
    under heavy tails"; seeds 7 and 8 agree). Light tail: tails.error_tail
    flags at most 10, and the efficiency's Student-t interval covers the truth
    as often as it claims. Heavy tail (squared error of shape 0.8): that
    interval covers it in about two trials of three, so it does not; the rule
    flags at least 95, and the interval the speed stage then states, [0, its
    upper end], covers it as often as a 95 % interval must."""
    rng = np.random.default_rng(2026)
    trials, flagged, plain, stated = 100, 0, 0, 0
    for _ in range(trials):
        x, r, truth = _firefly_renders(rng, shape, 0.02)
        e = costs.efficiency(metrics.per_render_relmse(x, r), 0.1 * rng.lognormal(0, 0.02, 6))
        true = 1 / (truth * 0.1)
        covers = e.ci.low <= true <= e.ci.high
        tail = tails.error_tail(x, r)
        flagged += tail.unbounded
        plain += covers
        stated += (true <= e.ci.high) if tail.unbounded else covers
    assert flagged_at_least <= flagged <= flagged_at_most, flagged
    assert stated >= coverage_floor(trials), stated
    if shape > 0.25:
        assert plain < coverage_floor(trials), plain


def test_an_error_tail_without_fireflies_is_bounded():
    """Renders with no firefly: nothing carried, no shape, bounded; the text
    of a heavy one names its count, share and shape."""
    rng = np.random.default_rng(1)
    r = np.ones((16, 16, 3))
    tail = tails.error_tail(1 + 0.1 * rng.standard_normal((4, 16, 16, 3)), r)
    assert (tail.fireflies, tail.share, tail.shape, tail.unbounded) == (0, 0.0, None, False)
    heavy = tails.ErrorTail(fireflies=120, share=0.6, shape=0.71, unbounded=True)
    assert "120 fireflies carry 60 %" in heavy.text() and "0.71 (≥ 0.5: no finite" in heavy.text()
    light = tails.ErrorTail(fireflies=120, share=0.6, shape=0.2, unbounded=False)
    assert "0.20 (< 0.5: a finite variance)" in light.text()
    few = tails.ErrorTail(fireflies=3, share=0.6, shape=None, unbounded=True)
    assert "too few (< 20)" in few.text()


def test_a_relmse_with_a_lower_bound_only_reads_so():
    """results.relmse_text: a two-sided interval, and one whose upper end is
    gone (heavy-tailed, or read back from JSON as NaN) as "[low, ∞)"."""
    from types import SimpleNamespace
    from mcillum.validation.results import relmse_text
    run = SimpleNamespace(relmse=0.21, relmse_ci=Interval(0.143, 0.278))
    assert relmse_text(run) == "0.21 [0.143, 0.278]"
    for high in (np.inf, np.nan):
        run.relmse_ci = Interval(0.143, high)
        assert relmse_text(run) == "0.21 [0.143, ∞)"


def test_a_render_that_cannot_meet_its_budget_has_its_efficiency_withheld(monkeypatch):
    """The speed stage (budgets.render, then speed.measure_speed) on fake
    renders whose timer is known: `path` and `mis` take what their cost
    model says, `emitter_sampling`'s timer reads a tenth of the budget
    whatever its spp (a busy core's launch, as cap_plane's 2 spp in 10 ms
    against 114 ms). Its corrections are bounded (CORRECTIONS), all miss,
    and its efficiency ÷ path is withheld (NaN, kind off_budget, a reason
    the summary table shows) and left out of the ranking, while `mis`,
    on budget, keeps its figure and interval."""
    from types import SimpleNamespace

    from mcillum.validation.results import json_io, speed_summary
    from mcillum.validation.run import references

    res, k, fixed, per_spp = 16, 6, 1e-3, 2e-3
    rng = np.random.default_rng(66)
    truth = np.ones((res, res, 3))
    sigma = {"path": 1.0, "mis": 0.5, "emitter_sampling": 0.3}   # noise of one sample
    budget = fixed + per_spp * 16                                 # path's 16 spp

    def fake_renders(sub, integrators, spps, renders, seeds_, label="", timed=False):
        out = {}
        for n, spp in spps.items():
            noise = sigma[n] / np.sqrt(spp) * rng.standard_normal((renders, res, res, 3))
            t = 0.1 * budget if n == "emitter_sampling" else fixed + per_spp * spp
            out[n] = Stack(n, spp, (truth + noise).astype(np.float32),
                           [t * (1 + 0.01 * i) for i in range(renders)], others=[None] * renders)
        return out

    monkeypatch.setattr(budgets.stacks, "interleaved", fake_renders)
    monkeypatch.setattr(budgets.timing, "warm", lambda *a, **kw: {})
    timings = {n: {1: [fixed + per_spp] * 3, 16: [fixed + 16 * per_spp] * 3} for n in sigma}
    executor = SimpleNamespace(timed_on=lambda: ["here"])
    from mcillum.validation.plan import seeds
    run = SimpleNamespace(executor=executor, stream=lambda name, block=0: seeds.stream(name, block))
    sub = SimpleNamespace(run=run, label="fake",
                          integrators=dict.fromkeys(sigma), reference=references.Reference(
                              truth, np.full(truth.shape, 1e-8), 64, 64, 1.0,
                              np.ones((64, 3))))
    ctx = SimpleNamespace(
        display=sub, plan=SimpleNamespace(display=SimpleNamespace(renders=k, res=res)),
        costs={n: costs.fit_cost({s: [min(t)] * 2 for s, t in v.items()})
               for n, v in timings.items()},
        timings=timings, budget_path_spp=[16], budget_stacks=[], budget_tries=[], notes=[],
        timing_load=[], timed_on=[], flip_maps={})
    assert budgets.render(ctx)
    tries = ctx.budget_tries[0]
    assert len(tries["emitter_sampling"]) == 1 + budgets.CORRECTIONS
    assert len(tries["mis"]) == 1 and len(tries["path"]) == 1
    speed.measure_speed(ctx)
    ratios = ctx.speed.efficiency_vs_path
    off, on = ratios["emitter_sampling"], ratios["mis"]
    assert off.kind == "off_budget" and math.isnan(off.ratio), off
    assert "off budget" in off.reason and f"{budget * 1e3:.3g} ms budget" in off.reason
    assert json_io.to_json(off)["ratio"] is None and json_io.to_json(off)["ci"] == [None, None]
    assert on.kind == "unbiased" and 0 < on.ci.low < on.ratio < on.ci.high < np.inf, on
    assert [p.estimator for p in ctx.speed.ranking] == ["mis", "path"]
    rows = {line.split(" | ")[0][2:]: line for line in speed_summary(ctx.speed)
            if line.startswith("| ") and " | " in line}
    assert "withheld: off budget" in rows["emitter_sampling"]
    assert f"{on.ratio:.3g} [" in rows["mis"]
    assert any("emitter_sampling: efficiency ÷ path withheld" in n for n in ctx.speed.notes)
