"""How errors must fall: the convergence rule of a Monte Carlo estimator
(its relMSE slope against spp), and the two rules of an estimator biased by
design (a quadrature): its bias goes to 0, and its error bars are
calibrated. The stages measure (stages/scene.py, stages/quadrature.py);
checks/scene.py asks these rules for the outcome.
"""

from __future__ import annotations

import numpy as np

from ..stats import metrics
from .evidence import TAIL_EVENTS

#: The slope Monte Carlo's relMSE follows against spp.
EXPECTED_SLOPE = -1.0

#: A slope interval wider than this decides nothing.
SLOPE_WIDTH = 1.0

#: How far from the expected slope an interval may lie and still be Monte
#: Carlo: the reference's own noise, subtracted from each rung's relMSE,
#: bends the last rungs (−0.87 [−0.93, −0.80] for uniform sampling on
#: probe_spheres, a pre-asymptotic ladder).
SLOPE_TOLERANCE = 0.15


def convergence_outcome(c, resolved: bool, rungs: int | None = None) -> tuple[str, str]:
    """(outcome, message) of a :class:`results.Convergence`: pass when the
    slope's 95 % interval is at most SLOPE_WIDTH wide, lies below 0, reaches
    within SLOPE_TOLERANCE of the expected −1, and the slope itself lies
    within twice that of −1 (consistent with Monte Carlo, not merely not
    excluding it); fail when it is that narrow and lies wholly above
    −1 + SLOPE_TOLERANCE (too slow: a bias, or an error that does not fall)
    at the level a fail at its look reads (``c.low_spent``, the α spent on
    that look: stages/sequential.level), and the estimator's tail is
    resolved (``resolved``: evidence.tail_resolved; an unseen tail flattens
    a slope); inconclusive otherwise (too wide, an unresolved tail, far from
    −1, or steeper). Too wide on a ladder of three ``rungs``, the message says
    that more would narrow it: the line's t quantile has n − 2 degrees of
    freedom (12.7 at 3 rungs, 3.2 at 5), and a learner's error, falling
    faster as it learns more, is not quite a line (a user's guided_path: 1.08
    wide on 3 rungs whatever the renders per rung, 0.42 on 5;
    docs/measurements.md#2026-12-03-user-guided-path-stock-style-room). Where
    the fit was continued on more renders per rung (``c.looks``), the message
    says on how many, and an inconclusive one that more would decide says that
    its budget is spent."""
    outcome, message = _outcome(c, resolved, rungs)
    if c.looks:
        message += (f" (on {c.renders} renders per rung, after {c.looks} more "
                    + ("look)" if c.looks == 1 else "looks)"))
    if (outcome == "inconclusive" and c.budget_renders and more_renders_decide(c)
            and 2 * c.renders > c.budget_renders):
        need = renders_to_decide(c)
        message += f"; budget spent: {c.renders} renders per rung" + (
            f", and about {need:.2g} would narrow it to {SLOPE_WIDTH} if it narrows as "
            "1/√renders" if need else ", and --budget twice this one's renders twice as many")
    return outcome, message


def renders_to_decide(c) -> float:
    """Renders per rung at which an interval wider than SLOPE_WIDTH would
    be that wide if it narrowed as 1/√renders; 0 for one not too wide. A
    guess, not a bound: on a heavy tail the width read off few renders
    swings (under probe_spheres' sunrise, 16 renders per rung projected
    2.3–15× the budget's 128 for fits that 128 then decided)."""
    width = c.high - c.low
    return c.renders * (width / SLOPE_WIDTH) ** 2 if width > SLOPE_WIDTH else 0.0


def more_renders_decide(c) -> bool:
    """Whether more renders per rung may decide an undecided fit: its interval
    is finite (at least 3 rungs above the reference's share) and not wholly
    steeper than −1 − SLOPE_TOLERANCE (the reference's noise bends the top
    rungs there, and more renders of the estimator do not remove it)."""
    return (not c.exact and np.isfinite(c.low) and np.isfinite(c.high)
            and c.high >= EXPECTED_SLOPE - SLOPE_TOLERANCE)


