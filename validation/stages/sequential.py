"""Sequential tests: a check that its first renders cannot decide renders
more, in growing batches, until it decides or its budget is spent.

Look 0 is the stage's own renders (a scene's ladder, a failure case's K
seeds). While the rules of evidence (checks/evidence.py) read the pooled
test as inconclusive — a rejection an unseen tail can explain, or no
rejection but an interval on the image mean's relative bias wider than ±ε —
a batch of fresh renders (the context's ``sequential`` seed stream, one
block per look) doubles the samples per pixel, and the test runs again on
everything rendered so far. Fireflies stop excusing a deficit once the
samples make them common: the rules weigh the deficit against the largest
event seen, and the deficit grows with the samples.

**Anytime-valid.** Looking after every batch would inflate the false-fail
rate of a test at a fixed level; look j is tested at

    α_j = α · 6 / (π² (j + 1)²)          (Σ_j α_j = α)

so that, by the union bound, a correct estimator fails at *some* look with
probability at most α however many looks the budget allows (Bonferroni
α-spending). Within a look the level is split as before (statistics.py:
α_j/2 over the image mean's channels, α_j/2 Šidák over pixel channels).

**A fail is confirmed.** A rejection that counts is tested again on the
next batch alone (fresh seeds, :data:`CONFIRM` × the samples so far), at
the rejected pixels and on the image mean (replication.replicated_rejection):
if it comes back, fail; if not, that batch joins the pool and the test goes
on. A fail that rests on darker pixels alone, with no firefly in the
renders, is confirmed on :data:`CONFIRM_UNSEEN` × the samples at the fewest
spp a seed block allows (:func:`confirming_batch`): a tail the first renders
missed shows there as fireflies, which the rules weigh. Where only pixels
came back in it, they are tested again against path on the batch's seeds,
with at least the reference's samples there (:func:`_beside`), not against
the reference the first test saw. The confirming batch is rendered
even past the budget; a fail it does not confirm, with the budget spent, is
inconclusive. Far past the reference (:data:`PATH_FIRST`) path renders
the confirming seeds first, in windows around the pixels a fail rests on;
where it shows the reference off there, the estimator's batch is not
rendered. An estimator biased by design is not confirmed: its fail is
the label of a failure case's row, and a scene comparison reads only its
first look (it has no ``unbiased`` check).

**The budget** is a multiple of the first look's samples per pixel (the
profile's ``[sequential]``, ``mcillum validate --budget``), and at most
:data:`REFERENCE_LEAD` × the reference's; at its end an inconclusive
reading says the samples per pixel reached and, where a tail is to blame,
about how many would see it.

**Where a split decides.** On a map with a sun, a test whose estimator the
sun split will test without the sun and with it widened
(stages/sun_split.py) stops as soon as its reading needs more than
:data:`BEYOND_BUDGET` × its budget to decide (``split_follows``): the
budget cannot decide it, the split does, each twin's test with a budget of
its own.
"""

from __future__ import annotations

import math

import numpy as np

from ..checks import evidence
from ..plan import seeds
from ..run import stacks
from ..stats import replication, statistics
from . import common
from .common import REFERENCE, kept_file

#: Renders per batch at most (a case's 64 seeds become batches of 16 renders).
BATCH_RENDERS = 16

#: A confirming batch has this many times the samples rendered so far: a
#: tail both the first renders and a batch as large missed (a rare path
#: worth a few times its pixel, below the firefly threshold) shows in one
#: this much larger, and a bias stays (emitter_sampling on the sunrise probe,
#: seed set 3: two pixels missed at 1024 samples, agreed at 16 × 16384).
CONFIRM = 4

