"""`mcillum validate`: verdicts, outputs, schema, resume and the reference cache."""

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import jsonschema
import numpy as np
import pytest
from scipy import stats

import mitsuba as mi

from mcillum import files
from mcillum.integrators.core import registry
from mcillum.envmaps import procedural
from mcillum.validation import cli, pipeline, results
from mcillum.validation.plan import profiles, scenes
from mcillum.validation.run import references, renders
from mcillum.validation.stages import budgets, common
from mcillum.validation.stages.context import Context, Run

import twins
from conftest import SCENES, disagreements
from test_profile_files import dump

# A small profile for tests: the two analytic scenes, few rungs.
TINY = profiles.Profile(name="quick", runs=(
    profiles.SceneRun(scene="furnace_sphere", res=8, ladder=(4, 16, 64, 256), renders=8,
                      max_depth=2),
    profiles.SceneRun(scene="cap_plane", res=4, ladder=(16, 64, 256, 1024), renders=8,
                      max_depth=2, display=profiles.Display(res=32)),
), reference_max_seconds=20.0)


@pytest.fixture
def tiny_profile(monkeypatch):
    monkeypatch.setitem(profiles.PROFILES, "quick", TINY)
    return TINY


def run_cli(tmp_path, *extra):
    out = tmp_path / "out"
    code = cli.main(["validate", "--out", str(out), "--cache", str(tmp_path / "cache"),
                     "--junit", str(tmp_path / "junit.xml"), *extra])
    return code, out


def test_correct_estimators_pass_and_outputs_are_complete(llvm, tiny_profile, tmp_path):
    code, out = run_cli(tmp_path)
    data = json.loads((out / "results.json").read_text())
    assert code == 0, [c for c in data["checks"] if not c["passed"]]
    assert data["passed"] and len(data["scenes"]) == 2
    schema = json.load(open(results.SCHEMA_FILE))
    jsonschema.validate(data, schema)
    assert data["version"] == results.VERSION and data["minor_version"] == results.MINOR_VERSION
    assert list(data["estimator_facts"]) == TINY.estimator_names()
    broken = {**data, "estimator_facts": {"x": {**data["estimator_facts"]["path"],
                                                "colour": "grey"}}}
    with pytest.raises(jsonschema.ValidationError):   # the schema checks the new fields
        jsonschema.validate(broken, schema)
    for scene in data["scenes"]:
        assert [e["name"] for e in scene["estimators"]] == TINY.estimator_names()
        for est in scene["estimators"]:
            assert [r["spp"] for r in est["runs"]] == list(scene["ladder"])
            assert all(r["nonfinite_fraction"] == 0 for r in est["runs"])
        assert scene["reference"]["passes"] >= references.MIN_PASSES
        assert (out / "images" / scene["name"] / "reference.exr").is_file()
        for est in scene["estimators"]:         # the per-pixel test the viewer shows
            p, meta = files.read_exr(out / "images" / scene["name"]
                                     / f"{est['name']}_spp{scene['ladder'][-1]}_mean.exr", "p")
            u = est["unbiasedness"]
            assert float(meta["alpha_pixel"]) == pytest.approx(u["alpha_pixel"])
            assert np.nanmin(p[..., 0]) == pytest.approx(u["min_p"], rel=1e-5, abs=1e-30)
    speed = data["scenes"][1]["speed"]                      # cap_plane has a display
    assert "speed" not in data["scenes"][0] and speed["res"] == 32
    assert set(speed["cost_model"]) == set(speed["efficiency_vs_path"]) == \
        set(TINY.estimator_names())
    assert [b["path_spp"] for b in speed["budgets"]] == sorted(b["path_spp"]
                                                              for b in speed["budgets"])
    for budget in speed["budgets"]:
        for run in budget["estimators"].values():
            assert len(run["wall_seconds"]) == len(run["relmse_per_render"]) == 4
            high = run["relmse_ci"][1]          # (null: a lower bound only, heavy-tailed)
            assert run["relmse_ci"][0] <= run["relmse"] <= (np.inf if high is None else high)
    assert_ranking_follows_the_intervals(speed)
    assert (out / "images" / "cap_plane" / "display" / "path.exr").is_file()
    broken = json.loads(json.dumps(data))
    broken["scenes"][1]["speed"]["cost_model"]["path"]["fixed_s_ci"] = [0.1]
    with pytest.raises(jsonschema.ValidationError):   # the schema checks the speed object
        jsonschema.validate(broken, schema)
    page = (out / "report" / "index.html").read_text()
    assert not re.search(r"\$[a-z_]+", re.sub(r"<(svg|style|script)\b.*?</\1>", "", page, flags=re.S))
    assert "albedo 0.5" in page                             # placeholders show their values
    rows = (out / "results.csv").read_text().splitlines()
    assert rows[0].startswith("scene,estimator,spp")
    assert len(rows) == 1 + len(TINY.runs) * len(TINY.estimator_names()) * 4
    assert "# mcillum validation" in (out / "summary.md").read_text()
    # (a run with a speed stage times the machine's fixed workload, and says it)
    probe = data["machine"]["speed"]
    assert 0 < probe["low"] <= probe["seconds"] <= probe["high"], probe
    said = f"{probe['workload']} in {probe['seconds'] * 1e3:.0f} ms"
    assert said in page and said in (out / "summary.md").read_text()
    suite = ET.parse(tmp_path / "junit.xml").getroot()
    assert int(suite.get("tests")) == len(data["checks"]) and suite.get("failures") == "0"


