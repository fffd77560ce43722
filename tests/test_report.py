"""The HTML report: chart builders on synthetic results (no rendering), a
self-contained page, and (marked `browser`) the page as Chromium shows it.
The browser's one "external" request goes to a closed loopback port: no test
sends a packet off this machine."""

import base64
import dataclasses
import html
import io
import json
import math
import os
import re
import shutil

import matplotlib
import numpy as np
import pytest
from PIL import Image

from mcillum import files, images
from mcillum.validation import report, results
from mcillum.validation.report import charts, parts
from mcillum.validation.report import scenes as scene_section
from mcillum.validation.report.parts import worst_window
from mcillum.validation.results import (Budget, BudgetRun, Check, Convergence, EstimatorInfo,
                                        EstimatorResult, Learning, LearningPoint, Ratio,
                                        ReferenceSummary,
                                        Results, RunStats, SceneResult, Speed, Unbiasedness)
from mcillum.validation.stats import costs

ESTIMATORS = ["uniform_hemisphere", "cosine_hemisphere", "path"]
COLOURS = {"uniform_hemisphere": "#d62728", "cosine_hemisphere": "#1f77b4", "path": "#444444"}


def synthetic_speed(rng, res=32) -> Speed:
    """A speed stage of the three estimators at ``res``²: time ∝ spp, and
    relMSE ∝ 1/spp with a constant that grows from path to uniform."""
    models = {n: costs.fit_cost({s: list(2e-3 + 1e-3 * s * rng.uniform(0.97, 1.03, 5))
                                 for s in (8, 32)}) for n in ESTIMATORS}
    budgets = []
    for path_spp in (4, 8, 16):
        seconds = costs.seconds_at(models["path"], path_spp)
        runs = {}
        for i, n in enumerate(ESTIMATORS):
            spp = costs.spp_for(models[n], seconds)
            per = list((3 - i) * 0.1 / spp * rng.uniform(0.9, 1.1, 4))
            mean, ci = costs.relmse_interval(per)
            runs[n] = BudgetRun(spp=spp, wall_seconds=list(seconds * rng.uniform(0.98, 1.02, 4)),
                                relmse=mean, relmse_ci=ci, relmse_per_render=per,
                                on_budget=True)
        budgets.append(Budget(seconds=seconds, path_spp=path_spp, estimators=runs,
                              reference_relmse=1e-5))
    top = budgets[-1].estimators
    ratios = {}
    for n, r in top.items():
        ratio, ci = costs.ratio_interval(r.relmse_per_render, r.wall_seconds,
                                         top["path"].relmse_per_render, top["path"].wall_seconds)
        ratios[n] = Ratio(ratio=ratio, ci=ci)
    eff = {n: costs.efficiency(r.relmse_per_render, r.wall_seconds) for n, r in top.items()}
    ranking = costs.ranking({n: (e.value, e.ci) for n, e in eff.items()})
    return Speed(res=res, renders=4, cost_model=models, budgets=budgets,
                 efficiency_vs_path=ratios, ranking=ranking, reference=reference_summary(),
                 mean_flip={n: 0.1 * (3 - i) for i, n in enumerate(ESTIMATORS)},
                 notes=["uniform_hemisphere: a note"])


def reference_summary() -> ReferenceSummary:
    return ReferenceSummary(integrator="path", spp=4096, passes=64, spp_per_pass=64,
                            seconds=1.0, cached_passes=0, rendered_passes=64,
                            target_variance=1e-6, achieved_variance=1e-6, capped=None,
                            key="k")


def synthetic_learning(name="cosine_hemisphere") -> Learning:
    """A learning curve that falls to a third and flattens."""
    points = [LearningPoint(passes=j, training_spp=16 * (2 ** j - 1), relmse=r,
                            relmse_low=0.8 * r, relmse_high=1.2 * r, seconds=0.01 * 2 ** j)
              for j, r in enumerate((3e-2, 1.8e-2, 1.2e-2, 1.0e-2, 1.0e-2))]
    return Learning(name=name, spp=64, renders=8, points=points)