def _outcome(c, resolved: bool, rungs: int | None) -> tuple[str, str]:
    """:func:`convergence_outcome` without the sequential fit's words."""
    if c.exact:
        return "pass", "exact (zero variance at every spp)"
    text = f"relMSE slope {c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]"
    if not np.isfinite(c.low) or not np.isfinite(c.high):
        return "inconclusive", (f"fewer than 3 rungs with an error above {metrics.RESOLVED:g}× "
                                "the reference's share")
    band = (EXPECTED_SLOPE - SLOPE_TOLERANCE, EXPECTED_SLOPE + SLOPE_TOLERANCE)
    if c.high - c.low > SLOPE_WIDTH:
        more = ""
        if rungs == 3:
            more = (": 3 rungs leave the line 1 degree of freedom, and a longer ladder "
                    "(more spp in the profile's ladder) would narrow it")
        return "inconclusive", f"{text}: wider than {SLOPE_WIDTH} (the ladder cannot decide{more})"
    if c.low > band[1]:
        spent = c.low if c.low_spent is None else c.low_spent
        if not resolved:
            return "inconclusive", (f"{text}: slower than {EXPECTED_SLOPE:+.0f}, but its tail "
                                    f"is unresolved (fewer than {TAIL_EVENTS:.0f} fireflies per "
                                    "pixel that holds one: an unseen tail flattens the slope)")
        if spent <= band[1]:
            return "inconclusive", (f"{text}: slower than {EXPECTED_SLOPE:+.0f} ± "
                                    f"{SLOPE_TOLERANCE}, but not at the level a fail at this "
                                    f"look reads (its interval reaches {spent:+.2f})")
        return "fail", f"{text}: slower than {EXPECTED_SLOPE:+.0f} ± {SLOPE_TOLERANCE}"
    if c.high < band[0]:
        return "inconclusive", (f"{text}: steeper than {EXPECTED_SLOPE:+.0f} ± "
                                f"{SLOPE_TOLERANCE} (the reference's noise, subtracted, "
                                "bends the top rungs)")
    if c.high >= 0 or abs(c.slope - EXPECTED_SLOPE) > 2 * SLOPE_TOLERANCE:
        return "inconclusive", (f"{text}: does not exclude {EXPECTED_SLOPE:+.0f} ± "
                                f"{SLOPE_TOLERANCE}, but " + ("reaches 0" if c.high >= 0 else
                                "lies far from it") + ": the ladder cannot decide")
    return "pass", f"{text}: consistent with {EXPECTED_SLOPE:+.0f} ± {SLOPE_TOLERANCE}"


#: Median RMSE / predicted std counted as calibrated (stages/quadrature.py).
CALIBRATED = (0.5, 2.0)

#: Outside this band the error bars fail: errors 3× the predicted std
#: (over-confident: the bars understate the error), or bars 10× wider than
#: the error (they say nothing). Between the bands: inconclusive.
MISCALIBRATED = (0.1, 3.0)

#: The rms bias (of the reference's rms) at the largest N that a quadrature
#: biased by design may keep: its bias must go to 0, and at N = 256 it is
#: within this, or the check fails (a weight 5 % off keeps 5 %).
BIAS_LIMIT = 0.02


def calibration_verdict(median: float) -> str:
    """calibrated, over-confident (errors larger than predicted) or
    under-confident, by the median measured RMSE over predicted std."""
    if CALIBRATED[0] <= median <= CALIBRATED[1]:
        return "calibrated"
    return "over-confident" if median > CALIBRATED[1] else "under-confident"


def calibration_outcome(median: float) -> str:
    """pass inside :data:`CALIBRATED`, fail outside :data:`MISCALIBRATED`,
    inconclusive between."""
    if CALIBRATED[0] <= median <= CALIBRATED[1]:
        return "pass"
    return "inconclusive" if MISCALIBRATED[0] <= median <= MISCALIBRATED[1] else "fail"


def bias_limit_outcome(low, high) -> tuple[str, str]:
    """(outcome, what) of a quadrature's rms bias at the smallest (``low``)
    and largest N (``high``, results.QuadratureBias): pass when the largest
    N's bias is below :data:`BIAS_LIMIT` by twice its standard error; fail
    when it is above by as much, or the bias grows with N by twice the
    standard error of the difference; inconclusive otherwise."""
    se = float(np.hypot(low.rms_bias_se, high.rms_bias_se))
    if high.rms_bias - low.rms_bias > 2 * se:
        return "fail", "the bias grows with N"
    if high.rms_bias - 2 * high.rms_bias_se > BIAS_LIMIT:
        return "fail", f"the bias at N = {high.directions} is above {BIAS_LIMIT:.0%}"
    if high.rms_bias + 2 * high.rms_bias_se <= BIAS_LIMIT:
        return "pass", f"below {BIAS_LIMIT:.0%} at N = {high.directions}"
    return "inconclusive", f"K renders cannot tell it from {BIAS_LIMIT:.0%} at N = {high.directions}"