def assert_ranking_follows_the_intervals(speed):
    """The ranking, recomputed here from the efficiency intervals it reports:
    most efficient first; rank = 1 + the number of estimators whose interval
    lies wholly above; ties are exactly the overlapping intervals. Each
    efficiency is 1/((relMSE − the reference's share)·t) of the largest
    budget's renders (mean relMSE, mean wall time: the definition, computed
    here), inside its interval; path's ratio to itself is 1; the renders
    measured are one of the estimator's tries."""
    ranking = speed["ranking"]
    ci = {p["estimator"]: p["ci"] for p in ranking}
    assert [p["efficiency"] for p in ranking] == sorted((p["efficiency"] for p in ranking),
                                                        reverse=True)
    vs_path = speed["efficiency_vs_path"]
    # a figure off its time budget (a loaded machine) is withheld, not ranked
    withheld = {n for n, r in vs_path.items() if r.get("kind") == "off_budget"}
    assert set(ci) == set(vs_path) - withheld
    if "path" not in withheld:
        assert vs_path["path"]["ratio"] == pytest.approx(1.0)
    top = speed["budgets"][-1]["estimators"]
    share = speed["budgets"][-1]["reference_relmse"]
    for p in ranking:
        run = top[p["estimator"]]
        assert {"spp": run["spp"], "wall_seconds": run["wall_seconds"]} in \
            [{k: t[k] for k in ("spp", "wall_seconds")} for t in run["tries"]]
        net = np.mean(run["relmse_per_render"]) - share
        mine = 1 / (net * np.mean(run["wall_seconds"])) if net > 0 else None
        assert p["efficiency"] == (pytest.approx(mine, rel=1e-6) if mine else None), (p, mine)
        lo, hi = ci[p["estimator"]]
        hi = np.inf if hi is None else hi
        if p["efficiency"] is None:
            continue
        assert lo <= p["efficiency"] <= hi
        above = [o for o in ci if ci[o][0] > hi]
        below = [o for o in ci if ci[o][1] is not None and ci[o][1] < lo]
        assert p["rank"] == 1 + len(above), (p, ci)
        assert set(p["tied_with"]) == set(ci) - set(above) - set(below) - {p["estimator"]}


def convergence_of(tmp_path, estimator, *extra):
    code, out = run_cli(tmp_path, "--scenes", "cap_plane", "--estimators", estimator,
                        "--no-speed", *extra)
    data = json.loads((out / "results.json").read_text())
    assert "speed" not in data["machine"]        # (no speed stage: no probe of the machine)
    return data["scenes"][0]["estimators"][0]["convergence"]


def test_uniform_estimator_slope_is_monte_carlo(llvm, tiny_profile, tmp_path):
    """A fitted slope (4 rungs, 16 … 1024 spp) whose 95 % interval holds −1
    (measured in 9 of 10 seed sets, as a 95 % interval should; the seeds
    here are fixed)."""
    c = convergence_of(tmp_path, "uniform_hemisphere")
    assert np.isfinite([c["slope"], c["low"], c["high"]]).all(), c
    assert c["low"] <= -1 <= c["high"] and c["consistent_with_mc"] and c["outcome"] == "pass", c


def test_convergence_check_fails_an_error_that_stops_shrinking(llvm, tiny_profile, tmp_path):
    """Its twin: the cosine estimator with its pdf 1.5× too high, whose
    relMSE levels off at its bias² (measured slope −0.26 [−0.56, +0.03];
    failed in 10 of 10 seed sets).
    (A 5 % pdf error is not resolved by the slope at this ladder: −0.95
    [−1.11, −0.78]; the unbiasedness check catches that one.)"""
    cls = twins.wrong_pdf_class("cosine_hemisphere", 1.5)
    mi.register_integrator("cosine_pdf_x1.5", lambda props, cls=cls: cls(props))
    c = convergence_of(tmp_path, "cosine_pdf_x1.5")
    assert not c["consistent_with_mc"] and c["outcome"] == "fail", c


