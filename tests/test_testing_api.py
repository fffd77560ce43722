"""The testing API (mcillum/testing.py) and the pytest plugin
(mcillum/pytest_plugin.py), as a user's test suite meets them: a user's
direct-light integrator and its broken twin (every light sample 5 % too
dark), a scene written the way stock Mitsuba scenes are, in folders outside
the checkout.

The plugin's tests run a user's test file in a fresh pytest process
(``pytester.runpytest_subprocess``): the plugin must arrive by its
``pytest11`` entry point alone, as it does for a user, and Mitsuba's
variant and the user's imported plugin stay out of this process.
``pytester`` is enabled by ``pytest_plugins`` below: pytest forbids that
variable in a non-root conftest.py, not in a test module.
"""

from __future__ import annotations

import os
import textwrap
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import pytest
from mcillum.validation.results import Check
from test_stock_scenes import write_scene
from user_code import MY_INTEGRATOR

from mcillum.errors import UsageError
from mcillum.testing import (
    Comparison,
    Inconclusive,
    assert_passes,
    assert_unbiased,
    compare,
)

pytest_plugins = ["pytester"]

#: The film's $res: 32², reduced to the quick profile's 24² for the statistics.
DEFINES = {"res": 32}


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """The user's folders: the plugin file, the scene (max_depth 2: direct
    light, as my_direct computes) and a references cache that every test of
    this module shares (a second comparison of the scene reuses `path`'s
    reference)."""
    root = tmp_path_factory.mktemp("user")
    plugin = root / "my_integrator.py"
    plugin.write_text(MY_INTEGRATOR)
    scene = write_scene(root / "scene", params='<integer name="max_depth" value="2"/>')
    return SimpleNamespace(plugin=str(plugin), scene=scene, cache=str(root / "cache"))


def run(user, integrator, out_dir):
    return compare(user.scene, integrator, plugins=user.plugin, out_dir=out_dir,
                   cache_dir=user.cache, defines=DEFINES)


# ------------------------------ compare and assert ------------------------------

def test_a_correct_integrator_passes_with_the_reference_rendered(user, tmp_path):
    c = run(user, "my_direct", tmp_path)
    assert_passes(c)
    assert_unbiased(c)
    assert {k.id for k in c.checks} >= {"scene/my_direct/unbiased", "scene/my_direct/finite"}
    assert c.passed and c.failed == [] and c.inconclusive == []
    assert c.reference_checks, "path was not rendered beside the integrator"
    assert c.report == str(tmp_path / "report" / "index.html") and os.path.isfile(c.report)
    assert c.images == [str(tmp_path / "images" / "scene")]
    assert any("statistics at 24×24" in n for n in c.notes), c.notes


def test_the_broken_twin_fails_naming_the_check_images_and_report(user, tmp_path):
    c = run(user, "my_direct_broken", tmp_path)
    assert [k.id for k in c.failed] == ["scene/my_direct_broken/unbiased"]
    for judge in (assert_passes, assert_unbiased):
        with pytest.raises(AssertionError) as err:
            judge(c)
        assert not isinstance(err.value, Inconclusive)
        text = str(err.value)
        assert "scene/my_direct_broken/unbiased: image mean darker" in text, text
        assert f"report: {c.report}" in text and os.path.isfile(c.report)
        assert f"images: {tmp_path / 'images' / 'scene'}" in text


# The verdicts of the helpers, on comparisons made up of checks (no render).

def made_up(*outcomes, notes=()):
    checks = [Check(id=f"room/mine/{what}", passed=o != "fail", message=f"{what} said {o}",
                    outcome=o) for what, o in outcomes]
    results = SimpleNamespace(checks=checks, scenes=[SimpleNamespace(name="room",
                                                                     notes=list(notes))])
    return Comparison(scene="room.xml", integrator="mine", reference="path",
                      results=results, out_dir="/runs/room", report="/runs/room/report.html")


def test_inconclusive_raises_inconclusive_with_what_could_not_decide():
    c = made_up(("finite", "pass"), ("unbiased", "inconclusive"))
    for judge in (assert_passes, assert_unbiased):
        with pytest.raises(Inconclusive) as err:
            judge(c)
        assert "room/mine/unbiased: unbiased said inconclusive" in str(err.value)
        assert "none failed" in str(err.value) and "report: /runs/room/report.html" in str(err.value)
        assert isinstance(err.value, AssertionError)     # never a pass where unknown
    with pytest.raises(AssertionError) as err:
        assert_passes(c, strict=True)
    assert not isinstance(err.value, Inconclusive) and "counted as failures" in str(err.value)


