"""The failures group: heavy-tail statistics, the sun split, verdicts, the
opt-in biased image, the glossy sweep, and no NaN/Inf/negative radiance from
any estimator in any failure case across 64 seeds.

Verdicts use the batch-means test of validation/stats/statistics.py at family-wise
α = 0.01 (Šidák over pixels × channels, plus the image-mean test), read by the
rules of evidence (checks/evidence.py) and continued on fresh batches until it
decides or its budget is spent (stages/sequential.py; α spent over the looks);
a rejection that counts is confirmed on a fresh batch. The same case run with a
cosine estimator whose pdf is 5 % off, or clamped, must come out "biased".
"""

import numpy as np
import pytest

from mcillum.envmaps import procedural, sun
from mcillum.integrators.core import registry
from mcillum.validation import pipeline
from mcillum.validation.plan import profiles
from mcillum.validation.run import renders
from mcillum.validation.stats import replication, statistics, tails
from mcillum.validation.checks import sun as sun_rules
from mcillum.validation.checks.evidence import FAILING, HEAVY
from mcillum.validation.stages import sequential
from mcillum.validation.stages.context import Run

from conftest import ALL_ESTIMATORS, SCENES
from twins import clamped_class, path_at_depth_class, radiance_clamp_class, wrong_pdf_class

# ------------------------------ Definitions ---------------------------------


def test_firefly_fraction_counts_pixels_ten_times_the_reference():
    ref = np.ones((2, 2, 3))
    renders_ = np.ones((4, 2, 2, 3))
    renders_[0, 0, 0] = 10.5          # a firefly
    renders_[1, 0, 1] = 9.0           # bright, but under 10×
    assert tails.firefly_fraction(renders_, ref) == pytest.approx(1 / 16)
    # black reference pixels are floored at 1 % of the image mean
    ref[1, 1] = 0.0                   # floor: 0.01 × 0.75, threshold 0.075
    renders_[:, 1, 1] = 0.0
    renders_[2, 1, 1] = 0.05
    assert tails.firefly_fraction(renders_, ref) == pytest.approx(1 / 16)
    renders_[2, 1, 1] = 0.2
    assert tails.firefly_fraction(renders_, ref) == pytest.approx(2 / 16)


def test_spp_to_match_scales_with_the_relmse_ratio():
    rng = np.random.default_rng(1)
    path = rng.exponential(0.01, 64)
    est = 4 * path
    m = tails.spp_to_match(est, path, 16)
    assert m.spp == pytest.approx(64)
    assert m.low < 64 < m.high


def test_percentiles_are_ordered():
    p = tails.percentiles(np.random.default_rng(2).lognormal(size=64))
    assert p.median <= p.p90 <= p.p99 <= p.max


def test_sun_split_finds_a_bright_cap_and_its_solid_angle():
    # a 5° disc 300× brighter than a unit sky, off the pole
    rgb = procedural.constant(1.0, 512, 256) + procedural.cap(
        300.0, 5.0, (0.6, 0.8, 0), 512, 256, supersample=4)
    sunless, facts = sun.split(rgb)
    cap = 2 * np.pi * (1 - np.cos(np.radians(5.0)))
    assert facts["solid_angle"] == pytest.approx(cap, rel=0.05)
    # its power: 300·Ω of (4π + 300·Ω)
    assert facts["power_share"] == pytest.approx(300 * cap / (4 * np.pi + 300 * cap), rel=0.05)
    assert (sunless[sun.sun_mask(rgb)] == 0).all() and np.isfinite(sunless).all()
    # linear split: the sunless map plus the sun texels is the map
    assert np.allclose(sunless + np.where(sun.sun_mask(rgb)[..., None], rgb, 0), rgb)


def test_widened_sun_keeps_the_sun_and_its_radiance_on_a_larger_disc():
    """The widened map: the sun's texels unchanged, a disc of the asked solid
    angle about it at the sun's power-weighted radiance, the rest of the map
    unchanged; a map without a sun has nothing to widen."""
    rgb = procedural.constant(1.0, 512, 256) + procedural.cap(
        300.0, 1.0, (0.6, 0.8, 0), 512, 256, supersample=4)
    mask = sun.sun_mask(rgb)
    out, facts = sun.widen(rgb, 0.05)
    assert facts["solid_angle"] == pytest.approx(0.05, rel=0.05)
    disc = (out != rgb).any(axis=-1)
    assert not (disc & mask).any() and (out[mask] == rgb[mask]).all()
    # the disc is round about the cap's centre, and at the sun's radiance
    d = procedural.directions(rgb.shape[1], rgb.shape[0])[:, :, 0]
    centre = np.array([0.6, 0.8, 0.0])
    angle = np.degrees(np.arccos(np.clip(d[disc] @ centre, -1, 1)))
    assert angle.max() < 8.0 and np.allclose(out[disc], out[disc][0])
    inside = (rgb[mask] * 1.0)
    assert inside.min(axis=0).max() <= out[disc][0].max() <= inside.max() * 1.001
    # what is neither sun nor disc is untouched
    assert (out[~disc & ~mask] == rgb[~disc & ~mask]).all()
    with pytest.raises(ValueError, match="no sun"):
        sun.widen(procedural.constant(1.0, 64, 32))


