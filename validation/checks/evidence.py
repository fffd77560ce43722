"""The rules of evidence: what a statistical test's rejection means, and
every verdict rule of the checks (scene.py, cases.py).

A statistical test says fail only where its assumptions hold. The rules
below are the one place that decides what a rejection of the batch-means
test (stats/statistics.py) means; the stages measure, and ask these rules
only which rejections to test again on fresh renders (a rejection that
counts is replicated, stages/scene.py and stages/cases.py).

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

from dataclasses import dataclass

import numpy as np
from scipy import stats

from mcillum.integrators import registry

from ..stats import tails

#: Below this many expected direct sun hits per pixel, K renders cannot tell
#: a missed sun from a bias (see envmaps/sun.py).
SUN_HITS = 3.0

#: Failure-case verdicts that leave the ``stable`` check inconclusive: a
#: rejection that a heavy tail explains, and one that did not replicate.
HEAVY = "inconclusive: heavy tail"
NOT_REPLICATED = "inconclusive: not replicated"
INCONCLUSIVE = (HEAVY, NOT_REPLICATED)

#: Failure-case verdicts that fail the ``stable`` check.
FAILING = ("biased", "non-finite/negative")

#: The verdict of an estimator biased by design whose bias the test found:
#: reported with its numbers, not a failure (its bias is judged against N).
BY_DESIGN = "biased (by design)"


def by_design(name: str) -> bool:
    """Is ``name`` biased by design (a quadrature: no unbiasedness to test)?"""
    return not registry.facts(name).unbiased


# --------------------------- The rules of evidence -----------------------------
#
# A statistical test says fail only where its assumptions hold. The batch-means
# test (stats/statistics.py) assumes that K renders show each pixel's distribution;
# an estimator that finds a small bright source only by chance breaks that:
# most renders miss it, so a pixel's mean is low *and* its variance small, and
# the test rejects a correct estimator. Such a tail cannot make a mean look too
# *high* (one bright render among K raises the mean and the variance alike:
# t ≈ √(hits)), so the rules below read the direction of every rejection. The
# estimator is **heavy-tailed here** when any of its renders holds a firefly
# (stats/tails.py: a pixel brighter than 10× the reference there).
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
# * A pixel's rejection does not count where **path's own renders** reject
#   there in the same direction (:func:`control_pixels`): every estimator's
#   K renders on a rung share their seeds, so they share the pixel samples;
#   where a pixel's value rests on events too rare for the budget (a sliver
#   of a bright edge in a dark pixel), path's renders, the control, differ
#   from the path reference as much, and the difference says nothing about
#   the estimator. For path itself every pixel rejection is of that kind
#   (path against path); its image mean still counts (a reference rendered
#   with other settings would shift it).
# * A rejection that does not count is **inconclusive**: the test saw a
#   difference that a tail could explain, and ``samples_needed`` says about
#   how many samples per pixel would see the tail TAIL_EVENTS times there.

#: Tail events per pixel that a budget must expect before its per-pixel test

#: can tell a missed tail from a bias (for ``samples_needed``).
TAIL_EVENTS = 10.0


@dataclass(kw_only=True)
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


def control_pixels(c) -> np.ndarray | None:
    """(H, W): +1 where path's own renders' comparison ``c`` rejects upward,
    −1 downward, 0 elsewhere (None: not tested)."""
    if c is None:
        return None
    return np.where(c.pixel_p < c.alpha_pixel, np.sign(c.pixel_t), 0).astype(np.int8)


def bias_outcome(c, events: np.ndarray, renders: int, samples: int,
                 carried: np.ndarray, reference_events: np.ndarray | None = None,
                 control: np.ndarray | None = None, is_control: bool = False) -> Decision:
    """The outcome of :class:`statistics.Comparison` ``c`` given the
    estimator's fireflies per pixel ``events`` over its ``renders`` renders
    of ``samples`` samples per pixel in all, what they ``carried`` of the
    image mean (tails.tail_events), path's fireflies per pixel
    (``reference_events``, None: not known) and path's own rejections on
    the same pixel samples (``control``: :func:`control_pixels`; for path
    itself ``is_control``) (the rules above)."""
    rejected = c.pixel_p < c.alpha_pixel
    up, down = rejected & (c.pixel_t > 0), rejected & (c.pixel_t < 0)
    all_up, all_down = int(up.sum()), int(down.sum())        # as recorded
    shared = np.zeros_like(up)
    if is_control:
        shared = up | down
    elif control is not None:
        shared = (up & (control > 0)) | (down & (control < 0))
    n_shared = int(shared.sum())
    up, down = up & ~shared, down & ~shared
    ref_tail = np.zeros_like(up) if reference_events is None else reference_events > 0
    up_counted = int((up & ~ref_tail).sum())
    n_up, n_down = int(up.sum()), int(down.sum())      # (besides the shared ones)
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
        return Decision(outcome=outcome, reason=reason, rejected_up=all_up,
                        rejected_down=all_down,
                        samples_needed=needed, tail_events=total, pixels=pixels,
                        pooled=high | low_counted, counted_up=bool(up_counted or pooled_up))

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
    control_said = (f"at {n_shared} px path's own renders (the same pixel samples) differ "
                    "from the path reference as much: events too rare there for this budget"
                    if n_shared else "")
    if not (pooled.any() or n_up or n_down):
        return decide("inconclusive", control_said + "; more samples per pixel there would "
                      "decide")
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
    if control_said:
        why.append(control_said)
    return decide("inconclusive", "; ".join(why)
                  + f"; about {needed:.2g} samples per pixel would see the tail "
                  f"{TAIL_EVENTS:.0f}× there" + ("" if seen else " (none seen: at least)"),
                  needed)



def decider(reference_mean: np.ndarray, spp: int, reference_events: np.ndarray | None):
    """``decide(comparison, renders)``: :func:`bias_outcome` of a comparison
    of ``renders`` (K, H, W, C) at ``spp``, with their own fireflies as tail
    evidence (for replications and failure cases)."""
    def decide(comparison, renders):
        events, k, carried = tails.tail_events([renders], reference_mean)
        return bias_outcome(comparison, events, k, spp * k, carried, reference_events)
    return decide


@dataclass(kw_only=True)
class Evidence:
    """What the stages measured of one estimator's unbiasedness on a scene:
    the pooled test of all rungs (``comparison``; None: not tested, its
    renders hold NaN/Inf), the fireflies of its renders (``events`` per
    pixel over ``renders`` renders of ``samples`` samples per pixel in all,
    what they ``carried`` of the image mean), path's fireflies
    (``reference_events``) and, where a rejection counted, the same test on
    K fresh renders (``replication``)."""

    comparison: object | None
    events: np.ndarray
    renders: int
    samples: int
    carried: np.ndarray
    reference_events: np.ndarray | None = None
    #: path's own rejections on the same pixel samples (:func:`control_pixels`);
    #: ``is_control``: this is path's evidence.
    control: np.ndarray | None = None
    is_control: bool = False
    replication: "Replication | None" = None

    @property
    def heavy(self) -> bool:
        """Its renders hold a firefly: heavy-tailed here."""
        return bool(self.events.any())

    def first_reading(self) -> "Decision":
        """:func:`bias_outcome` of the pooled test (before replication)."""
        return bias_outcome(self.comparison, self.events, self.renders, self.samples,
                            self.carried, self.reference_events, self.control,
                            self.is_control)


@dataclass(kw_only=True)
class Replication:
    """The test of a rejection that counted, again on ``renders`` fresh
    renders at ``spp`` (statistics.replicated_rejection): whether it came
    back, at which pixels (H, W), and whether the fresh renders' fireflies
    excused a downward one."""

    replicated: bool
    pixels: np.ndarray
    excused: bool
    renders: int
    spp: int


def unbiasedness(e: Evidence) -> Decision:
    """The verdict on an estimator's unbiasedness on a scene: the first
    reading of its pooled test by the rules above; a fail that did not come
    back in fresh renders is inconclusive (an α-chance alarm, or a bias too
    small for K); not tested (NaN/Inf in its renders) is a fail."""
    if e.comparison is None:
        return Decision(outcome="fail", reason="non-finite pixels")
    d = e.first_reading()
    r = e.replication
    if d.outcome != "fail" or r is None:
        return d
    if not r.replicated:
        d.outcome = "inconclusive"
        d.reason += (f"; not replicated in {r.renders} fresh renders at {r.spp} spp"
                     + (" (they caught fireflies: a tail)" if r.excused else ""))
    else:
        d.reason += (f"; replicated in {r.renders} fresh renders at {r.spp} spp"
                     + (f" ({int(r.pixels.sum())} px)" if r.pixels.any() else " (image mean)"))
    return d



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



#: Median RMSE / predicted std counted as calibrated (stages/quadrature.py).
CALIBRATED = (2.0 / 3.0, 1.5)


def calibration_verdict(median: float) -> str:
    """calibrated, over-confident (errors larger than predicted) or
    under-confident, by the median measured RMSE over predicted std."""
    if CALIBRATED[0] <= median <= CALIBRATED[1]:
        return "calibrated"
    return "over-confident" if median > CALIBRATED[1] else "under-confident"


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
