"""mcillum's pytest plugin: a user's tests compare their integrator with
Mitsuba's ``path`` (mcillum/testing.py).

Installing mcillum registers it (entry point ``pytest11``, name
``mcillum``; ``-p no:mcillum`` turns it off). It offers:

* the fixture ``mcillum_compare``: :func:`mcillum.testing.compare` with the
  run directory in the test's ``tmp_path`` (``tmp_path/"mcillum"``, then
  ``mcillum-2``… for further calls). Each report's path is recorded in the
  test's ``user_properties`` (``mcillum_report``: JUnit XML shows it) and
  in a report section ("Captured mcillum call", shown with a failure);
* the option ``--mcillum-strict``;
* the verdict of :class:`mcillum.testing.Inconclusive` raised by a test
  (``assert_passes`` with no failing but some inconclusive checks): xfail,
  its message as the reason; a failure under ``--mcillum-strict``.

A test::

    from mcillum.testing import assert_passes

    def test_my_direct_is_unbiased(mcillum_compare):
        c = mcillum_compare("scenes/room.xml", "my_direct",
                            plugins=["my_integrator.py"])
        assert_passes(c)

Loading the plugin imports no Mitsuba variant and no validation code: the
fixture sets the variant ($MCILLUM_VARIANT, else llvm_ad_rgb) when a test
asks for it, so a test suite that does not use it pays nothing.
"""

from __future__ import annotations

import pytest

from .testing import Inconclusive, _hide_user_errors

STRICT = "--mcillum-strict"


def pytest_addoption(parser):
    group = parser.getgroup("mcillum", "mcillum: integrators against Mitsuba's path")
    group.addoption(STRICT, action="store_true", dest="mcillum_strict",
                    help="fail a test that raises mcillum.testing.Inconclusive (checks "
                         "that could not decide at their budget) instead of xfail")


@pytest.fixture
def mcillum_compare(request, tmp_path):
    """``mcillum.testing.compare`` with ``out_dir`` defaulting to the test's
    ``tmp_path/"mcillum"`` (``mcillum-2``… for further calls); returns the
    Comparison and records its report's path on the test."""
    from .testing import compare
    from .validation.run import renders

    # A variant set here, not at import: only tests that compare pay for it.
    renders.set_variant(None)
    calls = []

    def run(scene, integrator, **kwargs):
        __tracebackhide__ = _hide_user_errors     # (a usage error: the user's line says it)
        calls.append(scene)
        if kwargs.get("out_dir") is None:
            suffix = "" if len(calls) == 1 else f"-{len(calls)}"
            kwargs["out_dir"] = tmp_path / f"mcillum{suffix}"
        comparison = compare(scene, integrator, **kwargs)
        request.node.user_properties.append(("mcillum_report", comparison.report))
        request.node.add_report_section(
            "call", "mcillum", f"{integrator} on {comparison.scene}: report "
            f"{comparison.report}\nimages: {', '.join(comparison.images)}")
        return comparison

    return run


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if call.when != "call" or call.excinfo is None or not report.failed \
            or not call.excinfo.errisinstance(Inconclusive):
        return
    if item.config.getoption("mcillum_strict"):
        report.sections.append(("mcillum", f"inconclusive, counted as a failure ({STRICT})"))
        return
    # As pytest's own xfail does: a skipped outcome that carries its reason.
    report.outcome = "skipped"
    report.wasxfail = f"inconclusive: {call.excinfo.value}"
