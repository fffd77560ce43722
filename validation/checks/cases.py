"""The checks of the failures group: per case × estimator ``refuses`` (an
estimator refuses exactly the scenes whose content it cannot reach, by its
registry facts) and ``stable`` (its verdict, :func:`case_verdict`:
fail for "biased" and "non-finite/negative", inconclusive for
:data:`evidence.INCONCLUSIVE`); per parameter sweep × estimator ``finite``.

Failure-case verdicts (:func:`case_verdict`): ``fine``; ``heavy-tailed``
(passes, but the error is carried by rare renders or pixels:
:func:`tails.is_heavy`); ``refused``; ``biased (opt-in)``; ``biased (by
design)`` (a quadrature's bias, reported with its numbers, not failed);
``biased`` (a rejection that counts by the rules of evidence, confirmed on a
fresh batch, or a bias on the map without its sun or with it widened, tested
by the same rules); ``non-finite/negative``. Where the sequential test's
budget is spent on a real sun (stages/sequential.py), the widened twin
decides (its pass: ``heavy-tailed``; its fail: ``biased``); otherwise
``inconclusive: heavy tail`` (every rejection is one a tail can explain at
the samples reached, or no rejection but an interval on the relative bias
wider than ±ε) or ``inconclusive: not replicated`` (a rejection that counted
did not come back on a fresh batch, and no budget was left to go on).
"""

from __future__ import annotations

from mcillum.integrators.core import registry

from ..results import CaseRow, Check, Sweep, SweepRow
from . import check
from ..stats import tails
from .evidence import BY_DESIGN, FAILING, HEAVY, INCONCLUSIVE, NOT_REPLICATED, by_design


def judge(case_id: str, rows: dict[str, CaseRow], contains: tuple[str, ...],
          pixels: int) -> list[Check]:
    """Each row's verdict (:func:`case_verdict`, written into the
    row), then the case's checks: ``contains`` is what the scene header
    declares, ``pixels`` the image's pixel count."""
    for row in rows.values():
        row.verdict = case_verdict(row, pixels)
    return [*refuses(case_id, rows, contains), *stable(case_id, rows)]


def refuses(case_id: str, rows: dict[str, CaseRow], contains: tuple[str, ...]) -> list[Check]:
    """An estimator refuses the scene exactly when its registry facts say it
    cannot reach some of the content the scene header declares."""
    out = []
    for name, row in rows.items():
        declared = not registry.facts(name).renders(contains)
        refused = row.refused
        if not (refused or declared):
            continue
        out.append(check(case_id, name, "refuses", refused and declared,
                         "refused as declared" if refused and declared else
                         ("refused, but its facts say it reaches "
                          f"{', '.join(contains) or 'everything here'}"
                          if refused else "rendered a scene it must refuse")))
    return out


def stable(case_id: str, rows: dict[str, CaseRow]) -> list[Check]:
    """Every estimator that rendered has a verdict other than biased or
    non-finite/negative."""
    return [check(case_id, name, "stable",
                  "fail" if row.verdict in FAILING else
                  "inconclusive" if row.verdict in INCONCLUSIVE else "pass",
                  verdict_line(row.verdict, row.numbers))
            for name, row in rows.items() if row.verdict != "refused"]


def verdict_line(v: str, n) -> str:
    """One line for a failure-case verdict and its numbers."""
    if v == "non-finite/negative":
        return (f"{n.nonfinite_values} NaN/Inf and {n.negative_values} negative values in "
                "the renders")
    if v == "biased (opt-in)":
        return (f"allow_unreachable=true: image mean {100 * n.image_mean_ratio:.1f} % of "
                f"path's ({100 * n.missing_fraction:.1f} % missing)")
    rel, t = n.relmse, n.test
    text = (f"{v}: relMSE median {rel.median:.3g}, p99 {rel.p99:.3g}, max {rel.max:.3g}; "
            f"fireflies {100 * n.firefly_fraction:.3f} %")
    if v == HEAVY:
        text += f"; {t.reason}"
        if n.sun is not None:
            s, hits = n.sun, n.sun.expected_sun_hits_per_pixel
            text += (f"; without the sun: {s.sunless_outcome or 'not biased'}; the sun "
                     f"({s.sun['solid_angle']:.2g} sr, {100 * s.sun_share_of_image:.0f} % of "
                     "path's image) "
                     + (f"allows at most {hits:.2g} direct hits per pixel in all "
                        f"{t.samples_per_pixel or n.samples_per_pixel} samples"
                        if hits is not None else
                        "is hit an unknown number of times (its facts give no largest pdf)"))
            if s.widened_outcome:
                text += f"; {widened_words(s)}"
    elif v == NOT_REPLICATED:
        text += (f"; {t.reason} ({t.rejected_pixels} px rejected, pooled p = "
                 f"{min(t.pooled_p):.3g})")
    elif v in ("biased", BY_DESIGN) and n.sun is not None and not n.sun.sunless_passed:
        text += f"; biased without the sun too: {n.sun.sunless_reason}; {n.sun.sunless_test}"
    elif widened_decided(n.sun):
        text += "; " + split_line(n.sun, t.samples_per_pixel, t.samples_needed)
    elif t is not None:
        text += f"; {t.reason + ' — ' if t.reason else ''}{t.test}"
    return text


