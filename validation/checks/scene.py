"""The checks of a scene comparison, per estimator: ``finite`` (no NaN/Inf),
``unbiased`` (the pooled batch-means test of all rungs, read by the rules of
evidence), ``converges`` (the slope of relMSE against spp); for an estimator
biased by design (a quadrature) ``bias_shrinks`` (its bias goes to 0: within
convergence.BIAS_LIMIT at N = 256) and ``calibrated`` (its posterior std
against the measured error) instead, from the quadrature stage. On a map
with a sun, an ``unbiased`` that the real sun left inconclusive is decided
by the sun split as a heavy-tail failure case's is (stages/sun_split.py,
:func:`split_decision`).
"""

from __future__ import annotations

import dataclasses

from ..results import Check, Convergence, EstimatorResult, Quadrature, Unbiasedness
from . import by_estimator, check, convergence, evidence
from .cases import split_line, widened_decided
from .evidence import Evidence, by_design


def judge(scene_id: str, measured: dict[str, EstimatorResult],
          found: dict[str, Evidence], quadrature: dict[str, Quadrature]) -> list[Check]:
    """Decide each estimator's unbiasedness and convergence from what the
    stages ``found`` (written into its records, every estimator's, biased by
    design or not), then every check of the scene, estimator by estimator."""
    for name, est in measured.items():
        decide_unbiasedness(est.unbiasedness, found[name])
        decide_convergence(est.convergence, found[name].tail_resolved, len(est.runs))
    return by_estimator([*finite(scene_id, measured), *unbiased(scene_id, measured),
                         *converges(scene_id, measured), *bias_shrinks(scene_id, quadrature),
                         *calibrated(scene_id, quadrature)])


def decide_unbiasedness(u: Unbiasedness, e: Evidence) -> None:
    """The verdict of :func:`evidence.unbiasedness`, or where the real sun
    left it inconclusive, of the sun split (:func:`split_decision`), written
    into ``u``."""
    d = evidence.unbiasedness(e)
    if e.sun is not None:
        u.sun = e.sun
        d = split_decision(d, e.sun, e.settled.samples)
    u.outcome, u.reason = d.outcome, d.reason
    u.rejected_up, u.rejected_down = d.rejected_up, d.rejected_down
    u.tail_events, u.samples_needed = d.tail_events, d.samples_needed
    u.relative_bias, u.half_width = d.relative_bias, d.half_width
    if e.settled is not None:
        u.looks, u.samples_per_pixel = e.settled.looks, e.settled.samples
        u.summary = e.settled.summary or u.summary


def split_decision(d: evidence.Decision, s, samples: int) -> evidence.Decision:
    """The decision ``d`` on the real map, decided by its sun split ``s``
    (a results.SunSplit) where it was inconclusive, as a heavy-tail failure
    case's (checks/cases.py): biased without the sun fails; with the sun
    widened, that test's pass or fail is the verdict; otherwise ``d``
    stands. ``samples``: per pixel, what the real map's test reached."""
    if d.outcome != "inconclusive":
        return d
    if not s.sunless_passed:
        return dataclasses.replace(d, outcome="fail", reason=(
            f"biased on the map without its sun: {s.sunless_reason}; {s.sunless_test}; "
            f"with the sun: {d.reason}"))
    if widened_decided(s):
        return dataclasses.replace(d, outcome=s.widened_outcome,
                                   reason=split_line(s, samples, d.samples_needed))
    return d


def decide_convergence(c: Convergence, resolved: bool, rungs: int | None = None) -> None:
    """The verdict of :func:`convergence.convergence_outcome`, written into
    ``c`` (``rungs``: the ladder's; ``resolved``: the ladder's tail, unless
    the sequential fit read the tail of all its renders)."""
    resolved = resolved if c.tail_resolved is None else c.tail_resolved
    c.outcome, c.message = convergence.convergence_outcome(c, resolved, rungs)
    c.passed = c.outcome == "pass"


def finite(scene_id: str, measured: dict[str, EstimatorResult]) -> list[Check]:
    """No NaN or Inf in any render of any rung."""
    out = []
    for name, est in measured.items():
        ok = all(r.nonfinite_fraction == 0 for r in est.runs)
        out.append(check(scene_id, name, "finite", ok,
                         "no NaN/Inf" if ok else "non-finite pixels in renders"))
    return out


def unbiased(scene_id: str, measured: dict[str, EstimatorResult]) -> list[Check]:
    """The verdict on each estimator's unbiasedness; not for estimators biased
    by design (their bias is measured against N instead: :func:`bias_shrinks`)."""
    out = []
    for name, est in measured.items():
        if by_design(name):
            continue
        u = est.unbiasedness
        plain = u.outcome == "pass" and not widened_decided(u.sun)
        out.append(check(scene_id, name, "unbiased", u.outcome,
                         u.summary if plain else f"{u.reason} — {u.summary}"))
    return out


def converges(scene_id: str, measured: dict[str, EstimatorResult]) -> list[Check]:
    """The error falls with spp as Monte Carlo's should
    (:func:`convergence.convergence_outcome`)."""
    return [check(scene_id, name, "converges", est.convergence.outcome, est.convergence.message)
            for name, est in measured.items() if not by_design(name)]


def bias_shrinks(scene_id: str, quadrature: dict[str, Quadrature]) -> list[Check]:
    """An estimator biased by design: its bias goes to 0
    (:func:`convergence.bias_limit_outcome`: at the largest N within
    convergence.BIAS_LIMIT of the reference's rms, and not growing with N)."""
    out = []
    for name, q in quadrature.items():
        if not q.bias or len(q.bias) < 2:
            continue
        lo, hi = q.bias[0], q.bias[-1]
        outcome, what = convergence.bias_limit_outcome(lo, hi)
        text = (f"{what}: rms bias {lo.rms_bias:.2%} ± {lo.rms_bias_se:.2%} at "
                f"N = {lo.directions}, {hi.rms_bias:.2%} ± {hi.rms_bias_se:.2%} at "
                f"N = {hi.directions} (of the reference's rms)")
        out.append(check(scene_id, name, "bias_shrinks", outcome, text))
    return out


def calibrated(scene_id: str, quadrature: dict[str, Quadrature]) -> list[Check]:
    """The posterior std predicts the error: median measured RMSE over
    predicted std inside convergence.CALIBRATED passes, outside
    convergence.MISCALIBRATED fails, between is inconclusive (naming the
    direction); exact estimators pass."""
    out = []
    for name, q in quadrature.items():
        c = q.calibration
        if c is None:
            continue
        text = (f"{c.verdict}: measured RMSE / predicted std median {c.median:.2f} "
                f"(quartiles {c.q25:.2f}–{c.q75:.2f}) over {c.pixels} pixel channels")
        outcome = ("pass" if c.verdict.startswith("exact") else
                   convergence.calibration_outcome(c.median))
        out.append(check(scene_id, name, "calibrated", outcome, text))
    return out