def _sun_row(widened: str | None, sunless: str = "pass"):
    """A hemisphere estimator's row on a sun case whose real-sun test spent its
    budget (inconclusive), with the sunless and widened outcomes given."""
    from mcillum.validation.results import BatchTest, CaseRow, Percentiles, SunSplit, TailNumbers

    test = BatchTest(passed=False, pass_fraction=0.9, min_p=1e-9, pooled_p=[0.3] * 3,
                     alpha_pixel=1e-6, test="rejected", outcome="inconclusive",
                     reason="darker at 3 px, but heavy-tailed", looks=8,
                     samples_per_pixel=131072)
    split = SunSplit(sun={"solid_angle": 2e-4}, sunless_passed=sunless != "fail",
                     sunless_test="", sunless_reference_mean=0.05,
                     expected_sun_hits_per_pixel=4.0, sun_share_of_image=0.4,
                     sunless_outcome=sunless, sunless_reason=f"{sunless} without the sun",
                     widened={"solid_angle": 0.2} if widened else None,
                     widened_outcome=widened, widened_reason=f"{widened} on the disc")
    numbers = TailNumbers(relmse=Percentiles(mean=1, median=0.1, p90=0.2, p99=10, max=100),
                          firefly_fraction=0.002, samples_per_pixel=1024, seeds=64,
                          seconds_median=0.01, image_mean_ratio=0.9, spp_to_match_path=None,
                          test=test, sun=split)
    return CaseRow(name="cosine_hemisphere", refused=False, numbers=numbers)


@pytest.mark.parametrize("widened, verdict", [("pass", "heavy-tailed"), ("fail", "biased"),
                                              ("inconclusive", HEAVY), (None, HEAVY)])
def test_the_widened_sun_decides_what_the_real_sun_left_open(widened, verdict):
    """A real-sun test that spent its budget is decided by the widened twin:
    its pass passes the case (the line says on what), its fail fails it, and
    anything else stays inconclusive; a bias without the sun fails first."""
    from mcillum.validation.checks import cases as case_checks

    row = _sun_row(widened)
    assert case_checks.case_verdict(row, 64) == verdict
    line = case_checks.verdict_line(verdict, row.numbers)
    if widened in ("pass", "fail"):
        assert "widened to 0.2 sr" in line and f"{widened} on the disc" in line
    assert case_checks.case_verdict(_sun_row("pass", sunless="fail"), 64) == "biased"


def test_a_partly_hidden_source_excuses_dark_pixels_not_a_dark_image():
    """On the widened sun's map a pixel that sees the disc through a sliver
    is darker until its hits arrive: a fail or an inconclusive resting only
    on such pixels leaves the image mean to decide (a pass, which the
    sequential test then holds to ±ε); one whose image mean is darker stays
    a fail, or undecided where a tail excused it; brighter pixels count."""
    from types import SimpleNamespace

    from mcillum.validation.checks import evidence

    def comparison(pooled_p=0.5, up_p=0.5):
        return SimpleNamespace(pixel_t=np.array([[-9.0, 0.5], [0.2, 0.1]]),
                               pixel_p=np.array([[1e-9, up_p], [0.5, 0.5]]), alpha_pixel=1e-6,
                               pooled_p=np.array([pooled_p, 0.5, 0.5]), alpha_pooled=1e-3)
    dark = np.array([[True, False], [False, False]])

    def decided(outcome="fail", pooled=False, up=False):
        return evidence.Decision(outcome=outcome, reason="darker at 1 px", pixels=dark.copy(),
                                 pooled=np.array([pooled, False, False]), counted_up=up,
                                 samples_needed=1e6 if outcome == "inconclusive" else None)

    c = comparison()
    for outcome in ("fail", "inconclusive"):
        d = sun_rules.partly_hidden(decided(outcome), c)
        assert d.outcome == "pass" and not d.pixels.any() and d.samples_needed is None
    excused = comparison(pooled_p=1e-5)         # a darker image mean a tail excused
    assert sun_rules.partly_hidden(decided(), excused).outcome == "inconclusive"
    assert sun_rules.partly_hidden(decided("inconclusive"), excused).outcome == "inconclusive"
    assert sun_rules.partly_hidden(decided(pooled=True), excused).outcome == "fail"
    assert sun_rules.partly_hidden(decided(up=True), comparison(up_p=1e-9)).outcome == "fail"
    brighter = comparison(up_p=1e-9)            # an upward pixel a tail excused
    assert sun_rules.partly_hidden(decided("inconclusive"), brighter).outcome == "inconclusive"