def synthetic_results(scenes=("alpha", "beta"), ladder=(4, 16, 64)) -> Results:
    """A run of three estimators on two scenes; uniform_hemisphere fails
    ``unbiased`` everywhere."""
    rng = np.random.default_rng(0)
    scene_results, checks = [], []
    for s in scenes:
        ests = []
        for i, name in enumerate(ESTIMATORS):
            runs = [RunStats(spp=spp, renders=8, relmse=0.5 / (i + 1) / spp,
                             relmse_per_render=list(0.5 / (i + 1) / spp
                                                    * rng.lognormal(0, 1, 8)),
                             mse=0.1, mape=0.1, bias=1e-3, bias_se=2e-3,
                             variance_per_render=0.01, nonfinite_fraction=0.0,
                             median_seconds=1e-4 * spp, seconds=[1e-4 * spp] * 8,
                             samples_per_second=1e6,
                             efficiency=(i + 1) * spp / (0.5 * 1e-4 * spp),
                             reference_relmse=0.0, firefly_fraction=0.0) for spp in ladder]
            passed = name != "uniform_hemisphere"
            # one inconclusive check: cosine in the second scene
            outcome = ("fail" if not passed else
                       "inconclusive" if (s, name) == (scenes[-1], "cosine_hemisphere")
                       else "pass")
            ests.append(EstimatorResult(
                name=name, params={"max_depth": 2}, compile_seconds=0.1, runs=runs,
                unbiasedness=Unbiasedness(spp=ladder[-1], passed=passed, pass_fraction=0.99,
                                          min_p=0.01, alpha=0.01, alpha_pixel=1e-5,
                                          pooled_p=[0.5], summary="m", outcome=outcome,
                                          reason=f"why {outcome}"),
                convergence=Convergence(slope=-1.0, low=-1.1, high=-0.9, exact=False,
                                        consistent_with_mc=True, passed=True)))
            checks.append(Check(id=f"{s}/{name}/unbiased", passed=passed,
                                message=f"m {outcome}", outcome=outcome))
        scene_results.append(SceneResult(
            name=s, path=f"scenes/{s}.xml", summary=f"{s}: a synthetic scene", res=8,
            max_depth=2, ladder=list(ladder), renders=8, reference=reference_summary(),
            estimators=ests, speed=synthetic_speed(rng),
            learning=[synthetic_learning()] if s == scenes[0] else None))
    facts = {n: EstimatorInfo(display_name=n.replace("_", " "), colour=COLOURS[n],
                              unreachable=[], max_direction_pdf=None) for n in ESTIMATORS}
    return Results(created="2026-11-22T12:00:00", profile="quick", variant="llvm_ad_rgb",
                   mitsuba_version="3.9.1", drjit_version="1.5.0",
                   machine={"platform": "Linux", "cpus": 2, "python": "3.11"}, alpha=0.01,
                   reference_fraction=0.1, wall_seconds=12.0, scenes=scene_results,
                   checks=checks, failures=[], estimator_facts=facts)


def test_colours_come_from_the_runs_facts():
    res = synthetic_results()
    assert charts.palette(res) == COLOURS
    res.estimator_facts.pop("cosine_hemisphere")            # an integrator without facts
    colours = charts.palette(res)
    assert colours["path"] == COLOURS["path"]
    assert len(set(colours.values())) == 3


@pytest.mark.parametrize("builder", [charts.error_vs_time, charts.error_vs_spp,
                                     charts.error_spread])
def test_scene_charts_label_axes_and_every_estimator(builder):
    svg = builder(synthetic_results().scenes[0], COLOURS)
    assert svg.startswith("<svg") and "</svg>" in svg
    for name in ESTIMATORS:
        assert name in svg
    for colour in COLOURS.values():
        assert colour.lower() in svg.lower()


def test_an_estimator_too_slow_for_a_smaller_budget_is_charted_where_it_rendered():
    """speed: an estimator that cannot fit MIN_SPP samples in a smaller
    budget is not rendered there (budgets.fits); its chart line starts at
    the first budget it rendered."""
    scene = synthetic_results().scenes[0]
    sp = scene.speed
    budgets_ = [dataclasses.replace(b, estimators={n: r for n, r in b.estimators.items()
                                                   if j or n != "uniform_hemisphere"})
                for j, b in enumerate(sp.budgets)]
    slow = dataclasses.replace(scene, speed=dataclasses.replace(sp, budgets=budgets_))
    svg = charts.error_vs_time(slow, COLOURS)
    assert "uniform_hemisphere" in svg and COLOURS["uniform_hemisphere"] in svg


def test_learning_is_shown_as_a_table_and_a_curve():
    """The learning stage's section: each point's training spp, relMSE with
    its interval and its ratio to no training; the curve's ticks name the
    training spp (0 included) in the estimator's colour."""
    scene = synthetic_results().scenes[0]
    page = scene_section._learning_section(scene, COLOURS)
    assert "<h3>Learning" in page and page.count("<tr>") == 1 + 5
    assert "0.0300 [0.024" not in page and "0.03 [0.024, 0.036]" in page and "0.33" in page
    svg = charts.learning_curve(scene.learning[0], COLOURS)
    assert COLOURS["cosine_hemisphere"] in svg
    for tick in ("0", "16", "48", "112", "240"):
        assert f">{tick}<" in svg, tick
    line = results.learning_summary(scene.learning[0])
    assert "0.03 after 0" in line and "0.01 after 240" in line and "0.33×" in line