def test_a_failure_outweighs_inconclusive_checks_and_lists_both():
    c = made_up(("unbiased", "fail"), ("converges", "inconclusive"))
    with pytest.raises(AssertionError) as err:
        assert_passes(c)
    assert not isinstance(err.value, Inconclusive)
    text = str(err.value)
    assert "failed 1 of 2 checks" in text and "inconclusive too:\n  room/mine/converges" in text


def test_no_check_is_no_pass():
    """An integrator that refused the scene has no checks: say so, with why."""
    c = made_up(notes=["mine does not render this scene: the scene holds glossy lobes"])
    with pytest.raises(AssertionError, match="no check of 'mine' ran on scene 'room'.*glossy"):
        assert_passes(c)


def test_assert_unbiased_judges_only_the_unbiased_checks():
    assert_unbiased(made_up(("unbiased", "pass"), ("converges", "fail")))
    with pytest.raises(AssertionError, match="failed 1 of 2 checks"):
        assert_passes(made_up(("unbiased", "pass"), ("converges", "fail")))
    with pytest.raises(AssertionError, match="no unbiased check.*use assert_passes"):
        assert_unbiased(made_up(("bias_shrinks", "pass"), ("calibrated", "pass")))


@pytest.mark.parametrize("scene, kwargs, said", [
    ("room.xml", {"reference": "volpath"}, "always Mitsuba's path tracer"),
    ("no_such_scene", {}, "is no scene of profile 'quick' (its scenes: furnace_sphere"),
    ("furnace_sphere", {"max_depth": 3}, "max_depth apply to a scene file"),
])
def test_usage_errors_say_what_to_do(scene, kwargs, said, tmp_path):
    with pytest.raises(UsageError) as err:
        compare(scene, "my_direct", out_dir=tmp_path, **kwargs)
    assert said in str(err.value)
    assert not any(tmp_path.iterdir()), "nothing may run before the arguments are checked"


# --------------------------------- The plugin ----------------------------------

@pytest.fixture
def fresh(pytester, monkeypatch):
    """A user's pytest run in its own process; plugins load by entry point."""
    monkeypatch.delenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("PYTEST_ADDOPTS", raising=False)
    return pytester


def test_the_fixture_passes_the_correct_and_fails_the_broken_integrator(user, fresh):
    fresh.makepyfile(test_mine=textwrap.dedent(f"""
        from mcillum.testing import assert_passes

        def check(mcillum_compare, name):
            assert_passes(mcillum_compare({user.scene!r}, name, plugins=[{user.plugin!r}],
                                          cache_dir={user.cache!r}, defines={DEFINES!r}))

        def test_correct(mcillum_compare):
            check(mcillum_compare, "my_direct")

        def test_broken(mcillum_compare):
            check(mcillum_compare, "my_direct_broken")
        """))
    junit = fresh.path / "junit.xml"
    result = fresh.runpytest_subprocess(f"--junitxml={junit}", timeout=300)
    result.assert_outcomes(passed=1, failed=1)
    result.stdout.fnmatch_lines(["*scene/my_direct_broken/unbiased: image mean darker*",
                                 "*Captured mcillum call*", "*my_direct_broken on *: report *"])
    reports = {case.get("name"): prop.get("value") for case in ET.parse(junit).iter("testcase")
               for prop in case.iter("property") if prop.get("name") == "mcillum_report"}
    assert set(reports) == {"test_correct", "test_broken"}, reports
    for name, report in reports.items():        # in the test's own tmp_path
        assert report.endswith(os.path.join(f"{name}0", "mcillum", "report", "index.html"))
        assert os.path.isfile(report)


def test_inconclusive_is_xfail_by_default_and_a_failure_when_strict(fresh):
    fresh.makepyfile(test_mine=textwrap.dedent("""
        import mitsuba as mi
        from mcillum.testing import Inconclusive

        def test_loaded_by_entry_point_without_a_variant(request):
            assert request.config.pluginmanager.has_plugin("mcillum")
            assert mi.variant() is None        # the plugin set none: no test asked

        def test_undecided():
            raise Inconclusive("room/mine/unbiased: 4 renders more would decide")

        def test_plain_failure():
            assert 1 == 2
        """))
    result = fresh.runpytest_subprocess("-rx")
    result.assert_outcomes(passed=1, xfailed=1, failed=1)
    said = "inconclusive: room/mine/unbiased: 4 renders more would decide"
    result.stdout.fnmatch_lines([f"XFAIL *test_undecided - {said}"])
    result = fresh.runpytest_subprocess("--mcillum-strict")
    result.assert_outcomes(passed=1, failed=2)
    result.stdout.fnmatch_lines(["*inconclusive, counted as a failure (--mcillum-strict)*"])