# ---------------------------- Verdicts on cases -------------------------------

QUICK = {c.id: c for c in profiles.QUICK.failures}


def _case(case_id, **changes):
    from dataclasses import replace

    return replace(QUICK[case_id], **changes)


@pytest.fixture
def run_case(llvm, tmp_path):
    def run(case, estimators, seed_set=0):
        ctx = Run(profiles.QUICK, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out"),
                  seed_set=seed_set)
        out, checks = pipeline.failure_case(ctx, case, estimators)
        return {e.name: e for e in out.estimators}, checks, out
    return run


def path_mean(case) -> np.ndarray:
    """`path`'s image of a case's scene (4 × 256 spp, reference seeds): what
    the firefly clamp of a control is set from."""
    scene = renders.load_scene(SCENES / f"{case.scene}.xml", res=case.res, **case.defines)
    path = renders.make_integrator("path", {})
    return np.mean([renders.render(scene, path, 256, 10 ** 6 + i).image[..., :3]
                    for i in range(4)], axis=0)


def run_with_controls(run_case, case):
    """The case with cosine and uniform (correct, heavy-tailed), mis and path
    (correct), and the negative controls: cosine with its pdf 5 % too high,
    cosine clamped at 10× path's pixel value (no firefly left), cosine with
    every sample clamped at radiance 100, 1000 and 15 000 (fireflies left:
    the bias a renderer's clamp adds; the last bites only the sun's hits),
    path at max_depth 2."""
    controls = [wrong_pdf_class("cosine_hemisphere", 1.05),
                clamped_class(path_mean(case)), radiance_clamp_class(100.0),
                radiance_clamp_class(1000.0), radiance_clamp_class(15000.0),
                path_at_depth_class(2)]
    for c in controls:
        registry.register(c)
    try:
        rows, checks, out = run_case(case, ["cosine_hemisphere", "uniform_hemisphere", "mis",
                                            *[c.plugin_name for c in controls], "path"])
    finally:
        for c in controls:
            registry.unregister(c.plugin_name)
    return rows, checks, [c.plugin_name for c in controls]


def test_sun_case_is_decided_on_the_split_and_fails_the_controls(run_case):
    """sun_sky, 8² px, 16 spp × 64 seeds, then the sequential test
    (stages/sequential.py; α = 0.01 spent over the looks): path and mis are
    fine; cosine misses the sun (0.0002 sr) in most renders; its test finds
    no bias, and stops where deciding would need more than BEYOND_BUDGET ×
    its budget (1024× its first samples), as the sun split decides it. The
    controls are biased: the wrong pdf without the sun, the clamps (with
    fireflies or without) and the missing bounces with the sun. A clamp at
    radiance 15 000 darkens only the sun's hits: the real sun cannot show
    it at this budget, the widened sun does (envmaps/sun.py), and so it
    does not pass as inconclusive."""
    rows, checks, controls = run_with_controls(run_case, QUICK["failures.heavy_tail.sun_sky"])
    assert rows["path"].verdict == "fine" and rows["mis"].verdict == "fine"
    cos = rows["cosine_hemisphere"]
    assert cos.verdict in (HEAVY, "heavy-tailed"), cos.verdict
    n = cos.numbers
    assert n.test.outcome == "inconclusive" and "would decide" in n.test.reason
    assert n.test.samples_needed > sequential.BEYOND_BUDGET * n.test.samples_per_pixel
    # decided on the split map: without the sun, and with it widened
    assert n.sun.sunless_outcome == "pass" and n.sun.widened["solid_angle"] > 100 * \
        n.sun.sun["solid_angle"]
    assert (cos.verdict == "heavy-tailed") == (n.sun.widened_outcome == "pass")
    assert n.relmse.max > 100 * n.relmse.median            # heavy tail
    assert n.spp_to_match_path.spp > 16 * 10
    assert rows["uniform_hemisphere"].verdict not in FAILING
    wrong, clamped, clamp100, clamp1000, clamp15000, shallow = (rows[c] for c in controls)
    assert wrong.verdict == "biased" and wrong.numbers.sun.sunless_outcome == "fail"
    assert clamped.verdict == "biased" and clamped.numbers.test.tail_events == 0
    for clamp in (clamp100, clamp1000):                     # fireflies do not excuse them
        assert clamp.verdict == "biased" and clamp.numbers.test.tail_events > 0, clamp
    assert clamp15000.verdict == "biased"
    assert clamp15000.numbers.test.outcome == "inconclusive"    # the real sun cannot tell
    assert clamp15000.numbers.sun.widened_outcome == "fail"
    assert shallow.verdict == "biased" and shallow.numbers.test.replicated
    failed = {c.id for c in checks if c.outcome == "fail"}
    assert failed == {f"failures.heavy_tail.sun_sky/{c}/stable" for c in controls}
    assert set(cos.images) == {"median", "worst"}