def test_axis_labels_carry_units():
    scene = synthetic_results().scenes[0]
    assert "wall time per render at 32² [ms]" in charts.error_vs_time(scene, COLOURS)
    assert "samples per pixel" in charts.error_vs_spp(scene, COLOURS)
    assert "slope -1.00" in charts.error_vs_spp(scene, COLOURS).replace("+", "")
    assert "ideal slope" in charts.error_vs_spp(scene, COLOURS)


def test_efficiency_summary_is_relative_to_path():
    svg = charts.efficiency_summary(synthetic_results(), COLOURS)
    assert "relative to Mitsuba" in svg and "path = 1" in svg
    assert "alpha" in svg and "beta" in svg


def test_results_round_trip_through_json():
    """results.json holds everything the report reads: writing and reading
    it back gives the same records."""
    res = synthetic_results()
    assert results.from_json(Results, json.loads(json.dumps(results.to_json(res)))) == res


def test_inconclusive_checks_are_skipped_in_junit_and_fail_only_when_strict(tmp_path):
    """Three outcomes: the run passes while no check fails; JUnit shows an
    inconclusive check as skipped with its reason, or with --strict as a
    failure; a file from before minor version 3 (no outcome) reads passed."""
    import xml.etree.ElementTree as ET

    res = synthetic_results()
    assert res.counts() == {"pass": 3, "fail": 2, "inconclusive": 1}
    assert not res.passed and [c.outcome for c in res.inconclusive] == ["inconclusive"]
    res.checks = [c for c in res.checks if c.outcome != "fail"]
    assert res.passed                                   # inconclusive is not a failure
    for strict, failures, skipped in ((False, "0", "1"), (True, "1", "0")):
        path = tmp_path / f"junit-{strict}.xml"
        results.write_junit(str(path), res, strict=strict)
        suite = ET.parse(path).getroot()
        assert (suite.get("failures"), suite.get("skipped")) == (failures, skipped)
        case = [c for c in suite if "cosine" in c.get("name")][-1]
        tag = "failure" if strict else "skipped"
        assert case.find(tag).get("message").endswith("m inconclusive")
    old = {"id": "a/b/unbiased", "passed": False, "message": "m"}
    assert results.from_json(Check, old).outcome == "fail"
    with pytest.raises(ValueError, match="outcome"):
        Check(id="a/b/c", passed=True, message="m", outcome="maybe")


def test_non_finite_numbers_are_written_as_null_and_read_back_as_nan(tmp_path):
    """An exact estimator's slope is NaN, an unbounded interval ±inf, a broken
    render's mean NaN: results.json (plain JSON) holds them as null."""
    res = synthetic_results()
    est = res.scenes[0].estimators[0]
    est.convergence = Convergence(slope=math.nan, low=-math.inf, high=math.inf, exact=True,
                                  consistent_with_mc=True, passed=True)
    est.runs[0].efficiency = math.inf
    results.write_json(str(tmp_path / "results.json"), res)
    constants = []                          # NaN, Infinity: not JSON
    json.loads((tmp_path / "results.json").read_text(), parse_constant=constants.append)
    assert constants == []
    back = results.load(str(tmp_path)).scenes[0].estimators[0]
    assert all(math.isnan(x) for x in (back.convergence.slope, back.convergence.low,
                                       back.convergence.high, back.runs[0].efficiency))


def test_results_of_minor_version_0_still_load(tmp_path):
    """A file from before minor version 1: no minor_version, estimator_facts
    or firefly_fraction, and refused failure rows with "numbers": {}."""
    data = results.to_json(synthetic_results())
    for key in ("minor_version", "estimator_facts"):
        data.pop(key)
    for scene in data["scenes"]:
        for est in scene["estimators"]:
            for run in est["runs"]:
                run.pop("firefly_fraction")
    data["failures"] = [{"id": "failures.unreachable.point_light", "group": "unreachable",
                         "label": "point_light", "scene": "point_light", "defines": {},
                         "res": 8, "spp": 16, "seeds": 16, "max_depth": 2, "summary": "",
                         "estimators": [{"name": "cosine_hemisphere", "refused": True,
                                         "message": "m", "verdict": "refused",
                                         "numbers": {}}]}]
    (tmp_path / "results.json").write_text(json.dumps(data))
    old = results.load(str(tmp_path))
    assert old.minor_version == 0 and old.estimator_facts == {}
    assert old.scenes[0].estimators[0].top.firefly_fraction is None
    assert old.failures[0].estimators[0].numbers is None