def test_a_slope_the_ladder_cannot_decide_is_rendered_on(llvm, monkeypatch, tmp_path):
    """Two renders per rung of one pixel leave uniform sampling's slope on
    cap_plane too uncertain to decide (the precondition, read with --budget
    1: no look allowed, inconclusive, "budget spent"). With the scene's
    budget the fit adds renders to every rung, doubling them at each look,
    from the rung's own seed block, until it decides: a pass, consistent
    with −1, on the renders it says."""
    two = profiles.Profile(name="quick", runs=(
        dataclasses.replace(TINY.runs[1], res=1, renders=2),), reference_max_seconds=20.0)
    monkeypatch.setitem(profiles.PROFILES, "quick", two)
    first = convergence_of(tmp_path / "one", "uniform_hemisphere", "--budget", "1")
    assert first["outcome"] == "inconclusive" and first["looks"] == 0, first
    assert "budget spent: 2 renders per rung" in first["message"], first
    c = convergence_of(tmp_path / "on", "uniform_hemisphere")
    assert c["looks"] >= 1 and c["renders"] == 2 * 2 ** c["looks"] <= c["budget_renders"], c
    assert c["outcome"] == "pass" and c["low"] <= -1 <= c["high"], c
    assert f"after {c['looks']} more look" in c["message"], c
    kept = os.listdir(tmp_path / "on" / "out" / "renders" / "cap_plane")
    assert sum("uniform_hemisphere-look" in f for f in kept) == 4 * c["looks"], kept


def test_too_few_rungs_claim_nothing(llvm):
    """Fewer than 3 rungs with error above the reference's: no slope, no
    claim of Monte Carlo convergence, inconclusive."""
    from mcillum.validation.checks import scene as scene_checks
    from mcillum.validation.stages import scene
    runs = [results.RunStats(spp=s, renders=8, relmse=r, relmse_per_render=[r] * 8, mse=r,
                             mape=0.1, bias=0.0, bias_se=0.01, variance_per_render=r,
                             nonfinite_fraction=0.0, median_seconds=0.01, seconds=[0.01] * 8,
                             samples_per_second=1e6, efficiency=1.0, reference_relmse=0.0)
            for s, r in ((16, 0.1), (64, 0.025))]
    c = scene.convergence_fit(runs)
    scene_checks.decide_convergence(c, resolved=True)
    assert not c.consistent_with_mc and not c.passed and c.outcome == "inconclusive", c


def _rung(spp, per_render):
    r = float(np.mean(per_render))
    return results.RunStats(spp=spp, renders=len(per_render), relmse=r,
                            relmse_per_render=list(per_render), mse=r, mape=0.1, bias=0.0,
                            bias_se=0.01, variance_per_render=r, nonfinite_fraction=0.0,
                            median_seconds=0.01, seconds=[0.01] * len(per_render),
                            samples_per_second=1e6, efficiency=1.0, reference_relmse=0.0)


def test_a_slope_is_as_uncertain_as_its_rungs():
    """Four rungs on a line of slope −0.77 by chance (what residuals alone
    read as −0.77 [−0.81, −0.73], a fail, for cosine sampling on
    probe_spheres): when one rung's 16 renders hold a heavy tail's rare
    render, the interval widens to hold −1; the same line from renders
    that agree stays narrow and fails."""
    from mcillum.validation.checks import scene as scene_checks
    from mcillum.validation.stages import scene
    spp = (16, 64, 256, 1024)
    level = [0.36 * (s / 16) ** -0.77 for s in spp]
    tailed = [_rung(s, [m * 0.6] * 15 + [m * 7.0]) for s, m in zip(spp, level)]
    tame = [_rung(s, [m * 0.98, m * 1.02] * 8) for s, m in zip(spp, level)]
    for runs, outcome in ((tailed, "pass"), (tame, "fail")):
        c = scene.convergence_fit(runs)
        scene_checks.decide_convergence(c, resolved=True)
        assert abs(c.slope + 0.77) < 1e-6 and c.outcome == outcome, c
    assert scene.convergence_fit(tailed).low < -1 + 0.15 < scene.convergence_fit(tame).low


def test_rungs_within_twice_the_references_share_are_left_out():
    """A ladder of slope −1 whose top rungs fall to the reference's share:
    net of the share they read as a line of slope −1 only if the share is
    exact, and the share is one realisation, shared by every render. The
    rungs within 2× of it are left out of the fit (its slope stays −1 on
    the rungs above); the share 10 % off bends a fit of all five rungs."""
    from mcillum.validation.stages import scene
    spp = (4, 16, 64, 256, 1024)
    share = 5e-4
    truth = [0.1 * 4 / s for s in spp]                 # net relMSE, slope −1
    # the share realised 10 % above its estimate: each rung's measured relMSE
    rungs = [dataclasses.replace(_rung(s, [t + 1.1 * share] * 8), reference_relmse=share)
             for s, t in zip(spp, truth)]
    kept = [r.spp for r in rungs if r.relmse > 2 * share]
    assert kept == [4, 16, 64, 256], kept
    slope = scene.convergence_fit(rungs).slope
    everything = scene.statistics.loglog_fit(spp, [r.relmse - share for r in rungs], 0.05)[0]
    # (what all five rungs read is further from −1)
    assert abs(slope + 1) < 0.01 and everything > slope + 0.01, (slope, everything)


