"""Testing API: check in your own test suite that your integrator agrees with
Mitsuba's ``path`` on your scene.

:func:`compare` runs the validation of one scene and one integrator against
the reference, within a profile's budget, and returns a :class:`Comparison`
(the typed results, and where the images and the report are). The
``assert_…`` helpers turn it into a test verdict::

    from mcillum.testing import assert_passes, compare

    c = compare("scenes/room.xml", "my_direct", plugins=["my_integrator.py"])
    assert_passes(c)        # AssertionError naming each failing check

Each check has three outcomes: pass, fail, or inconclusive (the evidence
cannot decide at this budget; its message says what would decide). A test
should not pass on "could not tell", and should not fail either, so an
inconclusive check raises :class:`Inconclusive`. It subclasses
AssertionError: where nothing knows better (plain Python, unittest, pytest
without mcillum's plugin) it counts as a failure, never as a pass. The
pytest plugin (mcillum/pytest_plugin.py, loaded automatically once mcillum
is installed) reports it as xfail instead, or as a failure under
``--mcillum-strict``; its fixture ``mcillum_compare`` is :func:`compare`
with the report written in the test's ``tmp_path``. Outside pytest, catch
:class:`Inconclusive` before AssertionError to tell the two apart.

The validation is imported when :func:`compare` first runs (it imports
Mitsuba's variants and the pipeline): importing this module stays cheap.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .errors import UsageError, UserError
from .integrators.core import registry

if TYPE_CHECKING:
    from .validation.plan.profiles import Profile
    from .validation.results import Check, Results

__all__ = ["Comparison", "Inconclusive", "assert_passes", "assert_unbiased", "compare"]

#: The reference of every comparison (Mitsuba's path tracer).
REFERENCE = registry.REFERENCE


def _hide_user_errors(excinfo) -> bool:
    """For ``__tracebackhide__``: True for a :class:`~mcillum.errors.UserError`
    (pytest then leaves the frame out: the user's line and the message say
    it all); other exceptions keep mcillum's frames, where a bug would be."""
    return excinfo.errisinstance(UserError)


class Inconclusive(AssertionError):
    """No check failed, but some could not decide at the budget given. The
    message lists them (each says what budget would decide), then where the
    images and the report are. An AssertionError, so that code unaware of
    it counts it as a failure; the pytest plugin reports it as xfail unless
    ``--mcillum-strict``."""


@dataclass(frozen=True)
class Comparison:
    """One integrator compared with the reference on one scene (a bundled
    scene's name may stand for several runs of it in the profile)."""

    scene: str                  # as given: a scene file's path or a bundled name
    integrator: str
    reference: str
    results: Results            # the whole run (mcillum.validation.results.Results)
    out_dir: str                # the run directory (validation/results/layout.py)
    report: str                 # its HTML report: out_dir/report/index.html

    @property
    def scene_ids(self) -> list[str]:
        """The scene runs' ids, as the check ids and image folders name them."""
        return [s.name for s in self.results.scenes]

    @property
    def images(self) -> list[str]:
        """The folders of the scene runs' images (reference, renders, means)."""
        return [os.path.join(self.out_dir, "images", i) for i in self.scene_ids]

    @property
    def notes(self) -> list[str]:
        """What the run says about the scene: settings taken from where, the
        film, and integrators that do not render it."""
        return [n for s in self.results.scenes for n in (s.notes or [])]

    @property
    def checks(self) -> list[Check]:
        """The integrator's checks (``<scene>/<integrator>/<what>``)."""
        return _of(self.results.checks, self.integrator)

    @property
    def reference_checks(self) -> list[Check]:
        """The reference's own checks against its converged image."""
        return _of(self.results.checks, self.reference)

    @property
    def failed(self) -> list[Check]:
        from .validation.results import having
        return having(self.checks, "fail")

    @property
    def inconclusive(self) -> list[Check]:
        from .validation.results import having
        return having(self.checks, "inconclusive")

    @property
    def passed(self) -> bool:
        """Checks ran for the integrator and every one of them passed."""
        return bool(self.checks) and all(c.outcome == "pass" for c in self.checks)