def fake_run_dir(tmp_path, res=None):
    """A results dir with a synthetic results.json and EXR images."""
    res = res or synthetic_results()
    rng = np.random.default_rng(1)
    for s in res.scenes:
        d = tmp_path / "images" / s.name
        d.mkdir(parents=True)
        ref = rng.uniform(0.2, 1.0, (8, 8, 3)).astype(np.float32)
        files.write_exr(d / "reference.exr", ref)
        for e in s.estimators:
            noisy = (ref * rng.uniform(0.5, 1.5, ref.shape)).astype(np.float32)
            files.write_exr(d / f"{e.name}_spp{e.top.spp}.exr", noisy)
            # its per-pixel test: one rejected pixel, (x 7, y 0), for uniform
            p = np.full((8, 8, 1), 0.5, np.float32)
            p[0, 7] = 1e-9 if e.name == "uniform_hemisphere" else 0.5
            files.write_exr(d / f"{e.name}_spp{e.top.spp}_mean.exr",
                            (ref * rng.uniform(0.9, 1.1, ref.shape)).astype(np.float32),
                            {"alpha_pixel": 1e-5}, {"p": p})
        (d / "display").mkdir()
        big = rng.uniform(0.2, 1.0, (32, 32, 3)).astype(np.float32)
        files.write_exr(d / "display" / "reference.exr", big)
        for e in s.estimators:
            noisy = (big * rng.uniform(0.5, 1.5, big.shape)).astype(np.float32)
            files.write_exr(d / "display" / f"{e.name}.exr", noisy,
                            {"spp": 3, "render_seconds": 0.001},
                            {"flip": rng.uniform(0, 1, (32, 32, 1)).astype(np.float32)})
    results.write_json(str(tmp_path / "results.json"), res)
    return tmp_path


def data_images(html_text):
    """Every <img> of the page: (format of its data URI, width and height shown,
    the image as Pillow decodes it)."""
    from PIL import Image

    found = re.findall(r'<img src="data:image/(\w+);base64,([^"]+)" alt="[^"]*" '
                       r'width="(\d+)" height="(\d+)"', html_text)
    return [(fmt, int(w), int(h), Image.open(io.BytesIO(base64.b64decode(b64))))
            for fmt, b64, w, h in found]


def test_a_run_without_a_speed_stage_draws_no_summary(tmp_path):
    """--no-speed or failure cases only: no empty "Summary across scenes"
    chart and no link to it, and no empty scene list where there are no scenes;
    with the stage, both."""
    res = synthetic_results()
    timed = open(report.build(str(fake_run_dir(tmp_path / "a", res))), encoding="utf-8").read()
    assert 'id="summary"' in timed and 'href="#summary"' in timed
    untimed = dataclasses.replace(res, scenes=[dataclasses.replace(s, speed=None)
                                               for s in res.scenes])
    text = open(report.build(str(fake_run_dir(tmp_path / "b", untimed))), encoding="utf-8").read()
    assert "Summary across scenes" not in text and 'href="#summary"' not in text
    alone = dataclasses.replace(res, scenes=[])             # failure cases only
    (tmp_path / "c").mkdir()
    text = open(report.build(str(fake_run_dir(tmp_path / "c", alone))), encoding="utf-8").read()
    assert "Scenes:" not in text and 'href="#failures"' in text


def test_report_is_self_contained(tmp_path):
    page = report.build(str(fake_run_dir(tmp_path)))
    text = open(page, encoding="utf-8").read()
    assert "cosine hemisphere" in text                      # the estimator table
    assert "default-src 'none'" in text                     # the page may fetch nothing
    markup = re.sub(r"<script\b.*?</script>", "", text, flags=re.S)
    assert not re.search(r'(src|href)="(?!data:|#)', markup)  # no external resources
    # one script, inline (the viewers'), and each scene's viewer data
    assert text.count("<script>") == 1 and "<script src" not in markup
    assert text.count('<script type="application/json" class=vdata>') == 2
    shown = data_images(text)
    # the renders are the viewers' data; pictures: reference, mean and error
    # for each of the 3 scene checks that need attention
    assert len(shown) == text.count("<img ") == 3 * 3
    assert "$" not in re.sub(r"<(svg|style|script)\b.*?</\1>", "", text, flags=re.S)
    for fmt, width, height, image in shown:
        assert fmt in ("png", "webp", "avif") and image.format.lower() == fmt
        image.load()                                        # decodable
        zoom = width // image.width                         # whole screen pixels per pixel
        assert zoom >= 1 and (width, height) == (zoom * image.width, zoom * image.height)
    # 2 scenes × 3: uniform fails in both, cosine is inconclusive in one
    assert "3 of 6 checks pass, 1 inconclusive, 2 fail" in text
    unsure = text.split("Inconclusive at this budget", 1)[1]
    assert "cosine_hemisphere/unbiased</code>: m inconclusive" in unsure
    assert 'class=warn title="why inconclusive">inconclusive' in text
    assert "alpha/uniform_hemisphere/unbiased" in text       # failures are listed
    assert not (tmp_path / "report" / "summary.md").exists()  # one summary.md: the run's


