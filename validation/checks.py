"""Every check of a validation run, and the rules behind each verdict.

A check is a function ``(context, units, reference) -> list[Check]``: it reads
what the stages measured (on the context), the renders (``units``: spp →
estimator → :class:`~mcillum.validation.sweeps.Unit`; None after a sweep, whose
points each had their own) and the reference (likewise), and says pass or fail
with a message. Check ids are
``<scene or case>/<estimator>/<what>``. The pipeline runs the tuples below:

* :data:`SCENE` — per scene × estimator: ``finite`` (no NaN/Inf), ``unbiased``
  (the batch-means test of all rungs pooled, :mod:`statistics`),
  ``converges`` (relMSE slope interval below 0, or exact);
* :data:`CASE` — per failure case × estimator: ``refuses`` (an estimator
  refuses exactly the scenes whose content it cannot reach, by its registry
  facts) and ``stable`` (its verdict is not "biased" or "non-finite/negative");
* :data:`SWEEP` — per swept case × estimator: ``finite``.

To add a check: write the function here and add it to the tuple of the runs
it applies to.

Failure-case verdicts (:func:`case_verdict`): ``fine``; ``heavy-tailed``
(unbiased, but the error is carried by rare renders or pixels:
:func:`tails.is_heavy`); ``K too small to tell``; ``refused``; ``biased
(opt-in)``; and the two that fail ``stable``: ``biased`` and
``non-finite/negative``. A rejection of the batch-means test counts as bias
only if it replicates in K fresh renders (an unseen tail replicates with
probability about α, a bias with the test's power); a replicated rejection
on a map with a sun is excused ("K too small to tell") when the estimator
agrees with the reference on the map without the sun and either is expected
to hit the sun fewer than :data:`SUN_HITS` times per pixel in all its samples
or has no bound on that (its facts give no largest pdf: BSDF sampling, and
the next-event estimators, whose excuse is doubtful: they sample the sun
directly).
"""

from __future__ import annotations

from mcillum.integrators import registry

from . import tails
from .results import Check

#: Below this many expected direct sun hits per pixel, K renders cannot tell
#: a missed sun from a bias (see envmaps/sun.py).
SUN_HITS = 3.0

#: Verdicts that fail the ``stable`` check.
FAILING = ("biased", "non-finite/negative")


def check(ctx, name: str, what: str, passed: bool, message: str) -> Check:
    return Check(f"{ctx.id}/{name}/{what}", bool(passed), message)


# ---------------------------- Scene comparisons -------------------------------

def finite(ctx, units, reference) -> list[Check]:
    """No NaN or Inf in any render of any rung."""
    out = []
    for name, est in ctx.measured.items():
        ok = all(r.nonfinite_fraction == 0 for r in est.runs)
        out.append(check(ctx, name, "finite", ok,
                         "no NaN/Inf" if ok else "non-finite pixels in renders"))
    return out


def unbiased(ctx, units, reference) -> list[Check]:
    """The pooled batch-means test (measured by the ``measure`` stage)."""
    return [check(ctx, name, "unbiased", est.unbiasedness.passed, est.unbiasedness.summary)
            for name, est in ctx.measured.items()]


def converges(ctx, units, reference) -> list[Check]:
    """The error falls with spp: the slope's 95 % interval lies below 0, or
    the estimator has zero variance at every spp (exact)."""
    out = []
    for name, est in ctx.measured.items():
        c = est.convergence
        out.append(check(ctx, name, "converges", c.passed,
                         "exact (zero variance at every spp)" if c.exact else
                         f"relMSE slope {c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]"))
    return out


SCENE = (finite, unbiased, converges)


# ------------------------------ Failure cases ---------------------------------

def case_verdict(row) -> str:
    """The verdict of one estimator's row in a failure case (see module doc)."""
    if row.refused and row.numbers is None:
        return "refused"
    n = row.numbers
    if row.refused:                      # rendered with allow_unreachable=true
        return "biased (opt-in)"
    if n.nonfinite_values or n.negative_values:
        return "non-finite/negative"
    t = n.test
    if t.passed:
        heavy = tails.is_heavy(n.relmse.max, n.relmse.median, n.firefly_fraction)
        return "heavy-tailed" if heavy else "fine"
    if t.replicated is False:
        return "K too small to tell"
    if n.sun is not None and n.sun.sunless_passed and (
            n.sun.expected_sun_hits_per_pixel is None
            or n.sun.expected_sun_hits_per_pixel < SUN_HITS):
        return "K too small to tell"
    return "biased"


def refuses(ctx, units, reference) -> list[Check]:
    """An estimator refuses the scene exactly when its registry facts say it
    cannot reach some of the content the scene header declares."""
    out = []
    for name, row in ctx.rows.items():
        declared = not registry.facts(name).renders(ctx.info.contains)
        refused = row.refused
        if not (refused or declared):
            continue
        out.append(check(ctx, name, "refuses", refused and declared,
                         "refused as declared" if refused and declared else
                         ("refused, but its facts say it reaches "
                          f"{', '.join(ctx.info.contains) or 'everything here'}"
                          if refused else "rendered a scene it must refuse")))
    return out


def stable(ctx, units, reference) -> list[Check]:
    """Every estimator that rendered has a verdict other than biased or
    non-finite/negative."""
    return [check(ctx, name, "stable", row.verdict not in FAILING,
                  describe(row.verdict, row.numbers))
            for name, row in ctx.rows.items() if row.verdict != "refused"]


def describe(v: str, n) -> str:
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
    if v == "K too small to tell" and n.sun is not None:
        s, hits = n.sun, n.sun.expected_sun_hits_per_pixel
        text += (f"; the per-pixel test rejects ({t.rejected_pixels} px) with the sun, "
                 f"passes without it; the sun ({s.sun['solid_angle']:.2g} sr, "
                 f"{100 * s.sun_share_of_image:.0f} % of path's image) is expected "
                 + (f"{hits:.2g} direct hits per pixel in all {n.samples_per_pixel} samples"
                    if hits is not None else "to be found only through the BSDF lobe"))
    elif v == "K too small to tell":
        text += (f"; the test rejected {t.rejected_pixels} px (pooled p = "
                 f"{min(t.pooled_p):.3g}) and no rejection replicated in {n.seeds} fresh "
                 "renders")
    elif n.sun is not None:
        text += f"; {t.test}; without the sun: {n.sun.sunless_test}"
    elif t is not None:
        text += f"; {t.test}"
    return text


CASE = (refuses, stable)


# ------------------------------- Glossy sweeps --------------------------------

def sweep_finite(ctx, units, reference) -> list[Check]:
    """No NaN, Inf or negative value at any swept parameter value."""
    param, values = ctx.plan.sweep
    out = []
    for row in ctx.sweep_rows:
        ok = row.nonfinite_values == 0
        out.append(check(ctx, row.name, "finite", ok,
                         f"relMSE ×{row.growth:.3g} from {param} = {values[0]} to {values[-1]}"
                         if ok and row.growth is not None else
                         f"{row.nonfinite_values} NaN/Inf/negative values"))
    return out


SWEEP = (sweep_finite,)


def run(checks_, ctx, units, reference, by_estimator: bool = False) -> list[Check]:
    """All checks of ``checks_`` on one context: in the order of ``checks_``,
    or, ``by_estimator``, every check of one estimator before the next's."""
    found = [c for f in checks_ for c in f(ctx, units, reference)]
    if not by_estimator:
        return found
    names = list(dict.fromkeys(c.id.split("/")[1] for c in found))
    return sorted(found, key=lambda c: names.index(c.id.split("/")[1]))  # (stable)