def test_a_reference_target_resolves_the_checks_not_a_quadrature():
    """references.target_for: 0.1 of the least noisy stack's RMSE, squared;
    with the checks' ε, no finer than a tenth of ε of the image's rms (a
    stack 10⁴× less noisy than the others no longer sets it); never coarser
    than a tenth of the variance of a stack that carries error bars."""
    from mcillum.validation.run import references
    rng = np.random.default_rng(5)
    image = np.full((8, 8, 3), 0.5)
    noisy = image + rng.normal(0, 0.1, (16, 8, 8, 3))        # variance 1e-2
    exact = image + rng.normal(0, 1e-3, (16, 8, 8, 3))       # variance 1e-6
    old = references.target_for([noisy, exact], 0.1)
    assert old == pytest.approx(1e-8, rel=0.4)
    floor = (0.1 * 0.02) ** 2 * 0.25                          # 1e-6
    assert references.target_for([noisy, exact], 0.1, 0.02) == pytest.approx(floor, rel=0.01)
    assert references.target_for([noisy], 0.1, 0.02) == pytest.approx(1e-4, rel=0.4)
    bars = references.target_for([noisy, exact], 0.1, 0.02, [exact])
    assert bars == pytest.approx(1e-7, rel=0.4) and bars < floor


def test_the_reference_resolves_the_error_bars_where_they_are_calibrated(monkeypatch):
    """Error bars are calibrated at the rung below the ladder's top
    (references.bars_rung), and the reference resolves that rung's: its
    target is BARS_SHARE of the variance there, 4× the top rung's."""
    import types

    from mcillum.validation.run import references, stacks
    from mcillum.validation.stages import common
    assert references.bars_rung([4, 16, 64, 256]) == 64
    assert references.bars_rung([256, 4, 16]) == 16 and references.bars_rung([32]) == 32
    rng = np.random.default_rng(3)
    image = np.full((8, 8, 3), 0.5)
    ladder = (4, 16, 64, 256)

    def rung(spp, name, sd, bars):
        x = image + rng.normal(0, sd, (16, 8, 8, 3))
        return stacks.Stack(name, spp, x, aovs={"posterior_std": x} if bars else {})
    found = {spp: {"path": rung(spp, "path", 0.2 / np.sqrt(spp), False),
                   "bayes": rung(spp, "bayes", 0.01 / np.sqrt(spp), True)} for spp in ladder}
    asked = []
    monkeypatch.setattr(references, "ensure", lambda ctx, target, spp: asked.append(target))
    run = types.SimpleNamespace(sequential=types.SimpleNamespace(scene_epsilon=0.02),
                                profile=types.SimpleNamespace(reference_fraction=0.1))
    common.build_reference(types.SimpleNamespace(stacks=found, is_case=False, run=run))
    at = {spp: references.BARS_SHARE * 1e-4 / spp for spp in ladder}
    assert asked[0] == pytest.approx(at[64], rel=0.3), (asked, at)


def test_biased_estimator_fails_with_exit_1(llvm, tiny_profile, tmp_path, capsys):
    biased = twins.wrong_pdf_class("cosine_hemisphere")
    mi.register_integrator("biased_cosine", lambda props, cls=biased: cls(props))
    code, out = run_cli(tmp_path, "--scenes", "cap_plane",
                        "--estimators", "cosine_hemisphere", "biased_cosine")
    data = json.loads((out / "results.json").read_text())
    failed = {c["id"] for c in data["checks"] if not c["passed"]}
    assert code == 1 and failed == {"cap_plane/biased_cosine/unbiased"}
    assert "biased_cosine/unbiased" in capsys.readouterr().out
    suite = ET.parse(tmp_path / "junit.xml").getroot()
    assert suite.get("failures") == "1"


def test_groups_run_one_group_only(llvm, tmp_path, monkeypatch):
    """--groups picks the scene comparisons or the failures group."""
    case = profiles.FailureCase(group="geometry", scene="edge_thin", res=4, spp=4, seeds=4)
    monkeypatch.setitem(profiles.PROFILES, "quick", profiles.Profile(
        name="quick", runs=TINY.runs[:1], failures=(case,), reference_max_seconds=10.0,
        estimators=("cosine_hemisphere", "path")))
    for group, scenes_, cases in (("failures", 0, 1), ("scenes", 1, 0)):
        code, out = run_cli(tmp_path / group, "--groups", group)
        data = json.loads((out / "results.json").read_text())
        assert code == 0 and (len(data["scenes"]), len(data["failures"])) == (scenes_, cases)


