"""The HTML report: chart builders on synthetic results (no rendering), a
self-contained page, and (marked `browser`) the page as Chromium shows it."""

import base64
import io
import json
import os
import re
import shutil

import numpy as np
import pytest

from mcillum.validation import charts, images, report

ESTIMATORS = ["uniform_hemisphere", "cosine_hemisphere", "path"]


def synthetic_results(scenes=("alpha", "beta"), ladder=(4, 16, 64)):
    rng = np.random.default_rng(0)
    out = {"schema": "mcillum.results", "version": 1, "created": "2026-11-22T12:00:00",
           "profile": "quick", "variant": "llvm_ad_rgb", "mitsuba_version": "3.9.1",
           "drjit_version": "1.5.0", "alpha": 0.01, "wall_seconds": 12.0,
           "machine": {"platform": "Linux", "cpus": 2, "python": "3.11"},
           "scenes": [], "checks": []}
    for s in scenes:
        ests = []
        for i, name in enumerate(ESTIMATORS):
            runs = [{"spp": spp, "relmse": 0.5 / (i + 1) / spp, "median_seconds": 1e-4 * spp,
                     "relmse_per_render": list(0.5 / (i + 1) / spp * rng.lognormal(0, 1, 8)),
                     "bias": 1e-3, "bias_se": 2e-3, "samples_per_second": 1e6,
                     "efficiency": (i + 1) * spp / (0.5 * 1e-4 * spp)} for spp in ladder]
            ests.append({"name": name, "runs": runs,
                         "unbiasedness": {"passed": name != "uniform_hemisphere",
                                          "pass_fraction": 0.99},
                         "convergence": {"slope": -1.0, "low": -1.1, "high": -0.9,
                                         "exact": False}})
            out["checks"].append({"id": f"{s}/{name}/unbiased",
                                  "passed": name != "uniform_hemisphere", "message": "m"})
        out["scenes"].append({
            "name": s, "summary": f"{s}: a synthetic scene", "res": 8, "max_depth": 2,
            "reference": {"spp": 4096, "passes": 64, "seconds": 1.0, "capped": None},
            "estimators": ests,
            "equal_time": {"budget_seconds": 1e-3, "predicted_ranking": ESTIMATORS[::-1],
                           "measured_ranking": ESTIMATORS[::-1], "agrees": True}})
    return out


def test_colours_are_stable_and_distinct():
    a = charts.colours(["path", "mine", "cosine_hemisphere", "other"])
    assert a == charts.colours(["path", "mine", "cosine_hemisphere", "other"])
    assert len(set(a.values())) == 4 and a["path"] == charts.KNOWN["path"]


@pytest.mark.parametrize("builder", [charts.error_vs_time, charts.error_vs_spp,
                                     charts.error_spread])
def test_scene_charts_label_axes_and_every_estimator(builder):
    res = synthetic_results()
    palette = charts.colours(ESTIMATORS)
    svg = builder(res["scenes"][0], palette)
    assert svg.startswith("<svg") and "</svg>" in svg
    for name in ESTIMATORS:
        assert name in svg
    for colour in palette.values():
        assert colour.lower() in svg.lower()


def test_axis_labels_carry_units():
    scene = synthetic_results()["scenes"][0]
    palette = charts.colours(ESTIMATORS)
    assert "wall time per render [ms]" in charts.error_vs_time(scene, palette)
    assert "samples per pixel" in charts.error_vs_spp(scene, palette)
    assert "slope -1.00" in charts.error_vs_spp(scene, palette).replace("+", "")
    assert "ideal slope" in charts.error_vs_spp(scene, palette)


def test_efficiency_summary_is_relative_to_path():
    svg = charts.efficiency_summary(synthetic_results(), charts.colours(ESTIMATORS))
    assert "relative to Mitsuba" in svg and "path = 1" in svg
    assert "alpha" in svg and "beta" in svg


def fake_run_dir(tmp_path, res=None):
    """A results dir with synthetic results.json and EXR images."""
    res = res or synthetic_results()
    rng = np.random.default_rng(1)
    for s in res["scenes"]:
        d = tmp_path / "images" / s["name"]
        d.mkdir(parents=True)
        ref = rng.uniform(0.2, 1.0, (8, 8, 3)).astype(np.float32)
        images.write_exr(d / "reference.exr", ref)
        for e in s["estimators"]:
            noisy = (ref * rng.uniform(0.5, 1.5, ref.shape)).astype(np.float32)
            images.write_exr(d / f"{e['name']}_spp{e['runs'][-1]['spp']}.exr", noisy)
            images.write_exr(d / f"{e['name']}_equal_time.exr", noisy,
                             {"spp": 3, "render_seconds": 0.001})
    (tmp_path / "results.json").write_text(json.dumps(res))
    return tmp_path


def data_images(html_text):
    return re.findall(r'<img src="data:image/png;base64,([^"]+)"', html_text)


def test_report_is_self_contained(tmp_path):
    import matplotlib.image

    page = report.build(str(fake_run_dir(tmp_path)))
    text = open(page, encoding="utf-8").read()
    assert "default-src 'none'" in text                     # the page may fetch nothing
    assert not re.search(r'(src|href)="(?!data:|#)', text)  # no external resources
    assert "<script" not in text
    pngs = data_images(text)
    assert len(pngs) == 2 * (1 + 3 + 3 + 3 + 4)  # per scene: ref, eq-time, eq-spp, errors, crops
    for b64 in pngs:
        assert matplotlib.image.imread(io.BytesIO(base64.b64decode(b64)), format="png").size
    assert "4 of 6 checks passed" in text                    # 2 scenes x 3, uniform fails
    assert "alpha/uniform_hemisphere/unbiased" in text       # failures are listed
    assert (tmp_path / "report" / "summary.md").is_file()


def test_report_needs_a_results_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="mcillum validate"):
        report.build(str(tmp_path))


def test_worst_window_finds_the_hot_spot():
    err = np.zeros((16, 16))
    err[10:13, 2:5] = 1.0
    y, x, size = report.worst_window([err, err * 0.5])
    assert size == 4 and y <= 10 < y + size and x <= 2 < x + size


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
        urls = [m["params"]["request"]["url"] for m in messages
                if m.get("method") == "Network.requestWillBeSent"]
        # (chrome:// URLs are the browser's own start page, not the page's)
        external = [u for u in urls if not u.startswith(("file:", "data:", "chrome:"))]
        return widths, has_content, errors, external
    finally:
        driver.quit()


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
                    '<img src="http://192.0.2.1/x.png"></body></html>')
    widths, _, errors, external = inspect_in_chromium(page, tmp_path)
    assert widths == [0, 0] and errors and external == ["http://192.0.2.1/x.png"]