def _of(checks, name: str) -> list:
    return [c for c in checks if c.id.split("/")[1:2] == [name]]


def compare(scene, integrator: str, *, reference: str = REFERENCE,
            profile: str | os.PathLike | Profile = "quick", plugins=(),
            out_dir: str | os.PathLike | None = None,
            cache_dir: str | os.PathLike | None = None, max_depth: int | None = None,
            rr_depth: int | None = None, hide_emitters: bool | None = None,
            defines: dict | None = None, res: int | None = None, seed_set: int = 0,
            speed: bool = False, variant: str | None = None) -> Comparison:
    """Compare ``integrator`` with ``reference`` on ``scene`` and return the
    :class:`Comparison`; it raises nothing for a failing check (the
    ``assert_…`` helpers do).

    ``scene``: a Mitsuba scene file (compared at a reduced film, by the
    profile's ``user_scenes`` rule), or a bundled scene's name (run as the
    profile says). ``profile``: "quick", "full", a profile file's path, or a
    Profile. ``plugins``: files or modules (one, or a list) that register
    the user's integrators, imported first. For a scene file only: ``max_depth``,
    ``rr_depth``, ``hide_emitters`` (over the scene's own integrator's),
    ``defines`` (its $-parameters) and ``res`` (the statistics film's longest
    side). ``out_dir``: the run directory (default: a fresh temporary folder,
    left in place for its report); ``cache_dir``: the references' cache
    (default ``$MCILLUM_CACHE`` or ~/.cache/mcillum). ``speed`` adds the
    speed-and-images stage (no verdict depends on it). ``variant``: the
    Mitsuba variant (default ``$MCILLUM_VARIANT`` or llvm_ad_rgb).

    Raises :class:`~mcillum.errors.UsageError` for a reference other than
    ``path``, a bundled name the profile does not compare, or scene-file
    settings given for a bundled scene; and what the validation raises for
    an unknown integrator, a broken scene or plugin
    (:class:`~mcillum.errors.UserError`), or a scene whose reference is
    black in every pixel, which no check could fail
    (:class:`~mcillum.errors.NoSignal`: no emitter, or none the sensor sees).
    """
    __tracebackhide__ = _hide_user_errors
    from .validation import pipeline
    from .validation.plan import profiles, scenes
    from .validation.results import layout

    if reference != REFERENCE:
        raise UsageError(f"reference '{reference}': the comparison's reference is always "
                         f"Mitsuba's path tracer ('{REFERENCE}'); to compare '{reference}' "
                         f"with it, pass it as the integrator")
    plan = profile if not isinstance(profile, (str, os.PathLike)) else \
        profiles.resolve(profile)
    scene = os.fspath(scene)
    if isinstance(plugins, (str, os.PathLike)):     # one file, not its characters
        plugins = [plugins]
    settings = {"max_depth": max_depth, "rr_depth": rr_depth, "hide_emitters": hide_emitters}
    if not scenes.is_path(scene):
        _check_bundled(scene, plan, {**settings, "defines": defines, "res": res})
    out_dir = os.fspath(out_dir) if out_dir is not None else \
        tempfile.mkdtemp(prefix="mcillum-compare-")
    results = pipeline.validate(
        plan, [scene], list(dict.fromkeys([integrator, reference])), out_dir,
        cache_dir=None if cache_dir is None else os.fspath(cache_dir), variant=variant,
        progress=False, groups=("scenes",), seed_set=seed_set, speed_stage=speed,
        plugins=tuple(os.fspath(p) for p in plugins), settings=settings, defines=defines, res=res)
    return Comparison(scene=scene, integrator=integrator, reference=reference,
                      results=results, out_dir=out_dir, report=layout.report_html(out_dir))


