"""A rejection that counts, tested again on fresh renders.

:func:`replicated_compare` and :func:`replicate` test a rejection that counts
(checks/evidence.py) again on fresh renders, at the rejected pixels (Šidák
over those, same direction) and on the image mean. A light-tailed false
alarm replicates with probability about α, a bias with the test's power; an
unseen tail would replicate, which is why only rejections that count are
replicated. Fresh pixels are tested again against the reference's own
integrator on fresh seeds (:func:`against_fresh_path`), not against the
reference the first test saw, whose own error would come back with them;
:func:`shared_with_control` reads that integrator on the same fresh seeds
where the image mean came back: what it shares is the reference's error.
"""

from __future__ import annotations

import numpy as np

from ..results import BatchTest
from .statistics import ALPHA, Comparison, Moments, compare


def replicated_compare(x, reference, fresh, alpha: float = ALPHA, decide=None) -> BatchTest:
    """:func:`compare` of renders ``x`` with ``reference``, read by
    ``decide(comparison, renders)`` (a :class:`checks.Decision`; None: every
    rejection counts). Where a rejection counts (outcome "fail"), the same
    test on ``fresh()`` renders at the rejected pixels and on the image mean:
    ``replicated`` says whether a rejection came back in the same direction
    (and, with ``decide``, the fresh renders' own reading does not excuse it).
    ``replicated`` is None when nothing needed replicating: a pass, or an
    inconclusive reading (fresh renders would miss the same tail)."""
    first = compare(x, reference, alpha)
    d = decide(first, x) if decide else None
    outcome = d.outcome if d else ("pass" if first.passed else "fail")
    out = BatchTest(passed=first.passed, pass_fraction=first.pass_fraction,
                    min_p=first.min_p, pooled_p=[float(p) for p in first.pooled_p],
                    alpha_pixel=first.alpha_pixel, test=first.summary(),
                    outcome=outcome, reason=d.reason if d else "",
                    tail_events=d.tail_events if d else 0,
                    samples_needed=d.samples_needed if d else None,
                    counted_up=d.counted_up if d else False)
    rejected = first.pixel_p < first.alpha_pixel
    out.rejected_pixels = int(rejected.sum())
    if outcome != "fail":
        return out
    replicated, pixels_again, again, excused = replicated_rejection(
        first, d, fresh(), reference, alpha, decide)
    out.replicated_pixels = int(pixels_again.sum())
    out.replicated = replicated
    out.replication_test = again.summary() + (f" ({excused})" if excused else "")
    return out


def replicated_rejection(first: Comparison, d, y, reference, alpha: float = ALPHA,
                         decide=None, control=None):
    """Did the rejections of ``first`` that counted (``d``, a
    :class:`checks.Decision`; None: all of them) come back in fresh renders
    ``y``? An upward one counts when it comes back; a downward pixel only
    where the fresh renders' tail cannot carry it; the image mean only where
    the fresh renders' own reading counts it (``decide(again, y)``); and,
    given ``control(pixels)`` (the reference's integrator on the fresh seeds,
    rendered only where a rejection came back), where only pixels came
    back, only those that ``y`` also rejects against the control's renders
    (:func:`against_fresh_path`), and otherwise none that comes back in the
    control too (:func:`shared_with_control`): it is the reference's (a
    rare event it caught, or missed) and the budget's, not the estimator's.
    Returns (replicated, pixels (H, W) that came back, the fresh comparison,
    what excused a rejection that came back: "" (nothing),
    :data:`TAIL_EXCUSE`, :data:`CONTROL_EXCUSE` or :data:`FRESH_EXCUSE`)."""
    rejected = first.pixel_p < first.alpha_pixel
    pixels = rejected if d is None or d.pixels is None else d.pixels
    pooled = (first.pooled_p < first.alpha_pooled) if d is None or d.pooled is None \
        else d.pooled
    pixels_again, pooled_again, again = replicate(first, y, reference, alpha, pixels, pooled)
    shared, excuse = False, CONTROL_EXCUSE
    if control is not None and pixels_again.any() and not pooled_again.any():
        # Only pixels came back: test them against the control's fresh renders,
        # not against the reference the first test saw (against_fresh_path).
        shared_px = pixels_again & ~against_fresh_path(first, y, control(pixels_again), alpha,
                                                       pixels_again)
        shared, excuse = bool(shared_px.any()), FRESH_EXCUSE
        pixels_again = pixels_again & ~shared_px
    elif control is not None:
        shared_px, shared_pooled = shared_with_control(first, y, control, reference, alpha,
                                                       pixels_again, pooled_again)
        shared = bool(shared_px.any() or shared_pooled.any())
        pixels_again, pooled_again = pixels_again & ~shared_px, pooled_again & ~shared_pooled
    if d is None or decide is None:
        replicated = bool(pixels_again.any() or pooled_again.any())
        return replicated, pixels_again, again, excuse if shared and not replicated else ""
    d2 = decide(again, y)
    up = pixels_again & (first.pixel_t > 0)
    down = pixels_again & (first.pixel_t < 0)
    if d2.tail_pixels is not None:          # a deficit the fresh renders' tail can carry
        down = down & ~d2.tail_pixels
    counted_pooled = d2.pooled if d2.pooled is not None else np.ones_like(pooled_again)
    replicated = bool(up.any() or down.any() or (pooled_again & counted_pooled).any())
    excused = ("" if replicated else TAIL_EXCUSE if (down.any() or pooled_again.any())
               else excuse if shared else "")
    return replicated, pixels_again, again, excused