def test_report_command_rewrites_the_page_and_the_summary(tmp_path, capsys):
    """`mcillum report DIR` writes DIR/report/index.html and DIR/summary.md
    (the one summary, results/tables.py) from DIR/results.json."""
    from mcillum.validation import cli
    run_dir = fake_run_dir(tmp_path)
    assert cli.main(["report", str(run_dir)]) == 0
    assert (run_dir / "report" / "index.html").is_file()
    assert "# mcillum validation" in (run_dir / "summary.md").read_text()
    assert str(run_dir / "report" / "index.html") in capsys.readouterr().out


def test_report_needs_a_results_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="mcillum validate"):
        report.build(str(tmp_path))


def test_worst_window_finds_the_hot_spot():
    err = np.zeros((16, 16))
    err[10:13, 2:5] = 1.0
    y, x, size = worst_window([err, err * 0.5])
    assert size == 4 and y <= 10 < y + size and x <= 2 < x + size


# --------------------------- Images and charts, compact ---------------------------

def test_maps_are_exactly_the_colours_of_their_colour_bar():
    """An error or FLIP map decodes to exactly the colours matplotlib picks for
    its values on the stepped scale its colour bar shows."""
    levels = parts.ERROR_LEVELS
    middles = (np.arange(64 * 64) % levels + 0.5) / levels          # every step, mid-step
    err = 1e-3 * 10 ** (3 * middles.reshape(64, 64))
    norm = matplotlib.colors.LogNorm(vmin=1e-3, vmax=1.0)
    wanted = parts.map_colours(levels)(norm(err), bytes=True)[..., :3]
    assert (parts.decoded(parts.error_map(err, 1e-3, 1.0)) == wanted).all()
    # a FLIP map's steps (the viewer's data, report/viewer.py) on its palette
    flip = np.random.default_rng(0).uniform(0, 1, (64, 64))
    colours = parts.map_colours(parts.FLIP_LEVELS)
    wanted = colours(flip, bytes=True)[..., :3]
    palette = colours(np.arange(parts.FLIP_LEVELS), bytes=True)[:, :3]
    assert (palette[parts.steps(flip, parts.FLIP_LEVELS)] == wanted).all()


def noisy_ramp(sigma: float, rng) -> np.ndarray:
    """A 128² 8-bit grey ramp with Gaussian noise of ``sigma`` levels."""
    ramp = np.linspace(40, 200, 128)[None, :, None] * np.ones((128, 1, 3))
    return np.clip(np.round(ramp + rng.normal(0, sigma, ramp.shape)), 0, 255).astype(np.uint8)


@pytest.mark.skipif(not parts._AVIF, reason="this Pillow has no AVIF encoder with libaom")
def test_renders_are_lossy_only_where_their_noise_stays():
    """A render is AVIF where that keeps its pixel-scale detail (its noise)
    within DETAIL_TOLERANCE and is smaller than exact: noise of 12 levels in a
    third of the bytes; noise of 1 level, which AVIF would smooth away, exact.
    The broken twin, AVIF at the default tuning, loses a third of the detail."""
    rng = np.random.default_rng(3)
    exact = lambda a: parts._picture(Image.fromarray(a), parts._LOSSLESS)  # noqa: E731
    faint, noisy = noisy_ramp(1.0, rng), noisy_ramp(12.0, rng)
    shown = parts.render(noisy)
    assert shown.uri.startswith("data:image/avif;") and len(shown.uri) < len(exact(noisy).uri) / 3
    kept = parts.detail(parts.decoded(shown)) / parts.detail(noisy)
    assert abs(kept - 1) <= parts.DETAIL_TOLERANCE
    assert (parts.decoded(parts.render(faint)) == faint).all()
    twin = parts._picture(Image.fromarray(noisy), [{"format": "avif", "quality": 60,
                                                   "subsampling": "4:4:4"}])
    assert parts.detail(parts.decoded(twin)) / parts.detail(noisy) < 0.67