#: A fail that rests only on darker pixels, with no firefly in the renders,
#: rests on "no firefly, no tail". A pixel can hold a tail that K renders
#: show as no firefly, and a confirming batch at higher spp averages each
#: event below the firefly threshold, so it confirms whenever it misses the
#: tail too (seed set 71: cosine sampling on probe_spheres_interior's sunless
#: map, one pixel of the rough gold sphere;
#: docs/measurements.md#2026-12-04-confirming-fail-tail-would). Such a fail is
#: confirmed on this many times the samples, rendered at as few spp as a seed
#: block's renders allow: an event is a firefly there, and the rules weigh it.
#: Not at the first look's spp where that is more: a sun split's first look is
#: the ladder's top rung alone, and there cosine sampling's glossy hits at a
#: silhouette pixel of glossy_phong stayed at 1.5-6.7× the reference in 256
#: renders of 1 024 spp, and a correct estimator failed (seed set 218;
#: docs/measurements.md#2026-12-06-guided-path-learns-sums-records). A darker
#: image mean is what a pdf off, a missing light or a clamp shows: its
#: confirmation stays at CONFIRM.
CONFIRM_UNSEEN = 16

#: Renders in one batch at most: a block of the sequential seed streams.
MAX_RENDERS = min(seeds.STREAMS[s].size
                  for s in ("sequential", "sunless_sequential", "widened_sequential"))


def confirming_batch(d, batches, k: int) -> tuple[int, int]:
    """(spp, renders) of the batch that confirms fail ``d`` read on
    ``batches``, the K = ``k`` renders of a look: CONFIRM × the samples so
    far in K renders; or, for a fail that rests on darker pixels alone (not
    the image mean), with no firefly in the renders, :data:`CONFIRM_UNSEEN`
    × the samples at the fewest spp a seed block (:data:`MAX_RENDERS`
    renders) can hold, at least K renders."""
    total = samples(batches)
    if d.tail_events or d.counted_up or (d.pooled is not None and np.any(d.pooled)):
        return max(1, math.ceil(CONFIRM * total / k)), k
    wanted = CONFIRM_UNSEEN * total
    spp = max(1, math.ceil(wanted / MAX_RENDERS))
    return spp, max(k, math.ceil(wanted / spp))


def level(alpha: float, look: int) -> float:
    """The level of look ``look`` (0 = the stage's own renders): α·6/(π²(j+1)²)."""
    return alpha * 6.0 / (math.pi ** 2 * (look + 1) ** 2)


def samples(batches) -> int:
    """Samples per pixel in all of ``batches`` [(spp, (K, H, W, C))]."""
    return int(sum(spp * x.shape[0] for spp, x in batches))


def batch(ctx, name: str, look: int, spp: int, k: int,
          tag: str = "") -> tuple[int, np.ndarray]:
    """(spp, K renders (K, H, W, 3)) of estimator ``name``: look ``look``'s
    batch, from block ``look`` of the context's sequential stream; kept
    (under ``tag`` instead of the name where given)."""
    stream = ctx.streams["sequential"]
    images = stacks.kept(ctx, kept_file(ctx, f"{stream}-{look}-{tag or name}"),
                         f"{stream}[{look}]",
                         {name: ctx.integrators[name]}, {name: spp}, k,
                         ctx.run.stream(stream, look).take(k), label=ctx.label)[name].images
    return spp, images[..., :3]


def renderer(ctx, name: str):
    """``more(look, spp, k)`` for :func:`settle`: :func:`batch` of ``name``."""
    return lambda look, spp, k: batch(ctx, name, look, spp, k)