FULL = {c.id: c for c in profiles.FULL.failures}


@pytest.mark.slow
@pytest.mark.parametrize("case", [QUICK["failures.heavy_tail.probe_spheres_sunrise"],
                                  FULL["failures.heavy_tail.sun_sky"]],
                         ids=["quick sunrise", "full sun_sky"])
def test_sun_cases_fail_the_controls(run_case, case):
    """The same on probe_spheres under the sunrise probe (its sun is a real
    one, 1024×512 texels, 4e4 at its peak), and on sun_sky at the full
    profile's budget (32², 16 spp × 128 seeds)."""
    rows, checks, controls = run_with_controls(run_case, case)
    for name in ("cosine_hemisphere", "uniform_hemisphere", "mis", "path"):
        assert rows[name].verdict not in FAILING, (name, rows[name].verdict)
    for c in controls:
        assert rows[c].verdict == "biased", (c, rows[c].verdict)


def test_heavy_tail_case_on_a_map_without_a_sun_is_not_split(run_case):
    """A heavy-tail case given a map with no sun (courtyard: a user's
    profile may name any map): nothing is split, no unseen sun excuses a
    darker image, and a pdf 5 % high fails on the map itself."""
    case = _case("failures.heavy_tail.lone_sphere_sunrise", label="lone_sphere_courtyard",
                 defines={"envmap": "courtyard"}, seeds=16)
    wrong = wrong_pdf_class("cosine_hemisphere", 1.05)
    registry.register(wrong)
    try:
        rows, checks, _ = run_case(case, ["cosine_hemisphere", wrong.plugin_name, "path"])
    finally:
        registry.unregister(wrong.plugin_name)
    for row in rows.values():
        assert row.numbers.sun is None, row.name
    assert rows["cosine_hemisphere"].verdict not in FAILING
    bad = rows[wrong.plugin_name]
    assert bad.verdict == "biased" and bad.numbers.test.outcome == "fail"
    assert "sun" not in bad.numbers.test.reason


def test_unreachable_case_refuses_and_measures_the_opt_in_bias(run_case):
    rows, checks, _ = run_case(_case("failures.unreachable.point_light", res=4, seeds=8),
                               ["cosine_hemisphere", "emitter_sampling", "path"])
    cos = rows["cosine_hemisphere"]
    assert cos.refused and "'key_light'" in cos.message
    assert cos.verdict == "biased (opt-in)"
    assert cos.numbers.missing_fraction == pytest.approx(1.0)    # only a point light
    assert rows["emitter_sampling"].verdict in ("fine", "heavy-tailed")
    assert all(c.passed for c in checks)
    assert any(c.id.endswith("cosine_hemisphere/refuses") for c in checks)


def test_glossy_sweep_reports_relmse_per_value(run_case):
    case = _case("failures.glossy.roughness", res=4, seeds=4, sweep=("alpha", (0.5, 0.05)))
    rows, checks, out = run_case(case, ["cosine_hemisphere", "bsdf_sampling", "path"])
    for row in rows.values():
        assert len(row.relmse) == 2 and np.isfinite(row.relmse).all()
    # a narrower lobe hurts the cosine estimator more than BSDF sampling
    assert rows["cosine_hemisphere"].growth > rows["bsdf_sampling"].growth
    assert all(c.passed for c in checks)


# ------------------------- No NaN/Inf/negative anywhere -----------------------