def test_a_failing_helper_shows_the_users_line_not_mcillums_frames(fresh):
    """``__tracebackhide__``: a failing assert_passes, and a usage error of the
    fixture, point at the test's own line and say the message; no frame of
    testing.py or pytest_plugin.py is printed (the made-up comparison needs
    no render)."""
    fresh.makepyfile(test_mine=textwrap.dedent("""
        from types import SimpleNamespace
        from mcillum.testing import Comparison, assert_passes, assert_unbiased
        from mcillum.validation.results import Check

        def made_up():
            check = Check(id="room/mine/unbiased", passed=False, outcome="fail",
                          message="image mean darker than the reference")
            results = SimpleNamespace(checks=[check],
                                      scenes=[SimpleNamespace(name="room", notes=[])])
            return Comparison(scene="room.xml", integrator="mine", reference="path",
                              results=results, out_dir="/runs", report="/runs/r.html")

        def test_fails():
            assert_passes(made_up())  # the user's line

        def test_fails_unbiased():
            assert_unbiased(made_up())  # the user's other line

        def test_usage(mcillum_compare):
            mcillum_compare("no_such_scene", "mine")  # the user's mistake
        """))
    result = fresh.runpytest_subprocess()
    result.assert_outcomes(failed=3)
    result.stdout.fnmatch_lines([
        "*assert_passes(made_up())  # the user's line",
        "E * 'mine' failed 1 of 1 checks against 'path' on scene 'room':",
        "E *room/mine/unbiased: image mean darker than the reference",
        "*assert_unbiased(made_up())  # the user's other line",
        "E * 'mine' failed 1 of 1 unbiased checks*",
        "*mcillum_compare(\"no_such_scene\", \"mine\")  # the user's mistake",
        "E *UsageError: scene 'no_such_scene' is no scene of profile 'quick'*"])
    shown = result.stdout.str()
    for internal in ("testing.py", "pytest_plugin.py", "_judge(", "def run("):
        assert internal not in shown, f"{internal} in the traceback:\n{shown}"


# ------------------------------ nothing left set ------------------------------

#: What a comparison found, as JSON: each check's id, outcome and message,
#: and a digest of each image it wrote (pixels, not the EXR's bytes).
_FOUND = '''
import hashlib, json, os, sys
from mcillum import files
from mcillum.testing import compare

def found(c):
    images = {}
    for folder in c.images:
        for name in sorted(os.listdir(folder)):
            if name.endswith(".exr"):
                pixels = files.read_exr(os.path.join(folder, name))[0]
                images[name] = hashlib.sha256(pixels.tobytes()).hexdigest()
    checks = [[k.id, k.outcome, k.message] for k in c.results.checks]
    return {"checks": checks, "images": images}

def run(scene, plugin, root, seed_set):
    c = compare(scene, "my_direct", plugins=plugin, out_dir=f"{root}/out{seed_set}",
                cache_dir=f"{root}/cache{seed_set}", defines={"res": 16}, res=8,
                seed_set=seed_set)
    return found(c)
'''


def test_two_seed_sets_in_one_process_are_as_in_two(user, tmp_path):
    """Two comparisons with different seed sets, one after the other in this
    process, find what each finds alone in a fresh process: the seed set
    travels with the run, and nothing of the first run is left set for the
    second (nor after it: a stream asked for outside a run is set 0's)."""
    import json
    import subprocess
    import sys

    from mcillum.validation.plan import seeds

    here = {}
    exec(_FOUND, here)
    alone = {}
    for s in (1, 2):
        code = _FOUND + f"\nprint(json.dumps(run({user.scene!r}, {user.plugin!r}, " \
                        f"{str(tmp_path / 'alone')!r}, {s})))"
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              check=True)
        alone[s] = json.loads(done.stdout.strip().splitlines()[-1])
    together = {s: here["run"](user.scene, user.plugin, str(tmp_path / "together"), s)
                for s in (1, 2)}
    assert together[1]["images"] and together[1]["checks"]
    # (every image differs between the sets: no stream ignores the run's set)
    differ = [together[1]["images"][k] != together[2]["images"][k] for k in together[1]["images"]]
    assert all(differ), together
    assert together == alone
    assert seeds.stream("bench").seed(0) == 900_000