def completed(directory):
    """Finished render steps (not the temporary files of one being written)."""
    return sorted(p for p in directory.rglob("*.npz") if not p.name.startswith(".partial-"))


@pytest.mark.parametrize("args", [
    ["--profile", "medium"],
    ["--scenes", "no_such_scene"],
    ["--estimators", "no_such_integrator"],
    ["--out", "{tmp}/a_file/out"],
])
def test_usage_errors_exit_2(llvm, tmp_path, args):
    (tmp_path / "a_file").write_text("not a directory")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    with pytest.raises(SystemExit) as info:
        cli.main(["validate", "--cache", str(tmp_path / "cache"), *args])
    assert info.value.code == 2


def test_rerun_resumes_without_rendering(llvm, tiny_profile, tmp_path, monkeypatch):
    """A re-run into a finished directory renders nothing and keeps the first
    run's wall time (its own is ``rerun_seconds``)."""
    run_cli(tmp_path, "--scenes", "furnace_sphere")
    first = json.loads((tmp_path / "out" / "results.json").read_text())
    npz = completed(tmp_path / "out" / "renders")
    stamps = [p.stat().st_mtime_ns for p in npz]
    calls = []
    original = renders.render
    monkeypatch.setattr(renders, "render", lambda *a, **k: calls.append(a[2]) or original(*a, **k))
    code, out = run_cli(tmp_path, "--scenes", "furnace_sphere")
    assert code == 0 and [p.stat().st_mtime_ns for p in npz] == stamps
    again = json.loads((out / "results.json").read_text())
    ref = again["scenes"][0]["reference"]
    assert ref["rendered_passes"] == 0 and ref["cached_passes"] == ref["passes"], ref
    assert calls == [], "a re-run into a finished directory rendered again"
    assert "rerun_seconds" not in first and again["wall_seconds"] == first["wall_seconds"]
    assert 0 < again["rerun_seconds"] < first["wall_seconds"]


def test_a_rerun_keeps_the_probe_of_the_run_it_reports(tmp_path):
    """A re-run that rendered nothing reports the first run's wall time and
    timings, so it keeps that run's machine probe beside them (its own
    machine may be another); a run that rendered reports its own."""
    probe = {"workload": "w", "seconds": 0.2, "low": 0.19, "high": 0.25}
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"wall_seconds": 1789.0, "machine": {"speed": probe}}))
    kept = SimpleNamespace(rendered=False, kept=True)
    assert pipeline._first_run(str(path), kept) == (1789.0, probe)
    path.write_text(json.dumps({"wall_seconds": 12.0, "machine": {}}))   # (no speed stage)
    assert pipeline._first_run(str(path), kept) == (12.0, None)
    assert pipeline._first_run(str(path), SimpleNamespace(rendered=True, kept=True)) is None


# ------------------------------ Reference cache --------------------------------

def furnace(tmp_path, res=4, spp_per_pass=16) -> Context:
    """The loaded furnace scene as a validation context (max_depth 2), with
    the reference cache in ``tmp_path``."""
    profile = profiles.Profile(name="test", runs=(), reference_spp_per_pass=spp_per_pass,
                               reference_max_spp=1 << 24)
    plan = profiles.SceneRun(scene="furnace_sphere", res=res, ladder=(1,), renders=2,
                             max_depth=2)
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path), str(tmp_path / "out")), plan,
                  "furnace_sphere", ["path"])
    common.load(ctx)
    return ctx


def test_small_images_get_larger_reference_passes():
    """A pass holds at least PASS_SAMPLES samples, its spp a doubling of the
    profile's, unless MIN_PASSES of them would pass the spp cap."""
    assert references.pass_spp(64, 128 * 128, 1 << 18) == 64
    assert references.pass_spp(64, 24 * 24, 1 << 18) == 128
    assert references.pass_spp(64, 8 * 8, 1 << 18) == 1024
    assert references.pass_spp(64, 8 * 8, 1 << 14) == 512          # 32 × 512 = the cap
    assert references.pass_spp(64, 8 * 8, 1 << 10) == 64           # never below the profile's