def control_renderer(ctx, name: str):
    """``control(look, spp, k, pixels, around)`` for :func:`settle` of
    estimator ``name``: (spp, K renders) of `path`, the reference's
    integrator, on the same seeds as a confirming batch (kept under its
    shape: estimators confirm at their own spp). Given ``pixels`` (H, W),
    the only ones read, it renders the :func:`~.common.windows` around them, placed
    in a copy of ``around`` (the confirming batch: what lies outside is not
    path's, and nothing reads it): sun_sky's cosine sampling at 32² needed
    path at 16 × 32 768 spp for 1 pixel, 398 s for the whole film. A film
    with a crop window of its own (a user's scene file as a failure case)
    is rendered whole: its pixels are the window's. Given ``only_windows``
    it returns None wherever it would render the whole film (a crop window
    of the film's own, or no :func:`~.common.windows` for ``pixels``). None
    for path itself, for an estimator biased by design (it confirms nothing:
    :func:`settle`'s ``confirm``) or where the context does not render it."""
    if name == REFERENCE or REFERENCE not in ctx.integrators or evidence.by_design(name):
        return None

    def control(look, spp, k, pixels=None, around=None, only_windows=False):
        tag = f"control-{spp}x{k}"
        film = None if ctx.scene is None else ctx.scene.sensors()[0].film()
        whole = film is not None and list(film.crop_offset()) == [0, 0] \
            and list(film.crop_size()) == list(film.size())
        parts = common.windows(pixels, film.rfilter().border_size()) \
            if pixels is not None and whole else None
        if not parts:
            return None if only_windows else batch(ctx, REFERENCE, look, spp, k, tag)
        images = np.array(around[..., :3], copy=True)
        for x, y, w, h in parts:
            sub = common.cropped(ctx, (x, y, w, h))
            images[:, y:y + h, x:x + w] = batch(sub, REFERENCE, look, spp, k,
                                                f"{tag}-crop{x}.{y}.{w}.{h}")[1]
        return spp, images
    return control


#: A test stops before its samples per pixel exceed this many times the
#: reference's: beyond that the comparison rests on the reference's own
#: unseen tail (the full profile's sun_sky at 32²: cosine sampling "brighter"
#: at one pixel at 256× the reference's 2048 spp, confirmed at 1024×).
REFERENCE_LEAD = 64


def budget(start: int, growth: float, reference_spp: int | None = None) -> int:
    """A test's budget in samples per pixel: ``growth`` × its first look's
    ``start``, stopped at :data:`REFERENCE_LEAD` × the reference's
    ``reference_spp`` (None: not stopped), never below ``start``."""
    full = int(start * growth)
    return max(start, min(full, REFERENCE_LEAD * reference_spp)) if reference_spp else full


#: Looks a test may take at most: the seed blocks of the sequential streams.
LOOKS = 20

#: A test the sun split follows stops where deciding needs more than this
#: many times its budget. Uniform, cosine and BSDF sampling on the real sun
#: of the full profile's seven heavy-tail cases asked for 1e6-5e7 samples
#: per pixel at every look, 8-80× the budget of 131 072, and none decided
#: in four full runs: their seven looks each, about 150 s of a run, ended
#: where the split map decided them
#: (docs/measurements.md#2026-12-06-real-sun-test-stops).
BEYOND_BUDGET = 8