def widened_decided(s) -> bool:
    """Did the widened sun's test decide (pass or fail) a case whose sun split
    is ``s`` (a results.SunSplit, or None)?"""
    return s is not None and s.widened_outcome in ("pass", "fail")


def widened_words(s) -> str:
    """The widened sun's test of sun split ``s`` in words (also the report's)."""
    return (f"with the sun widened to {s.widened['solid_angle']:.2g} sr at its own radiance: "
            f"{'BIASED: ' if s.widened_outcome == 'fail' else ''}{s.widened_reason}")


def split_line(s, samples: int, needed: float | None = None) -> str:
    """How the split map decided a test the real sun left undecided at
    ``samples`` per pixel (``needed``: about how many would have decided)."""
    real = (f"the real sun ({s.sun['solid_angle']:.2g} sr, {100 * s.sun_share_of_image:.0f} % "
            f"of path's image) is hit too rarely to decide in "
            f"{samples} samples per pixel"
            + (f" (about {needed:.2g} would)" if needed else ""))
    if s.widened_outcome == "fail":
        return f"{real}; {widened_words(s)}"
    return (f"decided on the split map: {real}; without it {s.sunless_reason}; "
            f"{widened_words(s)}")


def judge_sweep(case_id: str, rows: list[SweepRow], sweep: Sweep) -> list[Check]:
    """A parameter sweep's checks: ``finite`` per estimator."""
    return sweep_finite(case_id, rows, sweep)


def sweep_finite(case_id: str, rows: list[SweepRow], sweep: Sweep) -> list[Check]:
    """No NaN, Inf or negative value at any swept parameter value."""
    values = sweep.values
    out = []
    for row in rows:
        ok = row.nonfinite_values == 0
        out.append(check(case_id, row.name, "finite", ok,
                         f"relMSE ×{row.growth:.3g} from {sweep.param} = {values[0]} to "
                         f"{values[-1]}" if ok and row.growth is not None else
                         f"{row.nonfinite_values} NaN/Inf/negative values"))
    return out


def case_verdict(row, pixels: int) -> str:
    """The verdict of one estimator's row in a failure case of ``pixels``
    pixels (see the module doc); an estimator biased by design gets
    :data:`BY_DESIGN` where the others would get "biased"."""
    verdict = _case_verdict(row, pixels)
    return BY_DESIGN if verdict == "biased" and by_design(row.name) else verdict


def _case_verdict(row, pixels: int) -> str:
    if row.refused and row.numbers is None:
        return "refused"
    n = row.numbers
    if row.refused:                      # rendered with allow_unreachable=true
        return "biased (opt-in)"
    if n.nonfinite_values or n.negative_values:
        return "non-finite/negative"
    t, sun_ = n.test, n.sun
    if sun_ is not None and not sun_.sunless_passed:
        return "biased"                  # biased without the sun, by the same rules
    if t.outcome == "pass":
        heavy = tails.is_heavy(n.relmse.max, n.relmse.median, n.firefly_fraction)
        return "heavy-tailed" if heavy else "fine"
    if t.outcome == "fail":
        return "biased"                  # counted by the rules, confirmed on a fresh batch
    # the budget is spent on the real sun: the split map decides where it can
    # (without the sun passed; with it widened, envmaps/sun.py)
    widened = sun_.widened_outcome if sun_ is not None else None
    if widened == "fail":
        return "biased"
    if widened == "pass":
        return "heavy-tailed"
    return NOT_REPLICATED if t.replicated is False else HEAVY