def test_a_reference_of_many_passes_gets_larger_ones(llvm, tmp_path):
    """A reference expected to need N spp renders passes of the largest
    power-of-two multiple of the profile's at most N / PASSES_WANTED, within
    the cap; one in the cache goes on in its own pass size."""
    wanted = references.PASSES_WANTED
    assert references.pass_spp(16, 128 * 128, 1 << 20, expected=430_000) == 1024
    assert 430_000 / 1024 >= wanted / 2
    assert references.pass_spp(16, 128 * 128, 1 << 20, expected=wanted * 16) == 16
    assert references.pass_spp(16, 128 * 128, 1 << 14, expected=1e12) == 512  # 32 × 512 = the cap
    # (read only on average, as the speed stage's: fewer, larger passes)
    assert references.pass_spp(16, 128 * 128, 1 << 20, expected=wanted * 16,
                               wanted=references.AVERAGE_PASSES_WANTED) == 64
    rng = np.random.default_rng(2)
    renders_ = 0.5 + rng.normal(0, 0.1, (64, 8, 8, 3))        # variance 1e-2 at 16 spp
    assert references.expected_spp(renders_, 16, 1e-6) == pytest.approx(1.6e5, rel=0.1)
    ctx = furnace(tmp_path)
    a = references.ensure(ctx, 1.0)
    b = references.ensure(ctx, float(a.variance_of_mean.mean()) / 2, expected=1e9)
    assert b.spp_per_pass == a.spp_per_pass and b.cached_passes == a.passes < b.passes
    fresh = furnace(tmp_path / "other")
    c = references.ensure(fresh, 1.0, expected=16 * wanted * a.spp_per_pass)
    assert c.spp_per_pass == 16 * a.spp_per_pass               # at least `wanted` passes


def test_reference_is_extended_not_rerendered(llvm, tmp_path):
    ctx = furnace(tmp_path)
    a = references.ensure(ctx, 1.0)
    assert a.passes == references.MIN_PASSES and a.meta["rendered_passes"] == a.passes
    target = float(a.variance_of_mean.mean()) / 4          # needs ~4x the passes
    b = references.ensure(ctx, target)
    assert b.cached_passes == a.passes and b.passes > a.passes
    assert b.meta["rendered_passes"] == b.passes - a.passes
    assert float(b.variance_of_mean.mean()) <= target


def test_reference_key_changes_with_everything_that_changes_the_image(llvm, tmp_path):
    path = scenes.path("furnace_sphere")
    defines = renders.resolve_defines(path, res=4)
    base = references.cache_key(path, defines, {"max_depth": 2}, "llvm_ad_rgb")
    assert base != references.cache_key(path, {**defines, "res": "5"}, {"max_depth": 2},
                                        "llvm_ad_rgb")
    assert base != references.cache_key(path, defines, {"max_depth": 3}, "llvm_ad_rgb")
    assert base != references.cache_key(path, defines, {"max_depth": 2}, "scalar_rgb")
    # the bytes of referenced files count: an envmap edited in place changes the key
    env = tmp_path / "env.exr"
    files.write_exr(env, procedural.constant(1.0))
    sky = scenes.path("sky_sphere")
    k1 = references.cache_key(sky, {"envmap": str(env)}, {}, "llvm_ad_rgb")
    files.write_exr(env, procedural.constant(2.0))
    assert k1 != references.cache_key(sky, {"envmap": str(env)}, {}, "llvm_ad_rgb")


def test_reference_key_changes_with_the_code_that_fills_it(llvm, monkeypatch):
    """An edit to mcillum's Phong BSDF (which scenes may use) or to the
    reference code gives a new key: a stale reference is never served."""
    import inspect

    from mcillum.integrators.bsdfs import phong
    path = scenes.path("furnace_sphere")
    defines = renders.resolve_defines(path, res=4)

    def key():
        files.code_hash.cache_clear()
        return references.cache_key(path, defines, {"max_depth": 2}, "llvm_ad_rgb")

    base = key()
    source = inspect.getsource
    for module in (phong, references):
        monkeypatch.setattr(inspect, "getsource", lambda obj, m=module: source(obj) + (
            "\n# edited" if obj is m else ""))
        assert key() != base, module.__name__
        monkeypatch.setattr(inspect, "getsource", source)
    assert key() == base


def test_capped_reference_is_not_chased_again_by_a_rerun(llvm, tmp_path):
    """A reference that hit its time cap is used as it is by a re-run with the
    same caps and target (before, every re-run rendered until the cap again:
    30 s per quick scene); a stricter target or a higher cap extends it."""
    import dataclasses
    ctx = furnace(tmp_path)
    ctx.run.profile = dataclasses.replace(ctx.run.profile, reference_max_seconds=0.05)
    first = references.ensure(ctx, 1e-12)                    # out of reach
    assert first.capped == "time cap 0.05 s"
    again = references.ensure(ctx, 1e-12)
    assert again.meta["rendered_passes"] == 0 and again.capped == first.capped
    assert again.passes == first.passes
    stricter = references.ensure(ctx, 1e-13)
    assert stricter.meta["rendered_passes"] > 0 and stricter.passes > first.passes


def test_kept_renders_do_not_hang_on_the_reference_code(llvm, monkeypatch):
    """A change in how references are made (references.py) changes the
    reference cache's key but not the key of the estimators' kept renders
    (render_key); a change in the renderer changes both."""
    import types
    args = (str(SCENES / "furnace_sphere.xml"), {"res": 8}, {"max_depth": 2}, "llvm_ad_rgb")
    before = references.cache_key(*args), references.render_key(*args)
    edited = types.ModuleType("edited_references")
    edited.__file__ = __file__                       # another source, as an edit would be
    modules = references._filled_by()
    monkeypatch.setattr(references, "_filled_by", lambda: (edited, *modules[1:]))
    after = references.cache_key(*args), references.render_key(*args)
    assert after[0] != before[0] and after[1] == before[1]
    rendered_by = references._renders_by()
    monkeypatch.setattr(references, "_renders_by", lambda: (edited, *rendered_by[1:]))
    assert references.render_key(*args) != before[1]