def settle(first: list, reference, read, more, epsilon: float, growth: float,
           alpha: float = statistics.ALPHA, looks: int = LOOKS,
           reference_spp: int | None = None, control=None, confirm: bool = True,
           split_follows: bool = False):
    """The sequential test (module doc) of an estimator's renders ``first``
    [(spp, (K, H, W, C))] against ``reference`` (the reference's
    :class:`statistics.Moments`): ``read(comparison, batches, look)`` the
    rules of evidence at a look (an :class:`evidence.Decision`; look −1: a
    confirming batch alone), ``more(look, spp, k)`` the next batch's
    (spp, renders), ``epsilon`` the pass's bound on the relative bias,
    ``growth`` the budget as a multiple of the first look's samples,
    ``looks`` the most looks there are seeds for, ``reference_spp`` the
    reference's samples per pixel (the budget stops at
    :data:`REFERENCE_LEAD` × that), ``control(look, spp, k, pixels,
    around)`` the reference's integrator on a confirming batch's seeds
    (:func:`control_renderer`), rendered only where a rejection came back
    in it, or before it far past the reference (:data:`PATH_FIRST`) (None:
    none; see replication.replicated_rejection), ``confirm`` False: a fail stands at
    the look that reads it (an estimator biased by design, whose fail is
    its label, not a check's outcome), ``split_follows`` the sun split
    will decide what this test leaves inconclusive: it stops where its
    reading needs more than :data:`BEYOND_BUDGET` × the budget. Returns
    (:class:`evidence.Settled`, the last look's comparison)."""
    batches = [(spp, np.asarray(x)[..., :3]) for spp, x in first]
    start = samples(batches)
    limit = budget(start, growth, reference_spp)
    k = min(BATCH_RENDERS, max(x.shape[0] for _, x in batches))
    look, replicated, confirmation = 0, None, ""
    while True:
        c = statistics.compare(statistics.Moments.pooled(batches), reference,
                               level(alpha, look))
        total = samples(batches)
        d = evidence.settle(read(c, batches, look), c, epsilon, total)
        if d.outcome == "pass" or (d.outcome == "inconclusive" and 2 * total > limit):
            break
        if split_follows and d.outcome == "inconclusive" \
                and (d.samples_needed or 0) > BEYOND_BUDGET * limit:
            d.reason += (f"; stopped at {total} samples per pixel in {look + 1} look"
                         f"{'s' if look else ''}: {_would_decide(d)}, "
                         f"{d.samples_needed / limit:.0f}× the budget of {limit}")
            break
        if d.outcome == "fail" and not confirm:
            confirmation = "not confirmed: biased by design"
            break
        if look + 1 >= looks:
            break
        spp, renders = (confirming_batch(d, batches, k) if d.outcome == "fail" else
                        (max(1, math.ceil(total / k)), k))
        if d.outcome == "fail" and confirm and _path_first(d, c, total, reference_spp, control) \
                and _reference_at_fault(c, d, batches, reference, alpha,
                                        lambda at: control(look + 1, spp, renders, at,
                                                           np.zeros((renders,) + at.shape + (3,),
                                                                    np.float32), True)):
            replicated = False
            confirmation = (f"not confirmed: path in {renders} fresh renders at {spp} spp "
                            "differs from the reference as much there (the reference's "
                            "error, not the estimator's)")
            if 2 * total > limit:
                d.outcome = "inconclusive"
                d.reason += f"; {confirmation}, and the budget is spent"
                break
            # (the estimator's confirming batch would read the reference's
            # error again: the next look is an ordinary one)
            d.outcome, spp, renders = "inconclusive", max(1, math.ceil(total / k)), k
        new = more(look + 1, spp, renders)
        if d.outcome == "fail":
            fresh = [new]
            replicated, _, again, excused = replication.replicated_rejection(
                c, d, new[1], reference, alpha, lambda comp, y: read(comp, fresh, -1),
                _beside(control, look + 1, spp, renders, new[1], reference_spp)
                if control else None)
            confirmation = (f"{'replicated' if replicated else 'not replicated'} in "
                           f"{renders} fresh renders at {spp} spp"
                           + (f" ({excused})" if excused else ""))
            if replicated:
                break
            if 2 * total > limit:
                d.outcome = "inconclusive"
                d.reason += f"; {confirmation}, and the budget is spent"
                break
        batches.append(new)
        look += 1
    if d.outcome == "inconclusive" and 2 * total > limit and "budget" not in d.reason:
        d.reason += _spent(d, total, look + 1, start, limit < budget(start, growth),
                           reference_spp)
    if d.outcome == "fail" and confirmation:
        d.reason += f"; {confirmation}"
    # (after the looks: a vacuous pass is failed, never confirmed on more renders)
    d = evidence.nothing_tested(d, c)
    return evidence.Settled(decision=d, looks=look + 1, samples=total, budget=limit,
                            replicated=replicated, replication=confirmation), c