def chart_svgs() -> list[str]:
    scene = synthetic_results().scenes[0]
    return [charts.error_vs_time(scene, COLOURS), charts.error_vs_spp(scene, COLOURS),
            charts.error_spread(scene, COLOURS),
            charts.efficiency_summary(synthetic_results(), COLOURS),
            charts.learning_curve(synthetic_learning(), COLOURS),
            charts.colour_bar(1e-3, 1.0, parts.map_colours(parts.ERROR_LEVELS), "relative error")]


def test_charts_are_compact_well_formed_svg():
    """Every chart parses as XML; its text is text (not a path per glyph), in
    a font list that ends in a generic family; every class it uses has its rule;
    no comments, line breaks or plain groups are left."""
    import xml.etree.ElementTree as ET

    for svg in chart_svgs():
        ET.fromstring(svg)
        assert "<text" in svg and "DejaVuSans-" not in svg
        fonts = re.findall(r"font-family: ([^;}\"]+)", svg)
        assert fonts and all(f.endswith("sans-serif") for f in fonts), fonts
        rules = set(re.findall(r"\.(c[0-9a-f]{8})\{", svg))
        assert set(re.findall(r'class="([^"]+)"', svg)) <= rules
        assert "<!--" not in svg and "\n" not in svg and "<g>" not in svg


# ------------------------------ In a real browser ------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


needs_browser = pytest.mark.skipif(
    not (CHROMIUM and CHROMEDRIVER),
    reason="needs Debian's chromium and chromium-driver (make test installs them when run "
           "as root with apt)")


def inspect_in_chromium(page, tmp_path):
    """Open ``page`` headless; return (image widths, whether the screenshot has
    content, severe console messages, non-local requests)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    import matplotlib.image

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--window-size=1200,1600",
                 f"--user-data-dir={tmp_path / 'profile'}"):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        driver.get("file://" + os.path.abspath(page))
        widths = driver.execute_script(
            "return Array.from(document.images).map(i => i.complete ? i.naturalWidth : 0)")
        shot = tmp_path / "shot.png"
        driver.save_screenshot(str(shot))
        has_content = matplotlib.image.imread(shot).std() > 0.05
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        messages = [json.loads(e["message"])["message"] for e in driver.get_log("performance")]
        return widths, has_content, errors, external_requests(messages)
    finally:
        driver.quit()


def external_requests(messages):
    """The URLs that a file:// page asked for beyond file: and data:, from
    Chromium's performance log (DevTools ``Network.requestWillBeSent`` events).

    Only requests made for a document opened from a file count: the browser's
    own pages (its start page, and Chromium 150's new-tab page that asks for
    ``chrome-untrusted://new-tab-page/one-google-bar``) are not the page's,
    whatever scheme their requests use."""
    return [m["params"]["request"]["url"] for m in messages
            if m.get("method") == "Network.requestWillBeSent"
            and m["params"].get("documentURL", "").startswith("file:")
            and not m["params"]["request"]["url"].startswith(("file:", "data:"))]


def _sent(url, document):
    return {"method": "Network.requestWillBeSent",
            "params": {"request": {"url": url}, "documentURL": document}}


def test_only_the_pages_own_requests_count_as_external():
    """The browser's own requests (any Chromium version's start page) are left
    out; the page's file, data and network requests are told apart."""
    page = "file:///tmp/report/index.html"
    messages = [
        _sent("chrome-untrusted://new-tab-page/one-google-bar?paramsencoded=",
              "chrome://new-tab-page/"),
        _sent("chrome://new-tab-page/", "chrome://new-tab-page/"),
        _sent("https://www.google.com/async/newtab_promos", "chrome://new-tab-page/"),
        _sent(page, page),
        _sent("data:image/png;base64,AAAA", page),
        _sent("http://127.0.0.1:9/x.png", page),
        _sent("chrome-untrusted://anything", page),
        {"method": "Network.responseReceived", "params": {}},
    ]
    assert external_requests(messages) == ["http://127.0.0.1:9/x.png",
                                           "chrome-untrusted://anything"]


@pytest.mark.browser
@needs_browser
def test_report_renders_in_headless_chromium(tmp_path):
    page = report.build(str(fake_run_dir(tmp_path)))
    widths, has_content, errors, external = inspect_in_chromium(page, tmp_path)
    assert widths and all(w > 0 for w in widths), widths
    assert has_content, "the page rendered blank"
    assert not errors, errors
    assert not external, external


@pytest.mark.browser
@needs_browser
def test_browser_check_catches_a_broken_page(tmp_path):
    """The same inspection flags undecodable images and external requests."""
    page = tmp_path / "bad.html"
    page.write_text('<!DOCTYPE html><html><body><img src="data:image/png;base64,AAAA">'
                    '<img src="http://127.0.0.1:9/x.png"></body></html>')
    widths, _, errors, external = inspect_in_chromium(page, tmp_path)
    assert widths == [0, 0] and errors and external == ["http://127.0.0.1:9/x.png"]