def test_corrupt_cache_entry_is_rendered_anew(llvm, tmp_path):
    ctx = furnace(tmp_path)
    a = references.ensure(ctx, 1.0)
    file = references.cache_path(str(tmp_path), a.key)
    data = bytearray(open(file, "rb").read())
    data[len(data) // 2] ^= 0xFF                            # flip a byte in the pixels
    open(file, "wb").write(bytes(data))
    assert references.load(str(tmp_path), a.key) is None and not os.path.exists(file)
    open(file, "wb").write(b"partial")                      # a truncated file
    b = references.ensure(ctx, 1.0)
    assert b.cached_passes == 0 and b.meta["rendered_passes"] == b.passes
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-6)  # same seeds, same image


def test_cache_survives_a_killed_run(llvm, tmp_path):
    """Kill `mcillum validate` mid-run: no partial files are left where complete
    ones are expected, and a re-run completes, reusing what was finished.
    (Two estimators beside path: what is cached does not depend on how many.)"""
    out, cache = tmp_path / "out", tmp_path / "cache"
    small = tmp_path / "tiny.toml"
    small.write_text(dump(TINY))          # (a subprocess does not see the monkeypatch)
    cmd = [sys.executable, "-m", "mcillum.validation.cli", "validate", "--out", str(out),
           "--cache", str(cache), "--profile", str(small),
           "--estimators", "cosine_hemisphere", "mis"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while time.time() < deadline and not completed(out / "renders"):
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = completed(out / "renders")
    assert finished, "the run did not finish any step before the deadline"
    stamps = {p: p.stat().st_mtime_ns for p in finished}
    for p in finished:                                     # complete files only
        with np.load(p) as z:
            assert "key" in z.files
    assert not (out / "results.json").exists()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items())
    assert not list(tmp_path.rglob(".partial-*")), "a killed run's temp files were left"
    data = json.loads((out / "results.json").read_text())
    assert {s["name"] for s in data["scenes"]} == {"cap_plane", "furnace_sphere"}




# ------------------------- The speed stage, twice ---------------------------

def _speed_stage(tmp_path, out: str, estimators=None, scene="cornell_box", renders=4):
    """The speed-and-images stage alone on ``scene`` at 128² into ``out``
    (the reference cached under tmp_path), ``renders`` timed renders per
    estimator and budget."""
    from mcillum.validation import pipeline
    profile = profiles.Profile(name="quick", runs=(), reference_max_seconds=30.0)
    plan = profiles.SceneRun(scene=scene, res=8, ladder=(4,), renders=2,
                             display=profiles.Display(res=128, renders=renders))
    ctx = Context(Run(profile, "llvm_ad_rgb", str(tmp_path / "cache"), str(tmp_path / out)),
                  plan, scene, list(estimators or profile.estimator_names()))
    common.load(ctx)
    common.choose_estimators(ctx)
    return pipeline.run_stages(pipeline.SPEED, ctx).speed


@pytest.mark.slow
def test_speed_stage_reproduces_quiet_and_loaded(llvm, tmp_path):
    """The speed-and-images stage three times on the Cornell box at 128²
    (fresh output directories, the reference cached by the first), the
    third while another process keeps one core busy: every unbiased
    estimator's efficiency against `path` agrees within ±15 % wherever both
    runs state an interval narrower than that, and no pair one run tells
    apart is reversed in another (conftest.disagreements; its own test
    shows it reports both kinds). The loaded run says it was loaded, the
    quiet ones do not; at least 95 % of the renders met their budget or
    (a learner's) stand where no whole spp could (budgets.unreachable), and
    each that did not says why."""
    runs = [_speed_stage(tmp_path, f"out{i}") for i in range(2)]
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        runs.append(_speed_stage(tmp_path, "out2"))
    finally:
        busy.kill()
        busy.wait()
    first, second, loaded = runs
    assert first.budgets[-1].seconds > 0.1           # not a launch-overhead measurement
    assert not first.loaded and not second.loaded, (first.others_cores, second.others_cores)
    assert loaded.loaded and loaded.others_cores > 0.5, loaded.others_cores
    assert any("the machine was loaded" in n for n in loaded.notes)
    at_budgets = [(n, r, b.seconds) for sp in runs for b in sp.budgets
                  for n, r in b.estimators.items()]
    assert all(r.on_budget or r.note for _, r, _ in at_budgets)
    # (a budget between two whole spp a learner's times jump across cannot
    # be met by any spp: guided_path adds a training pass at 8 and 24 spp)
    met = [r.on_budget or (registry.facts(n).learns
                           and budgets.unreachable(r.tries, t) is not None)
           for n, r, t in at_budgets]
    assert sum(met) >= 0.95 * len(met), [(n, t, r.note) for (n, r, t), m
                                         in zip(at_budgets, met) if not m]
    for a, b in ((first, second), (first, loaded), (second, loaded)):
        assert disagreements(a.efficiency_vs_path, b.efficiency_vs_path,
                             a.ranking, b.ranking) == []