FAILURE_SCENES = [
    ("sun_sky", {}), ("probe_spheres", {"envmap": "sunrise"}),
    ("probe_spheres", {"envmap": "city"}), ("probe_spheres", {"envmap": "interior"}),
    ("glossy_sphere", {"alpha": 0.01}), ("glossy_phong", {"exponent": 3000}),
    ("point_light", {}), ("smooth_glass", {}),
]


@pytest.mark.parametrize("scene, defines", FAILURE_SCENES,
                         ids=[f"{s}-{'-'.join(map(str, d.values())) or 'default'}"
                              for s, d in FAILURE_SCENES])
def test_no_estimator_emits_nan_inf_or_negative_over_64_seeds(llvm, scene, defines):
    from conftest import SCENES

    # (8² px as tests/test_scenes.py, so the kernels compiled there are reused)
    loaded = renders.load_scene(SCENES / f"{scene}.xml", res=8, **defines)
    for name in ALL_ESTIMATORS + ["path"]:
        integrator = renders.make_integrator(name, {"allow_unreachable": True}
                                             if name != "path" else {})
        x = np.stack([renders.render(loaded, integrator, 4, seed).image
                      for seed in range(64)])
        assert np.isfinite(x).all(), (scene, name)
        assert x.min() >= 0, (scene, name, x.min())


def test_a_rejection_counts_only_if_it_replicates():
    rng = np.random.default_rng(4)
    ref = statistics.Moments.of(rng.normal(1.0, 0.05, (64, 4, 4, 3)))
    same = lambda: rng.normal(1.0, 0.05, (64, 4, 4, 3))        # noqa: E731
    shifted = lambda: rng.normal(1.1, 0.05, (64, 4, 4, 3))     # noqa: E731
    real = replication.replicated_compare(shifted(), ref, shifted)
    assert not real.passed and real.replicated
    # a first batch whose mean at one pixel came out low by chance (as when a
    # tail went unseen) rejects, but fresh renders do not repeat it
    wild = same()
    wild[:, 0, 0] -= 0.05
    fluke = replication.replicated_compare(wild, ref, same)
    assert not fluke.passed and fluke.replicated is False
    assert replication.replicated_compare(same(), ref, same).replicated is None


HARDEST = [QUICK["failures.heavy_tail.sun_sky"],
           QUICK["failures.heavy_tail.probe_spheres_sunrise"],
           QUICK["failures.heavy_tail.probe_spheres_interior"],
           profiles.FailureCase(group="heavy_tail", scene="glossy_sphere", res=8, spp=16,
                                seeds=64, defines={"alpha": 0.02},
                                label="glossy_sphere_alpha_0.02")]


@pytest.mark.slow
@pytest.mark.parametrize("seed_set", [3, 4, 5])
@pytest.mark.parametrize("case", HARDEST, ids=lambda c: c.label or c.scene)
def test_no_correct_estimator_is_called_biased_on_the_hardest_cases(run_case, case, seed_set):
    """False fails on the hardest cases, with seed sets 3, 4 and 5 (plan/
    seeds.py), which no rule was tuned on (the profile uses set 0; sets 1
    and 2 tuned the rules before the sequential tests): no shipped
    estimator is "biased" (each sequential test at α = 0.01 spent over its
    looks, a fail confirmed on a fresh batch)."""
    rows, checks, _ = run_case(case, [*ALL_ESTIMATORS, "path"], seed_set)
    verdicts = {n: r.verdict for n, r in rows.items()}
    assert not any(v in FAILING for v in verdicts.values()), verdicts
    assert not [c for c in checks if c.outcome == "fail"]


def test_a_refusal_is_kept_without_the_frames_that_hold_its_scene(tmp_path):
    """cases.probe_refusals keeps each estimator's refusal of the scene in
    ``ctx.refused``. With its traceback, the refusal's frames held the
    context and its scene in a cycle after the case was released, and every
    later render dispatched over that scene's objects until Python's
    collector came
    (docs/measurements.md#2026-12-05-ms-floor-recording-lingering): it is kept
    without."""
    from mcillum.validation.stages import cases, common
    from mcillum.validation.stages.context import Context
    profile = profiles.Profile(name="quick", runs=())
    plan = profiles.FailureCase(group="unreachable", scene="point_light", res=8, spp=4,
                                seeds=2, max_depth=2)
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / "out")),
                  plan, plan.id, ["cosine_hemisphere", "mis", "path"], dict(plan.defines))
    common.load(ctx)
    cases.probe_refusals(ctx)
    refusal = ctx.refused["cosine_hemisphere"]
    assert refusal is not None and "delta emitter" in str(refusal)
    assert refusal.__traceback__ is None
    assert ctx.refused.get("mis") is None
