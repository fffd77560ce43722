"""The rules of evidence: what a statistical test's rejection means.

A statistical test says fail only where its assumptions hold. The rules
below are the one place that decides what a rejection of the batch-means
test (stats/statistics.py) means, and what a pass must show (the image
mean unbiased within ±ε); the stages measure, and ask these rules whether
to render on (stages/sequential.py). The verdicts built on them: a scene's
``unbiased`` check (scene.py) and a failure case's verdict (cases.py:
``case_verdict``, whose names are defined here). On a map with a sun
they are read with the sun in mind (checks/sun.py).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import stats

from mcillum.integrators.core import registry

from ..stats import tails

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
# * A pixel's rejection **downward** counts unless a tail can carry its
#   deficit (:func:`pixel_tail_can_carry`): no firefly anywhere, no tail;
#   otherwise each unseen event adds at most the largest event seen in the
#   image (tails.largest_event) to the pixel's sum of samples, so an
#   unbiased estimator must have missed at least deficit / that many events
#   there beyond the e it caught; if a Poisson count of e or fewer has
#   probability below the per-pixel level at that rate, the tail cannot
#   explain it. The excuse scales with the evidence: the deficit grows with
#   the samples, the largest event does not, so a sequential test that keeps
#   rendering (stages/sequential.py) ends it.
# * The image mean's rejection **downward** counts unless its tail can carry
#   the deficit (:func:`tail_can_carry`): the fireflies seen carried s of the
#   image mean in k events; for the estimator to be unbiased, its tail must
#   carry s + d (d: the deficit beyond the test's critical value), i.e. the
#   renders saw only k of about k·(s + d)/s events. If a Poisson count that
#   low has probability below the pooled test's level, the tail cannot
#   explain it.
# * A pixel's rejection does not count where **path's own renders** reject
#   there in the same direction (:func:`control_pixels`, the first look of a
#   scene run only): every estimator's K renders on a rung share their seeds,
#   so they share the pixel samples; where a pixel's value rests on events
#   too rare for the budget (a sliver of a bright edge in a dark pixel),
#   path's renders, the control, differ from the path reference as much,
#   and the difference says nothing about the estimator. For path itself
#   every pixel rejection is of that kind (path against path); its image
#   mean still counts (a reference rendered with other settings would shift
#   it). Later looks render fresh seeds, which path's renders do not share.
# * On the map with a widened sun (stages/sun_split.py) no pixel's rejection
#   **downward** counts (sun.partly_hidden): pixels that see the disc
#   only through a sliver are dark until its hits reach them; the image
#   mean decides there.
# * A rejection that does not count is **inconclusive**: the test saw a
#   difference that a tail could explain, and ``samples_needed`` says about
#   how many samples per pixel would see the tail TAIL_EVENTS times there.
# * No rejection is a **pass** only where the interval on the image mean's
#   relative bias lies inside ±ε (:func:`settle`); a wider one is
#   inconclusive: the test could not have seen a bias of ε.

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
    #: The image mean's bias relative to the reference's, per channel, and the
    #: half-width of its interval at the test's level (the largest channel's).
    relative_bias: list[float] | None = None
    half_width: float | None = None
    #: (H, W) pixels whose deficit a tail could carry (:func:`pixel_tail_can_carry`)
    tail_pixels: np.ndarray | None = None


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


def pixel_tail_can_carry(c, events: np.ndarray, samples: int,
                         event_value: float) -> np.ndarray:
    """(H, W): could a tail whose events each add at most ``event_value`` to a
    pixel's sum of ``samples`` samples, of which the renders caught
    ``events`` there, explain the pixel's deficit in :class:`statistics.
    Comparison` ``c`` (the rules above)? False everywhere without a firefly
    (``event_value`` 0)."""
    if event_value <= 0 or c.pixel_diff is None:
        return np.zeros(np.shape(c.pixel_p), bool)
    crit = stats.norm.isf(c.alpha_pixel / 2)
    deficit = np.maximum(0.0, -np.nan_to_num(c.pixel_diff) - crit * np.nan_to_num(c.pixel_se))
    needed = events + samples * deficit / event_value
    return stats.poisson.cdf(events, needed) >= c.alpha_pixel


def control_pixels(c) -> np.ndarray | None:
    """(H, W): +1 where path's own renders' comparison ``c`` rejects upward,
    −1 downward, 0 elsewhere (None: not tested)."""
    if c is None:
        return None
    return np.where(c.pixel_p < c.alpha_pixel, np.sign(c.pixel_t), 0).astype(np.int8)


def bias_outcome(c, events: np.ndarray, renders: int, samples: int,
                 carried: np.ndarray, reference_events: np.ndarray | None = None,
                 control: np.ndarray | None = None, is_control: bool = False,
                 event_value: float = 0.0) -> Decision:
    """The outcome of :class:`statistics.Comparison` ``c`` given the
    estimator's fireflies per pixel ``events`` over its ``renders`` renders
    of ``samples`` samples per pixel in all, what they ``carried`` of the
    image mean (tails.tail_events), the largest event among them
    (``event_value``, tails.largest_event), path's fireflies per pixel
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
    carry = pixel_tail_can_carry(c, events, samples, event_value)
    down_counted = down & ~carry
    n_down_counted = int(down_counted.sum())
    down = down & ~down_counted                       # the excused ones
    n_down = int(down.sum())
    pixels = (up & ~ref_tail) | down_counted

    def decide(outcome, reason, needed=None):
        return Decision(outcome=outcome, reason=reason, rejected_up=all_up,
                        rejected_down=all_down,
                        samples_needed=needed, tail_events=total, pixels=pixels,
                        pooled=high | low_counted, counted_up=bool(up_counted or pooled_up),
                        tail_pixels=carry)

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
    if n_down_counted:
        counted.append(f"darker at {n_down_counted} px"
                       + (f", more than a tail ({total} fireflies in {renders} renders) can "
                          "explain there" if heavy else f", with no firefly in {renders} renders"))
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



def decider(reference_mean: np.ndarray, reference_events: np.ndarray | None,
            control: np.ndarray | None = None, is_control: bool = False):
    """``read(comparison, batches, look)``: :func:`bias_outcome` of a
    comparison of ``batches`` ([(spp, (K, H, W, C) renders)], pooled), with
    their own fireflies as tail evidence, path's ``reference_events``, and
    path's own rejections (``control``; ``is_control``: this is path) at
    look 0 only — the ladder's seeds, which later batches do not share."""
    def read(comparison, batches, look):
        spps = [spp for spp, _ in batches]
        stack = [x for _, x in batches]
        events, k, carried = tails.tail_events(stack, reference_mean, spps)
        samples = int(sum(spp * x.shape[0] for spp, x in batches))
        first = look == 0
        return bias_outcome(comparison, events, k, samples, carried, reference_events,
                            control if first else None, is_control and first,
                            tails.largest_event(stack, reference_mean, spps))
    return read


def settle(d: Decision, c, epsilon: float, samples: int = 0) -> Decision:
    """``d`` with the image mean's relative bias and the half-width of its
    interval (:meth:`statistics.Comparison.relative_bias`) recorded; a pass
    whose interval does not lie inside ±``epsilon`` becomes inconclusive
    (the test could not have seen a bias of ε), and ``samples_needed`` says
    about how many samples per pixel (``samples`` now) would narrow it
    enough, the half-width falling as 1/√samples (at least as many: a tail
    still unseen widens it)."""
    rel, half = c.relative_bias()
    ok = np.isfinite(rel)
    if not ok.any():                        # a black image: nothing relative to say
        return d
    d.relative_bias = [float(x) for x in np.where(ok, rel, 0.0)]
    d.half_width = float(np.max(half[ok]))
    widest = float(np.max(np.abs(rel[ok]) + half[ok]))
    bias = f"image mean {_signed(rel[ok])} ± {100 * d.half_width:.2g} %"
    if d.outcome == "pass":
        if widest <= epsilon:
            d.reason = f"unbiased within ±{100 * epsilon:.3g} %: {bias}"
        else:
            d.outcome = "inconclusive"
            d.reason = (f"no bias found, but {bias} reaches {100 * widest:.2g} %, "
                        f"beyond ±{100 * epsilon:.3g} %")
            room = epsilon - float(np.max(np.abs(rel[ok])))
            if samples and room > 0:
                d.samples_needed = samples * (d.half_width / room) ** 2
    elif d.outcome == "fail":
        d.reason += f"; {bias}"
    return d


def nothing_tested(d: Decision, c) -> Decision:
    """``d``, but a pass against a reference whose image mean is zero in
    every channel (comparison ``c``) becomes a fail: the renders matched a
    black reference, so they were black too, and no bias could have been
    seen; the test could not have failed. A fail, not a refusal (an
    error): the run's other checks keep their results, and the check names
    itself (exit 1); not inconclusive, which exits 0 without ``--strict``
    and would pass vacuously again. A user's scene whose whole reference is
    black is refused before any check (stages/common.py: require_signal);
    this catches what is tested on a black image all the same (a twin's
    map, a profile file's case)."""
    ref = getattr(c, "reference_image_mean", None)
    if d.outcome != "pass" or ref is None or np.any(np.asarray(ref, np.float64) > 0):
        return d
    return dataclasses.replace(d, outcome="fail", reason=(
        "nothing tested: the reference and the renders are zero in every pixel, and black "
        "matches black whatever the estimator does; light the scene (an emitter the "
        "sensor sees) to test it"))


def _signed(rel: np.ndarray) -> str:
    """The largest relative bias in percent, with its sign."""
    x = rel[np.argmax(np.abs(rel))]
    return f"{100 * x:+.2g} %"


@dataclass(kw_only=True)
class Evidence:
    """What the stages measured of one estimator's unbiasedness on a scene:
    the pooled test of all rungs (``comparison``; None: not tested, its
    renders hold NaN/Inf), the fireflies of its renders (``events`` per
    pixel, over ``samples`` samples per pixel in all), path's fireflies
    (``reference_events``) and, once the sequential test has run
    (stages/sequential.py), its outcome (``settled``)."""

    comparison: object | None
    events: np.ndarray
    samples: int
    reference_events: np.ndarray | None = None
    #: path's own rejections on the same pixel samples (:func:`control_pixels`);
    #: ``is_control``: this is path's evidence.
    control: np.ndarray | None = None
    is_control: bool = False
    settled: Settled | None = None
    sun: object | None = None       # results.SunSplit (stages/sun_split.py)

    @property
    def tail_resolved(self) -> bool:
        """:func:`tail_resolved` of its fireflies."""
        return tail_resolved(self.events)


def tail_resolved(events: np.ndarray) -> bool:
    """No firefly in ``events`` (per pixel), or as many per pixel that holds
    one as a test needs to see a tail (:data:`TAIL_EVENTS`): one firefly is
    no evidence."""
    held = int((events > 0).sum())
    return held == 0 or events.sum() >= TAIL_EVENTS * held


@dataclass(kw_only=True)
class Settled:
    """A sequential test's end (stages/sequential.py): the decision at the
    last look, the looks taken, the samples per pixel reached, the budget,
    and whether a rejection that counted came back in a fresh batch."""

    decision: Decision
    looks: int
    samples: int
    budget: int
    replicated: bool | None = None
    replication: str = ""
    summary: str = ""               # the last look's statistics.Comparison.summary


def unbiasedness(e: Evidence) -> Decision:
    """The verdict on an estimator's unbiasedness on a scene: the sequential
    test's (:class:`Settled`); not tested (NaN/Inf in its renders) is a
    fail."""
    if e.comparison is None:
        return Decision(outcome="fail", reason="non-finite pixels")
    return e.settled.decision