#: What excused a rejection that came back (:func:`replicated_rejection`).
TAIL_EXCUSE = "their fireflies carry it: a tail"
CONTROL_EXCUSE = ("the reference's integrator on the same seeds differs from the "
                  "reference as much there: the reference's error, not the estimator's")
FRESH_EXCUSE = ("against the reference's integrator on fresh seeds they do not differ "
                "there: the reference's error, not the estimator's")


def against_fresh_path(first: Comparison, y, path, alpha: float, pixels) -> np.ndarray:
    """The pixels (H, W) among ``pixels`` where fresh renders ``y`` reject
    ``path``, the reference's integrator rendered on seeds neither the first
    test nor the reference used, in ``first``'s direction (Šidák over
    ``pixels``). The first test's reference is left out on purpose: where
    its own error made the rejection, fresh renders tested against it
    confirm that error again, the more surely the more samples they hold.
    Seed set 877's lone_sphere_studio: a reference pixel 4.6 of its standard
    errors high (0.2105 against 0.20885 from path at 16.8 M fresh spp) was
    "replicated" by bayesian_importance's 990 fresh renders, which read
    0.2088 (docs/measurements.md#2026-12-07-seed-set-fail-reference). Against
    path's fresh renders a rejection comes back with probability at most α
    whatever the first test saw; a bias comes back with the power of a test
    against a reference as precise as path's renders (the caller renders them
    with at least the reference's samples where it can)."""
    against = Moments.of(np.asarray(path, np.float64))
    still, _, _ = replicate(first, y, against, alpha, pixels,
                            np.zeros(first.pooled_p.shape, bool))
    return still


def shared_with_control(first: Comparison, y, control, reference, alpha: float,
                        pixels, pooled) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (H, W), image-mean channels (C,)) among ``pixels`` and
    ``pooled`` that fresh renders ``y`` reject only as ``control(at)``, the
    reference's own integrator on the same seeds, does (rendered only where
    there is something to test: at least at pixels ``at`` (H, W), or, for
    None, everywhere and the image mean; path beside a confirming batch
    cost 398 s for one pixel read). Where the control also rejects in
    ``first``'s direction, the reference is suspect there, and ``y`` is
    tested against the control instead; what that does not reject in the
    same direction is shared. A reference 1.6 % high at one
    pixel, 4.4 of its own standard errors (a user's rough plastic, GGX α
    0.01, under a sunless sky: path's rare glossy hits), makes every
    estimator there look darker however many samples it takes, and path's
    fresh renders show it."""
    none = (np.zeros_like(np.asarray(pixels, bool)), np.zeros_like(np.asarray(pooled, bool)))
    if not (np.any(pixels) or np.any(pooled)):
        return none
    path = control(None if np.any(pooled) else pixels)
    suspect_px, suspect_pooled, _ = replicate(first, path, reference, alpha, pixels, pooled)
    if not (suspect_px.any() or suspect_pooled.any()):
        return none
    against = Moments.of(np.asarray(path, np.float64))
    still_px, still_pooled, _ = replicate(first, y, against, alpha, suspect_px, suspect_pooled)
    return suspect_px & ~still_px, suspect_pooled & ~still_pooled


def replicate(first: Comparison, y, reference, alpha: float = ALPHA, pixels=None,
              pooled=None):
    """Test fresh renders ``y`` where ``first`` rejected (or at ``pixels``
    (H, W) and image-mean channels ``pooled`` (C,) only): (pixels that reject
    again in the same direction, Šidák over those tested; channels whose
    image mean rejects again in the same direction; the fresh renders' own
    :func:`compare`)."""
    rejected = first.pixel_p < first.alpha_pixel
    pixels = rejected if pixels is None else (np.asarray(pixels, bool) & rejected)
    pooled = (first.pooled_p < first.alpha_pooled) if pooled is None else \
        np.asarray(pooled, bool)
    again = compare(y, reference, alpha)
    pixels_again = np.zeros_like(rejected)
    if pixels.any():
        at = compare(y, reference, alpha, mask=pixels)
        same_way = np.sign(at.pixel_t) == np.sign(first.pixel_t)
        pixels_again = pixels & (at.pixel_p < at.alpha_pixel) & same_way
    pooled_again = pooled & (again.pooled_p < again.alpha_pooled) & \
        (np.sign(first.pooled_t) == np.sign(again.pooled_t))
    return pixels_again, pooled_again, again