def test_strict_exit_code_counts_inconclusive_checks(tmp_path, monkeypatch, capsys):
    """`mcillum validate` exits 0 when checks are only inconclusive, 1 with
    --strict (the pipeline replaced by a synthetic run with one of each)."""
    from mcillum.validation import cli, pipeline

    res = synthetic_results()
    res.checks = [c for c in res.checks if c.outcome != "fail"]
    monkeypatch.setattr(pipeline, "validate", lambda *a, **k: res)
    args = ["validate", "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "c")]
    assert cli.main(args) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    n = res.counts()
    assert last == (f"PASSED: pass {n['pass']}, fail 0, inconclusive {n['inconclusive']} "
                    f"of {len(res.checks)} checks"), last
    assert cli.main([*args, "--strict"]) == 1
    out = capsys.readouterr().out
    assert "1 inconclusive, 0 fail" in out
    assert out.strip().splitlines()[-1].startswith("FAILED: ") and "--strict" in out
    for bad in (["--seed-set", "1000"], ["--budget", "0.5"]):
        with pytest.raises(SystemExit) as exit_:
            cli.main([*args, *bad])
        assert exit_.value.code == 2


@pytest.mark.parametrize("ev, text", [(-0.0, "x"), (0.04, "x"), (-0.02, "x"),
                                      (1.0, "x·2<sup>+1.0</sup>"), (-2.34, "x·2<sup>-2.3</sup>")])
def test_tone_mapping_scale_reads_plainly(ev, text):
    """An exposure that rounds to 0 reads as `x`, not `x·2^-0.0`."""
    assert scene_section._scaling(ev) == text


def test_a_flat_reference_is_shown_grey_with_room_for_its_noise():
    """cap_plane's disk fills its frame (every pixel 0.584): the 99th
    percentile mapped to 1 showed its renders white, noise above the mean
    clipped. A lit scene keeps its 99th percentile at 1 (the median rule
    only ever darkens)."""
    rng = np.random.default_rng(3)
    flat = np.full((16, 16, 3), 0.584)
    ev = images.exposure_for(flat)
    assert 0.25 < 0.584 * 2 ** ev <= images.MEDIAN_AT_MOST
    noisy = flat * rng.uniform(0.5, 1.5, flat.shape)
    assert np.mean(images.tonemap(noisy, ev) == 255) < 0.01
    lit = np.full((16, 16, 3), 0.04)
    lit[:3, :3] = 9.0                                  # a light: 3.5 % of the pixels
    assert images.exposure_for(lit) == np.round(-np.log2(9.0) * 2) / 2
    assert images.exposure_for(np.zeros((4, 4, 3))) == 0.0


def test_a_heavy_tailed_figure_reads_as_a_bound_everywhere(tmp_path):
    """A heavy-tailed efficiency (kind heavy_tailed, interval [0, upper end])
    and relMSE ([low, ∞)), and one with no bound either way: results.json
    holds them as the schema says, they read back, the summary and the page
    show "≤ x (heavy-tailed)", "unbounded either way" and "[low, ∞)", the
    summary chart names its "?", and the accuracy-vs-time chart draws
    them."""
    import jsonschema
    from mcillum.validation.results import Interval
    res = synthetic_results()
    speed = res.scenes[0].speed
    run = speed.budgets[-1].estimators["uniform_hemisphere"]
    run.relmse_ci = Interval(run.relmse_ci.low, math.inf)
    r = speed.efficiency_vs_path["uniform_hemisphere"]
    speed.efficiency_vs_path["uniform_hemisphere"] = Ratio(
        ratio=r.ratio, ci=Interval(0.0, r.ci.high), kind="heavy_tailed")
    r = res.scenes[1].speed.efficiency_vs_path["cosine_hemisphere"]
    res.scenes[1].speed.efficiency_vs_path["cosine_hemisphere"] = Ratio(
        ratio=r.ratio, ci=Interval(0.0, math.inf), kind="heavy_tailed")
    run_dir = fake_run_dir(tmp_path, res)
    jsonschema.validate(json.loads((run_dir / "results.json").read_text()),
                        json.load(open(results.SCHEMA_FILE)))
    back = results.load(str(run_dir))
    bound = back.scenes[0].speed.efficiency_vs_path["uniform_hemisphere"]
    assert results.ratio_text(bound) == f"≤ {bound.ci.high:.3g} (heavy-tailed)"
    assert "unbounded either way (heavy-tailed)" in results.ratio_text(
        back.scenes[1].speed.efficiency_vs_path["cosine_hemisphere"])
    low = back.scenes[0].speed.budgets[-1].estimators["uniform_hemisphere"]
    assert results.relmse_text(low).endswith(f"[{low.relmse_ci.low:.3g}, ∞)")
    summary = "\n".join(results.speed_summary(back.scenes[0].speed))
    assert "(heavy-tailed)" in summary and "∞)" in summary and "heavy-tailed: rare" in summary
    page = open(report.build(str(run_dir)), encoding="utf-8").read()
    assert "(heavy-tailed)" in page and "∞)" in page
    assert "?: heavy-tailed, no bound" in charts.efficiency_summary(back, COLOURS)
    assert "<svg" in charts.error_vs_time(back.scenes[0], COLOURS)


def test_a_figure_withheld_off_its_budget_reads_withheld_everywhere(tmp_path):
    """An efficiency withheld off its budget (kind off_budget, ratio and
    interval NaN, a reason; not ranked: stages/speed.py off_budget):
    results.json holds it as the schema says (null), it reads back, and the
    summary, the page and the charts show no interval for it, the reason
    instead, while the other estimators keep theirs."""
    import jsonschema
    from mcillum.validation.results import Interval
    res = synthetic_results()
    speed = res.scenes[0].speed
    why = "off budget: median 10 ms at 2 spp against a 114 ms budget (×0.088)"
    speed.efficiency_vs_path["uniform_hemisphere"] = Ratio(
        ratio=math.nan, ci=Interval(math.nan, math.nan), kind="off_budget", reason=why)
    speed.ranking = [p for p in speed.ranking if p.estimator != "uniform_hemisphere"]
    run_dir = fake_run_dir(tmp_path, res)
    jsonschema.validate(json.loads((run_dir / "results.json").read_text()),
                        json.load(open(results.SCHEMA_FILE)))
    back = results.load(str(run_dir)).scenes[0].speed
    withheld = back.efficiency_vs_path["uniform_hemisphere"]
    assert withheld.kind == "off_budget" and math.isnan(withheld.ratio)
    assert results.ratio_text(withheld) == f"withheld: {why}"
    summary = "\n".join(results.speed_summary(back))
    assert f"withheld: {why}" in summary and "off-budget: withheld" in summary
    kept = back.efficiency_vs_path["cosine_hemisphere"]
    assert f"{kept.ratio:.3g} [{kept.ci.low:.3g}, {kept.ci.high:.3g}]" in summary
    page = open(report.build(str(run_dir)), encoding="utf-8").read()
    assert html.escape(f"withheld: {why}") in page
    assert "<svg" in charts.efficiency_summary(results.load(str(run_dir)), COLOURS)


def test_the_page_opens_on_what_needs_attention_and_the_matrix(tmp_path):
    """Failed checks first, then inconclusive ones, each linked to an element
    of the page; the matrix gives each estimator × scene its worst verdict
    and efficiency ÷ path, and links every cell to its scene's row."""
    text = open(report.build(str(fake_run_dir(tmp_path))), encoding="utf-8").read()
    head = text.split("<section id=matrix>", 1)[0]
    assert text.index("id=attention") < text.index("id=matrix") < text.index('<section id="alpha">')
    listed = re.findall(r"<li class=att><span class=(\w+)>.</span> <a href='#([^']+)'>"
                        r"<code>([^<]+)</code>", head)
    assert [c for _, _, c in listed] == ["alpha/uniform_hemisphere/unbiased",
                                         "beta/uniform_hemisphere/unbiased",
                                         "beta/cosine_hemisphere/unbiased"]
    assert [cls for cls, _, _ in listed] == ["bad", "bad", "warn"]
    ids = set(re.findall(r"""id=['"]?([^'" >]+)""", text))
    assert all(target in ids for _, target, _ in listed)
    matrix = text.split("<section id=matrix>", 1)[1].split("</section>", 1)[0]
    rows = {re.search(r"</span>([a-z_]+)</th>", r).group(1): r
            for r in re.findall(r"<tr><th><span class=sw.*?</tr>", matrix)}
    glyphs = {n: re.findall(r"<span class=(?:ok|bad|warn|desc)>(.)</span>", r)
              for n, r in rows.items()}
    assert glyphs == {"uniform_hemisphere": ["✗", "✗"], "cosine_hemisphere": ["✓", "?"],
                      "path": ["✓", "✓"]}
    links = re.findall(r"<a href='#([^']+)'>", matrix)
    assert links and all(link in ids for link in links)
    assert "alpha--uniform_hemisphere" in links
    # efficiencies ÷ path: uniform's interval lies below 1, so its cell is red
    assert re.search(r"class='cell effdown'[^>]*><a href='#alpha--uniform_hemisphere'>", matrix)
