"""Every check of a validation run, and the rules behind each verdict.

A check is a function ``(context, units, reference) -> list[Check]``: it reads
what the stages measured (on the context), the renders (``units``: spp →
estimator → :class:`~mcillum.validation.sweeps.Unit`; None after a sweep, whose
points each had their own) and the reference (likewise), and gives one of
three outcomes with a message: **pass**, **fail**, or **inconclusive** (the
evidence cannot decide at this budget; the run stays green unless
``--strict``). Check ids are ``<scene or case>/<estimator>/<what>``. The
pipeline runs the tuples below:

* :data:`SCENE` — per scene × estimator: ``finite`` (no NaN/Inf), ``unbiased``
  (the batch-means test of all rungs pooled, :mod:`statistics`, read by
  :func:`bias_outcome`), ``converges`` (:func:`convergence_outcome`); for
  an estimator biased by design (a quadrature) instead ``bias_shrinks``
  (from N = 16 to 256 directions) and ``calibrated`` (its posterior std
  against the measured error), from the quadrature stage (quadrature.py);
* :data:`CASE` — per failure case × estimator: ``refuses`` (an estimator
  refuses exactly the scenes whose content it cannot reach, by its registry
  facts) and ``stable`` (its verdict: fail for "biased" and
  "non-finite/negative", inconclusive for :data:`INCONCLUSIVE`);
* :data:`SWEEP` — per swept case × estimator: ``finite``.

To add a check: write the function here and add it to the tuple of the runs
it applies to. The rules of evidence (below) are the one place that decides
what a rejection of the unbiasedness test means.

Failure-case verdicts (:func:`case_verdict`): ``fine``; ``heavy-tailed``
(passes, but the error is carried by rare renders or pixels:
:func:`tails.is_heavy`); ``refused``; ``biased (opt-in)``; ``biased (by
design)`` (a quadrature's bias, reported with its numbers, not failed);
``inconclusive: heavy tail`` (every rejection is one a tail can explain; or,
on a map with a sun, a rejection that replicated but not on the map without
the sun, by an estimator whose renders caught fireflies and which is expected
to hit the sun fewer than :data:`SUN_HITS` times per pixel by its largest pdf,
or has no such bound; or a sun no render is expected to hit anywhere);
``inconclusive: not replicated`` (a rejection that counts did not come back
in K fresh renders: an α-chance alarm, or a bias too small for K); and the
two that fail: ``biased`` (a rejection that counts and replicated and no sun
explains, or a bias on the map without its sun, tested by the same rules) and
``non-finite/negative``. Replication can decide only where the test's
assumptions hold: fresh renders miss an unseen tail in the same pixels, so an
inconclusive reading is not replicated, and only the rejections that counted
are tested again. An estimator without fireflies gets no sun excuse (a
firefly clamp is exactly that), whatever its pdf, unless no render is
expected to hit the sun anywhere; an upward rejection never gets one (a
missed sun only darkens).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from mcillum.integrators import registry

from . import tails
from .results import Check

#: Below this many expected direct sun hits per pixel, K renders cannot tell
#: a missed sun from a bias (see envmaps/sun.py).
SUN_HITS = 3.0

#: Failure-case verdicts that leave the ``stable`` check inconclusive: a
#: rejection that a heavy tail explains, and one that did not replicate.
HEAVY = "inconclusive: heavy tail"
NOT_REPLICATED = "inconclusive: not replicated"
INCONCLUSIVE = (HEAVY, NOT_REPLICATED)

#: Verdicts that fail the ``stable`` check.
FAILING = ("biased", "non-finite/negative")


def check(ctx, name: str, what: str, outcome, message: str) -> Check:
    """A check with ``outcome`` "pass", "fail" or "inconclusive" (or a bool:
    pass or fail)."""
    if isinstance(outcome, (bool, np.bool_)):
        outcome = "pass" if outcome else "fail"
    return Check(f"{ctx.id}/{name}/{what}", outcome != "fail", message, outcome)


# --------------------------- The rules of evidence -----------------------------
#
# A statistical test says fail only where its assumptions hold. The batch-means
# test (statistics.py) assumes that K renders show each pixel's distribution;
# an estimator that finds a small bright source only by chance breaks that:
# most renders miss it, so a pixel's mean is low *and* its variance small, and
# the test rejects a correct estimator. Such a tail cannot make a mean look too
# *high* (one bright render among K raises the mean and the variance alike:
# t ≈ √(hits)), so the rules below read the direction of every rejection. The
# estimator is **heavy-tailed here** when any of its renders holds a firefly
# (tails.py: a pixel brighter than 10× the reference there).
#
# * A rejection **upward** (estimator brighter) counts as bias — at a pixel,
#   unless path's own renders caught a firefly there (the reference, path's
#   mean, may lack an unseen tail there).
# * A pixel's rejection **downward** counts as bias only if the estimator is
#   not heavy-tailed here.
# * The image mean's rejection **downward** counts if the estimator is not
#   heavy-tailed, or if its tail cannot carry the deficit
#   (:func:`tail_can_carry`): the fireflies seen carried s of the image mean
#   in k events; for the estimator to be unbiased, its tail must carry
#   s + d (d: the deficit beyond the test's critical value), i.e. the renders
#   saw only k of about k·(s + d)/s events. If a Poisson count that low has
#   probability below the pooled test's level, the tail cannot explain it.
# * A rejection that does not count is **inconclusive**: the test saw a
#   difference that a tail could explain, and ``samples_needed`` says about
#   how many samples per pixel would see the tail TAIL_EVENTS times there.

#: Tail events per pixel that a budget must expect before its per-pixel test
#: can tell a missed tail from a bias (for ``samples_needed``).
TAIL_EVENTS = 10.0


@dataclass
class Decision:
    """The outcome of one unbiasedness test under the rules above."""

    outcome: str                    # pass | fail | inconclusive
    reason: str                     # one line: which rejections counted, and why
    rejected_up: int = 0            # pixels whose smallest-p channel rejects upward
    rejected_down: int = 0
    samples_needed: float | None = None   # samples per pixel (inconclusive only)
    tail_events: int = 0            # fireflies in the estimator's renders
    pixels: np.ndarray | None = None      # (H, W) the pixel rejections that counted
    pooled: np.ndarray | None = None      # (C,) the image-mean rejections that counted
    counted_up: bool = False        # a rejection upward counted (no tail excuses it)


def tail_can_carry(c, events: int, carried: np.ndarray) -> np.ndarray:
    """Per channel: could a tail that carried ``carried`` of the image mean in
    ``events`` fireflies be under-sampled enough to explain the image mean's
    deficit in :class:`statistics.Comparison` ``c`` (the rules above)?"""
    if events == 0:
        return np.zeros_like(np.asarray(c.pooled_t), bool)
    crit = stats.norm.isf(c.alpha_pooled / 2)
    deficit = np.maximum(0.0, -np.asarray(c.pooled_diff) - crit * np.asarray(c.pooled_se))
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = np.where(carried > 0, events * (carried + deficit) / carried, np.inf)
    return stats.poisson.cdf(events, expected) >= c.alpha_pooled


def bias_outcome(c, events: np.ndarray, renders: int, samples: int,
                 carried: np.ndarray, reference_events: np.ndarray | None = None) -> Decision:
    """The outcome of :class:`statistics.Comparison` ``c`` given the
    estimator's fireflies per pixel ``events`` over its ``renders`` renders
    of ``samples`` samples per pixel in all, what they ``carried`` of the
    image mean (tails.tail_events), and path's fireflies per pixel
    (``reference_events``, None: not known) (the rules above)."""
    rejected = c.pixel_p < c.alpha_pixel
    up, down = rejected & (c.pixel_t > 0), rejected & (c.pixel_t < 0)
    ref_tail = np.zeros_like(up) if reference_events is None else reference_events > 0
    up_counted = int((up & ~ref_tail).sum())
    n_up, n_down = int(up.sum()), int(down.sum())
    pooled = np.asarray(c.pooled_p) < c.alpha_pooled
    high = pooled & (np.asarray(c.pooled_t) > 0)            # per channel
    low = pooled & (np.asarray(c.pooled_t) < 0)
    total = int(events.sum())
    heavy = total > 0
    low_counted = low & ~tail_can_carry(c, total, np.asarray(carried, np.float64))
    pooled_up, pooled_down = bool(high.any()), bool(low.any())
    pooled_counted = bool(low_counted.any())
    pixels = (up & ~ref_tail) | (down if not heavy else np.zeros_like(down))

    def decide(outcome, reason, needed=None):
        return Decision(outcome, reason, n_up, n_down, needed, total, pixels,
                        high | low_counted, bool(up_counted or pooled_up))

    if not (pooled.any() or rejected.any()):
        return decide("pass", "no rejection")
    counted = []
    if pooled_up or up_counted:
        counted.append("brighter than the reference"
                       + (" (image mean)" if pooled_up else f" at {up_counted} px"))
    if pooled_counted:
        counted.append("image mean darker than the reference"
                       + (f", more than its tail ({total} fireflies in {renders} renders) "
                          "can explain" if heavy else ""))
    if n_down and not heavy:
        counted.append(f"darker at {n_down} px, with no firefly in {renders} renders")
    if counted:
        return decide("fail", "; ".join(counted))
    # Every rejection is one a tail can explain: how many samples would see it?
    where = down if n_down else np.ones_like(down)
    seen = int(events[where].sum())
    needed = samples * TAIL_EVENTS * int(where.sum()) / max(seen, 1)
    why = []
    if pooled_down or n_down:
        why.append("darker" + (" image mean" if pooled_down else "")
                   + (" and" if pooled_down and n_down else "")
                   + (f" at {n_down} px" if n_down else "")
                   + f", but heavy-tailed ({total} fireflies in {renders} renders"
                   + (f", {seen} at those pixels" if n_down else "") + ")")
    if n_up:
        why.append(f"brighter at {n_up} px, where path's own renders caught fireflies "
                   "(the reference may lack its tail there)")
    return decide("inconclusive", "; ".join(why)
                  + f"; about {needed:.2g} samples per pixel would see the tail "
                  f"{TAIL_EVENTS:.0f}× there" + ("" if seen else " (none seen: at least)"),
                  needed)


#: The slope Monte Carlo's relMSE follows against spp.
EXPECTED_SLOPE = -1.0

#: A slope interval wider than this decides nothing.
SLOPE_WIDTH = 1.0

#: How far above the expected slope an interval must lie to fail: a slope of
#: −0.99 ± 0.005 is Monte Carlo (the reference's own noise, subtracted from
#: each rung's relMSE, bends the last rungs by about that much).
SLOPE_TOLERANCE = 0.15


def convergence_outcome(c, heavy: bool) -> tuple[str, str]:
    """(outcome, message) of a :class:`results.Convergence`: fail when the
    slope's 95 % interval lies above the expected slope (by more than
    SLOPE_TOLERANCE) and is at most SLOPE_WIDTH wide (too slow for Monte
    Carlo: a bias, or an error that does not fall), unless the estimator is
    heavy-tailed (an unseen tail makes low-spp errors look small:
    pre-asymptotic); pass when the interval lies below 0 otherwise;
    inconclusive when it is too wide to say either."""
    if c.exact:
        return "pass", "exact (zero variance at every spp)"
    text = f"relMSE slope {c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]"
    if not np.isfinite(c.low) or not np.isfinite(c.high):
        return "inconclusive", "fewer than 3 rungs with an error above the reference's"
    width = c.high - c.low
    if c.low > EXPECTED_SLOPE + SLOPE_TOLERANCE:
        if width > SLOPE_WIDTH:
            return "inconclusive", f"{text}: too wide (> {SLOPE_WIDTH}) to decide"
        if heavy:
            return "inconclusive", (f"{text}: slower than {EXPECTED_SLOPE:+.0f}, but "
                                    "heavy-tailed (an unseen tail flattens the slope)")
        return "fail", f"{text}: slower than {EXPECTED_SLOPE:+.0f}"
    if c.high < 0:
        return "pass", text
    return "inconclusive", (f"{text}: contains 0 and does not lie more than "
                            f"{SLOPE_TOLERANCE} above {EXPECTED_SLOPE:+.0f}: cannot decide")


# ---------------------------- Scene comparisons -------------------------------

def finite(ctx, units, reference) -> list[Check]:
    """No NaN or Inf in any render of any rung."""
    out = []
    for name, est in ctx.measured.items():
        ok = all(r.nonfinite_fraction == 0 for r in est.runs)
        out.append(check(ctx, name, "finite", ok,
                         "no NaN/Inf" if ok else "non-finite pixels in renders"))
    return out


def _by_design(name: str) -> bool:
    """Is ``name`` biased by design (a quadrature: no unbiasedness to test)?"""
    return not registry.facts(name).unbiased


def unbiased(ctx, units, reference) -> list[Check]:
    """The pooled batch-means test (measured by the ``measure`` stage), read
    by :func:`bias_outcome`; not for estimators biased by design (their bias
    is measured against N instead: :func:`bias_shrinks`)."""
    out = []
    for name, est in ctx.measured.items():
        if _by_design(name):
            continue
        u = est.unbiasedness
        out.append(check(ctx, name, "unbiased", u.outcome,
                         u.summary if u.outcome == "pass" else f"{u.reason} — {u.summary}"))
    return out


def converges(ctx, units, reference) -> list[Check]:
    """The error falls with spp as Monte Carlo's should
    (:func:`convergence_outcome`)."""
    return [check(ctx, name, "converges", est.convergence.outcome, est.convergence.message)
            for name, est in ctx.measured.items() if not _by_design(name)]


def bias_shrinks(ctx, units, reference) -> list[Check]:
    """An estimator biased by design: its rms bias at N = 256 directions is
    below that at N = 16 by more than twice the standard error of the
    difference (pass), above it by as much (fail), else inconclusive."""
    out = []
    for name, q in ctx.quadrature.items():
        if not q.bias or len(q.bias) < 2:
            continue
        lo, hi = q.bias[0], q.bias[-1]
        se = math.hypot(lo.rms_bias_se, hi.rms_bias_se)
        text = (f"rms bias {lo.rms_bias:.2%} ± {lo.rms_bias_se:.2%} at N = {lo.directions}, "
                f"{hi.rms_bias:.2%} ± {hi.rms_bias_se:.2%} at N = {hi.directions} "
                f"(of the reference's rms)")
        if lo.rms_bias - hi.rms_bias > 2 * se:
            outcome = "pass"
        elif hi.rms_bias - lo.rms_bias > 2 * se:
            outcome, text = "fail", "the bias grows with N: " + text
        else:
            outcome, text = "inconclusive", "no difference K renders resolve: " + text
        out.append(check(ctx, name, "bias_shrinks", outcome, text))
    return out


def calibrated(ctx, units, reference) -> list[Check]:
    """The posterior std predicts the error: median measured RMSE over
    predicted std within quadrature.CALIBRATED (pass); otherwise
    inconclusive, naming the direction (a prior that does not fit the
    lighting is a finding about the scene, not a broken estimator)."""
    out = []
    for name, q in ctx.quadrature.items():
        c = q.calibration
        if c is None:
            continue
        text = (f"{c.verdict}: measured RMSE / predicted std median {c.median:.2f} "
                f"(quartiles {c.q25:.2f}–{c.q75:.2f}) over {c.pixels} pixel channels")
        ok = c.verdict == "calibrated" or c.verdict.startswith("exact")
        out.append(check(ctx, name, "calibrated", "pass" if ok else "inconclusive", text))
    return out


SCENE = (finite, unbiased, converges, bias_shrinks, calibrated)


# ------------------------------ Failure cases ---------------------------------

#: The verdict of an estimator biased by design whose bias the test found:
#: reported with its numbers, not a failure (its bias is judged against N).
BY_DESIGN = "biased (by design)"


def case_verdict(row, pixels: int) -> str:
    """The verdict of one estimator's row in a failure case of ``pixels``
    pixels (see the module doc); an estimator biased by design gets
    :data:`BY_DESIGN` where the others would get "biased"."""
    verdict = _case_verdict(row, pixels)
    return BY_DESIGN if verdict == "biased" and _by_design(row.name) else verdict


def _case_verdict(row, pixels: int) -> str:
    if row.refused and row.numbers is None:
        return "refused"
    n = row.numbers
    if row.refused:                      # rendered with allow_unreachable=true
        return "biased (opt-in)"
    if n.nonfinite_values or n.negative_values:
        return "non-finite/negative"
    t, sun_ = n.test, n.sun
    if t.outcome == "pass":
        heavy = tails.is_heavy(n.relmse.max, n.relmse.median, n.firefly_fraction)
        return "heavy-tailed" if heavy else "fine"
    if sun_ is not None and not sun_.sunless_passed:
        return "biased"                  # biased without the sun, by the same rules
    if t.outcome == "inconclusive":
        return HEAVY
    if not t.replicated:
        return NOT_REPLICATED
    if sun_ is None or t.counted_up:
        return "biased"                  # (a missed sun only ever darkens)
    hits = sun_.expected_sun_hits_per_pixel
    if hits is not None and hits * pixels < SUN_HITS:
        return HEAVY                     # a sun no render is expected to hit anywhere
    if t.tail_events > 0 and (hits is None or hits < SUN_HITS):
        # not biased without the sun, heavy-tailed with it, and not expected
        # to hit the sun SUN_HITS times per pixel (or no bound on its pdf)
        return HEAVY
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
    return [check(ctx, name, "stable",
                  "fail" if row.verdict in FAILING else
                  "inconclusive" if row.verdict in INCONCLUSIVE else "pass",
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
    if v == HEAVY:
        text += f"; {t.reason}"
        if n.sun is not None:
            s, hits = n.sun, n.sun.expected_sun_hits_per_pixel
            text += (f"; without the sun: {s.sunless_outcome or 'not biased'}; the sun "
                     f"({s.sun['solid_angle']:.2g} sr, {100 * s.sun_share_of_image:.0f} % of "
                     "path's image) is expected "
                     + (f"{hits:.2g} direct hits per pixel in all {n.samples_per_pixel} samples"
                        if hits is not None else
                        "to be hit an unknown number of times (its facts give no largest pdf)"))
    elif v == NOT_REPLICATED:
        text += (f"; {t.reason}; no rejection replicated in {n.seeds} fresh renders "
                 f"({t.rejected_pixels} px rejected, pooled p = {min(t.pooled_p):.3g})")
    elif v in ("biased", BY_DESIGN) and n.sun is not None and not n.sun.sunless_passed:
        text += f"; biased without the sun too: {n.sun.sunless_reason}; {n.sun.sunless_test}"
    elif t is not None:
        text += f"; {t.reason + ' — ' if t.reason else ''}{t.test}"
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