def _check_bundled(name: str, plan, given: dict) -> None:
    __tracebackhide__ = _hide_user_errors
    """A bundled scene runs as the profile says: it must be one of the
    profile's, and the settings of a scene file do not apply to it."""
    names = list(dict.fromkeys(r.scene for r in plan.runs))
    if name not in names:
        raise UsageError(f"scene '{name}' is no scene of profile '{plan.name}' (its scenes: "
                         f"{', '.join(names) or 'none'}); a scene file's path (an .xml) "
                         "also works")
    set_ = [k for k, v in given.items() if v is not None]
    if set_:
        raise UsageError(f"{', '.join(set_)} apply to a scene file; bundled scene '{name}' "
                         f"runs as profile '{plan.name}' says (write a profile file to "
                         "change it, or give the scene's file)")


def assert_passes(comparison: Comparison, strict: bool = False) -> None:
    """Every check of the integrator passed; returns None.

    Raises AssertionError listing each failing check's id and message (and
    any inconclusive ones), the images' folders and the report; also when no
    check of the integrator ran (it does not render the scene: the notes say
    why). With no failure but some inconclusive checks, raises
    :class:`Inconclusive` (with ``strict``: AssertionError)."""
    __tracebackhide__ = True    # (pytest shows the user's line and the message, not ours)
    _judge(comparison, comparison.checks, "checks", strict)


def assert_unbiased(comparison: Comparison, strict: bool = False) -> None:
    """The integrator's ``unbiased`` checks (its mean image against the
    reference) passed; returns None. Raises as :func:`assert_passes` does,
    for these checks only; AssertionError also for an integrator biased by
    design, which has no such check."""
    __tracebackhide__ = True
    unbiased = [c for c in comparison.checks if c.id.rsplit("/", 1)[-1] == "unbiased"]
    if comparison.checks and not unbiased:
        raise AssertionError(
            f"'{comparison.integrator}' has no unbiased check on {_where(comparison)} (an "
            "estimator biased by design gets bias_shrinks and calibrated instead): use "
            f"assert_passes\n{_paths(comparison)}")
    _judge(comparison, unbiased, "unbiased checks", strict)


def _judge(c: Comparison, checks: list, what: str, strict: bool) -> None:
    __tracebackhide__ = True
    if not checks:
        # Silence is no pass: an integrator that refuses the scene, or does
        # not define its max_depth, is left out of the run.
        notes = "; ".join(c.notes) or "none"
        raise AssertionError(f"no check of '{c.integrator}' ran on {_where(c)}: it rendered "
                             f"nothing there (the run's notes: {notes})\n{_paths(c)}")
    from .validation.results import having
    failed, unsure = having(checks, "fail"), having(checks, "inconclusive")
    if failed or (unsure and strict):
        head = (f"'{c.integrator}' failed {len(failed)} of {len(checks)} {what} against "
                f"'{c.reference}' on {_where(c)}:" if failed else
                f"'{c.integrator}': {len(unsure)} of {len(checks)} {what} inconclusive "
                f"against '{c.reference}' on {_where(c)} (strict: counted as failures):")
        lines = [head, *_listed(failed or unsure)]
        if failed and unsure:
            lines += ["inconclusive too:", *_listed(unsure)]
        raise AssertionError("\n".join([*lines, _paths(c)]))
    if unsure:
        head = (f"'{c.integrator}': {len(unsure)} of {len(checks)} {what} inconclusive "
                f"against '{c.reference}' on {_where(c)}: none failed, but the evidence "
                "cannot decide at this budget")
        raise Inconclusive("\n".join([head, *_listed(unsure), _paths(c)]))


def _where(c: Comparison) -> str:
    return "scene " + (", ".join(f"'{i}'" for i in c.scene_ids) or f"'{c.scene}'")


def _listed(checks) -> list[str]:
    return [f"  {k.id}: {k.message}" for k in checks]


def _paths(c: Comparison) -> str:
    return f"images: {', '.join(c.images) or 'none'}\nreport: {c.report}"