def _beside(control, look: int, spp: int, renders: int, around, reference_spp):
    """``beside(pixels)``: the renders (K, H, W, C) of ``control``, the
    reference's integrator, on the seeds of the confirming batch ``around``
    (``renders`` at ``spp``). Where pixels alone are read and windows around
    them can be rendered, at least the reference's ``reference_spp`` samples
    per pixel in all: the fresh renders are tested against these instead of
    the reference (replication.against_fresh_path), and a bias must come
    back there as it would against the reference. One pixel of the lone
    sphere at the reference's 284 672 spp costs about 0.3 s."""
    def beside(pixels):
        if pixels is not None and reference_spp:
            more = max(spp, math.ceil(reference_spp / renders))
            got = control(look, more, renders, pixels, around, True)
            if got is not None:
                return got[1]
        return control(look, spp, renders, pixels, around)[1]
    return beside


#: A fail read at this many times the reference's samples per pixel or
#: more, on a few pixels and not on the image mean, first asks path on the
#: confirming batch's seeds, in windows around those pixels, whether the
#: reference is off there (:func:`_reference_at_fault`): where it is, the
#: estimator's confirming batch (:func:`confirming_batch`) would only read
#: the reference's error again. The estimator's renders so far, not that
#: batch, are then tested against path's: a bias at a pixel where the
#: reference is off the same way must show in fewer samples to fail. In
#: sun_sky's failure case the last look, at 64× the reference's spp, read
#: "brighter at 1 px" in seed sets 98 and 103, and path beside the
#: confirming batch read it too: 127 s of confirming renders in seed set 98
#: (docs/measurements.md#2026-12-05-path-asked-first-far).
PATH_FIRST = 16


def _pixels(d, c) -> np.ndarray:
    """The pixels (H, W) fail ``d`` on comparison ``c`` rests on."""
    return d.pixels if d.pixels is not None else c.pixel_p < c.alpha_pixel


def _path_first(d, c, total: int, reference_spp: int | None, control) -> bool:
    """Whether fail ``d`` (on comparison ``c``, at ``total`` samples per
    pixel) asks path first (:data:`PATH_FIRST`)."""
    if control is None or not reference_spp or total < PATH_FIRST * reference_spp:
        return False
    if d.pooled is not None and np.any(d.pooled):
        return False
    pixels = _pixels(d, c)
    return 0 < int(pixels.sum()) <= common.WINDOW_PIXELS


def _reference_at_fault(c, d, batches, reference, alpha: float, path) -> bool:
    """Whether every pixel fail ``d`` (on comparison ``c`` of ``batches``
    against ``reference``) rests on is the reference's error, as
    replication.shared_with_control reads it for the estimator's renders so
    far: ``path(pixels)``, the reference's integrator on fresh seeds in
    windows around ``pixels`` as (spp, renders) (None: it could not be
    rendered so), rejects the reference there in the same direction, and
    those renders do not reject path's."""
    pixels = _pixels(d, c) & (c.pixel_p < c.alpha_pixel)
    got = path(pixels)
    if got is None:
        return False
    shared, _ = replication.shared_with_control(
        c, statistics.Moments.pooled(batches), lambda _: got[1], reference, alpha, pixels,
        np.zeros(c.pooled_p.shape, bool))
    return bool(shared.any()) and bool(np.array_equal(shared, pixels))


def _would_decide(d) -> str:
    """"about N would decide", or "those would decide" where the reading
    already names N (a tail's "about N samples per pixel would see it")."""
    n = f"{d.samples_needed:.2g}"
    return "those would decide" if f"about {n} " in d.reason else f"about {n} would decide"


def _spent(d, total: int, looks: int, start: int, capped: bool, reference_spp) -> str:
    """What an inconclusive reading adds when its budget is spent: the samples
    reached, whether the reference capped them, and what would decide."""
    text = f"; budget spent: {total} samples per pixel in {looks} looks"
    if capped:
        text += f" (at most {REFERENCE_LEAD}× the reference's {reference_spp} spp)"
    if d.samples_needed is None:
        return text
    text += f" ({_would_decide(d)}; "
    if capped:
        return text + (f"a reference of about {d.samples_needed / REFERENCE_LEAD:.2g} spp "
                       "would allow it)")
    return text + f"rerun with --budget {2 ** math.ceil(math.log2(d.samples_needed / start)):g})"