def _widened(value: float, ci, renders: int, level: float = 0.999):
    """The 95 % interval ``ci`` about ``value`` (log-symmetric, Student-t
    with ``renders`` − 1 degrees of freedom, stats/costs.ratio) taken to
    ``level``."""
    scale = stats.t.ppf((1 + level) / 2, renders - 1) / stats.t.ppf(0.975, renders - 1)
    return results.Interval(value * (ci.low / value) ** scale, value * (ci.high / value) ** scale)


@pytest.mark.slow
def test_a_users_integrator_whose_error_renders_cannot_bound_is_read_as_a_bound(llvm, tmp_path):
    """A user's plugin file: `path` with every sample weighted by a Pareto W
    of mean 1 and no finite variance (user_code.SPIKY_PATH). It is unbiased,
    but its error rests on rare samples: the speed stage reads it
    heavy-tailed (stats/tails.py: error_tail), its efficiency an upper bound
    ([0, its upper end]) and its relMSE at the largest budget a lower bound
    ([low, ∞)), and says so in a note (where K renders do not even resolve
    its net relMSE, no upper end either); `path` beside it keeps its
    two-sided figures."""
    from mcillum import plugins
    from user_code import SPIKY_PATH
    plugin = tmp_path / "code" / "spiky_path.py"
    plugin.parent.mkdir()
    plugin.write_text(SPIKY_PATH)
    plugins.load(str(plugin), "llvm_ad_rgb")
    speed = _speed_stage(tmp_path, "out", ["spiky_path", "path"])
    spiky, path = speed.efficiency_vs_path["spiky_path"], speed.efficiency_vs_path["path"]
    assert spiky.kind == "heavy_tailed" and spiky.ci.low == 0.0, spiky
    assert spiky.ratio <= spiky.ci.high, spiky
    top = speed.budgets[-1].estimators
    assert top["spiky_path"].relmse_ci.high == np.inf
    assert path.kind == "unbiased" and 0 < path.ci.low < 1 < path.ci.high, path
    assert np.isfinite(top["path"].relmse_ci.high)
    assert any(n.startswith("spiky_path at") and "efficiency is an upper bound" in n
               for n in speed.notes), speed.notes


@pytest.mark.slow
def test_an_efficiency_whose_truth_is_known_is_read_right(llvm, tmp_path):
    """`path` rendering every image twice and keeping one, from a user's
    plugin file: at spp s its time is twice path's, fixed cost included, so
    at equal time its efficiency is half of path's at its own spp: 0.5 ·
    (a/s_path + b)/(a/s_twice + b) with path's cost model (a, b). The speed
    stage reads it within 15 % (its own timing noise: one slow render in 8
    moves it by 5 %,
    docs/measurements.md#2026-12-03-speed-stage-reading-efficiency); its
    interval, taken to 99.9 % (:func:`_widened`), covers it: the 95 % one
    covered 8 of 10 runs, partly because the truth extrapolates the pilot's
    line (1-3 % off at 30 spp,
    docs/measurements.md#2026-12-05-known-efficiency-ratio-readings), and a
    test that fails one run in ten is no test for CI. The 95 % interval still
    tells the reading apart from those a mistake in the timing would give: the
    thrown render not counted (2×) or counted twice (½×)."""
    from mcillum import plugins
    from user_code import TWICE_PATH
    plugin = tmp_path / "code" / "twice_path.py"
    plugin.parent.mkdir()
    plugin.write_text(TWICE_PATH)
    plugins.load(str(plugin), "llvm_ad_rgb")
    speed = _speed_stage(tmp_path, "out", ["twice_path", "path"], renders=8)
    path, top = speed.cost_model["path"], speed.budgets[-1].estimators
    a, b = path.fixed_s, path.per_spp_s
    truth = 0.5 * (a / top["path"].spp + b) / (a / top["twice_path"].spp + b)
    got = speed.efficiency_vs_path["twice_path"]
    assert abs(got.ratio / truth - 1) <= 0.15, (got, truth)
    wide = _widened(got.ratio, got.ci, renders=8)
    assert wide.low <= truth <= wide.high, (got, wide, truth)
    assert truth / 1.5 < got.ci.low and got.ci.high < 1.5 * truth, (got, truth)
