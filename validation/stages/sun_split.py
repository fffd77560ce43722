"""A test at one spp read with the sun in mind, and the sun split: what a
real sun left undecided, decided on the map without it and with it widened.

A failure case tests its K renders at its spp; a scene comparison's sun
split tests K renders at the top rung of its ladder (:func:`first_look`).
Either is read by the rules of evidence (checks/evidence.py) and continued
on fresh batches until it decides or its budget is spent
(:func:`settled_test`, stages/sequential.py).

On a map with a sun (envmaps/sun.py), the estimators whose test did not
pass are tested again on the map without its sun: the **sunless twin**, a
context of its own that the pipeline runs through
:data:`~mcillum.validation.pipeline.SUNLESS` (rendering is linear in the
map). Those the real sun left inconclusive, that passed without it and that
do not sample the emitters are tested once more on the map with its sun
**widened** to a disc the samples hit: the **widened twin**, run the same
way. Failure cases split the sun of their heavy-tail maps; scene
comparisons that of their map, which the renders get as ``$envmap``
(a user's scene that names its map by file, or in an included file,
too: plan/user_scenes.py, ``map_parameter``). The verdicts are the
checks' (checks/cases.py, checks/scene.py).
"""

from __future__ import annotations

import numpy as np

from mcillum.envmaps import sun
from mcillum.integrators.core import registry

from ..checks import evidence
from ..checks import sun as sun_rules
from ..plan import scene_files, user_scenes
from ..results import BatchTest, SunSplit
from ..run import references, renders
from ..stats import tails
from . import common, sequential
from .common import REFERENCE


# ------------------------------- The test at one spp ----------------------------

def terms(ctx) -> tuple[float, float]:
    """(ε, budget as a multiple of the first look's samples) of a context's
    test: the profile's case terms for a failure case, its scene terms for
    a scene comparison's twins (``--budget`` overrides either)."""
    seq = ctx.run.sequential
    if ctx.is_case:
        return seq.case_epsilon, ctx.run.growth(seq.case_budget)
    return seq.scene_epsilon, ctx.run.growth(seq.scene_budget)


def _reader(ctx, name: str):
    """``read(comparison, batches, look)``: the rules of evidence for this
    context's renders of ``name``, with path's fireflies (counted once per
    context) as the reference's tail. On a map with a sun (``ctx.sun``, a
    failure case's), the sun is a tail the renders may not have seen yet,
    whatever else they caught: while the estimator's largest pdf expects
    fewer than SUN_HITS direct hits per pixel in the samples so far
    (N·Ω·max p; or it declares no largest pdf), no downward rejection counts
    (checks/sun.py: unseen_sun) and the test renders on. On the widened sun's map
    (``ctx.disc``) no downward pixel rejection counts
    (checks/sun.py: partly_hidden)."""
    spp, _ = common.first_look(ctx)
    found = ctx.stacks[spp]
    path_events = (tails.tail_events([found[REFERENCE].images], ctx.reference.mean)[0]
                   if REFERENCE in found else None)
    decide = evidence.decider(ctx.reference.mean, path_events)
    rays = directions(ctx, name)
    finds_sun = samples_emitters(name)

    def read(comparison, batches, look):
        d = decide(comparison, batches, look)
        if ctx.disc:
            return sun_rules.partly_hidden(d, comparison)
        if ctx.sun is None or finds_sun:
            return d
        hits = expected_sun_hits(name, sequential.samples(batches) * rays,
                                 ctx.sun["solid_angle"])
        if hits is None or hits < sun_rules.SUN_HITS:
            sun_rules.unseen_sun(d, comparison, hits)
        return d
    return read


def settled_test(ctx, name: str, x: np.ndarray) -> BatchTest:
    """The sequential test (stages/sequential.py) of estimator ``name``'s
    renders ``x`` at the context's first look, a fail confirmed beside
    path's renders of the confirming seeds, as a :class:`BatchTest`."""
    epsilon, growth = terms(ctx)
    # an estimator biased by design: its fail is its label (checks/cases.py),
    # not worth a confirming batch (up to 1 000 renders of N directions)
    settled, c = sequential.settle([(common.first_look(ctx)[0], x)], ctx.reference.moments(),
                                   _reader(ctx, name), sequential.renderer(ctx, name),
                                   epsilon, growth, reference_spp=ctx.reference.spp,
                                   control=sequential.control_renderer(ctx, name),
                                   confirm=not evidence.by_design(name),
                                   split_follows=split_follows(ctx, name))
    d = settled.decision
    return BatchTest(passed=c.passed, pass_fraction=c.pass_fraction, min_p=c.min_p,
                     pooled_p=[float(p) for p in c.pooled_p], alpha_pixel=c.alpha_pixel,
                     test=c.summary(), outcome=d.outcome, reason=d.reason,
                     tail_events=d.tail_events, samples_needed=d.samples_needed,
                     counted_up=d.counted_up, rejected_pixels=d.rejected_up + d.rejected_down,
                     replicated=settled.replicated,
                     replication_test=settled.replication or None, looks=settled.looks,
                     samples_per_pixel=settled.samples, relative_bias=d.relative_bias,
                     half_width=d.half_width)


def split_follows(ctx, name: str) -> bool:
    """Will the sun split decide what ``name``'s test on this context's map
    leaves inconclusive: the real map of a sun (found: ``ctx.sun``), and an
    estimator that does not sample the emitters (the widened twin tests
    only those)? A twin's own test has no split after it."""
    return ctx.sun is not None and not ctx.disc and not samples_emitters(name)


# ------------------------- What each kind of context holds -----------------------

def _outcome(ctx, name: str) -> str | None:
    """The outcome of ``name``'s test on the real map (None: not tested)."""
    if ctx.is_case:
        n = ctx.rows[name].numbers
        return n.test.outcome if n is not None and n.test is not None else None
    found = ctx.evidence.get(name)
    if found is None or found.settled is None:
        return None
    return found.settled.decision.outcome


def _not_passed(ctx) -> list[str]:
    """The estimators whose test on the real map was run and did not pass:
    not `path`, the reference, nor in a scene comparison one biased by
    design, which has no ``unbiased`` check (a case's row of one still
    says whether it is biased without the sun too)."""
    return [n for n in ctx.estimators if n != REFERENCE
            and (ctx.is_case or not evidence.by_design(n))
            and _outcome(ctx, n) not in (None, "pass")]


def _holder(ctx, name: str):
    """Where ``name``'s sun split goes: a case row's numbers, a scene
    estimator's evidence (checks/scene.py writes it into its record)."""
    return ctx.rows[name].numbers if ctx.is_case else ctx.evidence[name]


def _samples(ctx, name: str) -> int:
    """Samples per pixel ``name``'s test on the real map reached."""
    if ctx.is_case:
        return ctx.rows[name].numbers.test.samples_per_pixel
    return ctx.evidence[name].settled.samples


# ------------------------------ The sunless twin --------------------------------

def find_sun(ctx) -> None:
    """``ctx.sun``, ``ctx.sunless_map``: the sun of the map the renders get
    as ``$envmap`` (envmaps/sun.py: its facts) and the map without it; None
    where they get no map by that name or the map has no sun."""
    if ctx.sun is not None or "envmap" not in (ctx.resolved or {}):
        return
    sunless_map, facts = sun.without_sun(ctx.resolved["envmap"])
    if facts["texels"]:
        ctx.sunless_map, ctx.sun = sunless_map, facts


def note_unsplit_sun(ctx) -> None:
    """A scene comparison whose renders do not get the map as ``$envmap``
    cannot be split (a user's scene where plan/user_scenes.py could not give
    it: ``map_parameter`` says why): where that map has a sun and an
    estimator's ``unbiased`` did not pass, a note of the scene says so, why,
    and what the split would have tested. Reads the loaded scene's
    environment emitter (its texels, as Mitsuba holds them), so it runs
    before the scene is let go."""
    if ctx.is_case or "envmap" in (ctx.resolved or {}) or ctx.scene is None:
        return
    open_ = _not_passed(ctx)
    texels = renders.environment_texels(ctx.scene) if open_ else None
    if texels is None:
        return
    _, facts = sun.split(texels)
    if facts["texels"]:
        ctx.scene_notes.append(
            f"its map has a sun ({facts['solid_angle']:.2g} sr, "
            f"{100 * facts['power_share']:.0f} % of the map's power) that the sun split "
            f"cannot take off: {_why_unsplit(ctx)}; so {', '.join(open_)} "
            f"{'was' if len(open_) == 1 else 'were'} not tested without it and with it "
            "widened")


def _why_unsplit(ctx) -> str:
    """Why the renders of ``ctx``'s scene do not get its map as ``$envmap``."""
    fallback = ("mcillum found no envmap emitter naming a map file in the scene's XML: "
                "name the map in its filename")
    if ctx.info.bundled:
        return "the scene names its map's file: give it as $envmap"
    try:
        return user_scenes.map_parameter(ctx.info.path, ctx.defines)[1] or fallback
    except scene_files.SceneFileError:
        return fallback


def sunless_twin(ctx) -> None:
    """``ctx.sunless``: the context on its map without the sun, for the
    estimators whose test did not pass (inconclusive: a rejection a tail
    can explain, or an interval wider than ±ε; or biased), with `path`, on
    seed streams of its own; None where the map has no sun (a failure case
    splits only its heavy-tail group's). The sun is found before the tests
    on the real map (cases.test_bias; scene.settle: :func:`find_sun`), whose
    stop reads it."""
    if ctx.is_case and ctx.plan.group != "heavy_tail":
        return
    tested = _not_passed(ctx)
    if not tested or ctx.sun is None:
        return
    ctx.sunless = ctx.derive([*tested, REFERENCE], label=f"{ctx.id} sunless",
                             streams={"renders": "sunless", "sequential": "sunless_sequential"},
                             envmap=ctx.sunless_map)


def split_sun(ctx) -> None:
    """Each estimator of the sunless twin tested there by the same rules (a
    bias there is a bias, whatever the sun does), with the sun's facts and
    the number of direct hits it expects in the samples its test reached,
    N·Ω·max p."""
    sub = ctx.sunless
    if sub is None:
        return
    sunless_mean = float(sub.reference.mean[..., :3].mean())
    image_mean = float(ctx.reference.mean[..., :3].mean())
    spp, _ = common.first_look(sub)
    for name in sub.estimators[:-1]:        # those tested (the last is path, the reference)
        test = settled_test(sub, name, sub.stacks[spp][name].images)
        _holder(ctx, name).sun = SunSplit(
            sun=ctx.sun, sunless_passed=test.outcome != "fail",
            sunless_test=test.test, sunless_reference_mean=sunless_mean,
            expected_sun_hits_per_pixel=expected_sun_hits(
                name, _samples(ctx, name) * directions(ctx, name), ctx.sun["solid_angle"]),
            sun_share_of_image=1.0 - sunless_mean / image_mean, sunless_outcome=test.outcome,
            sunless_reason=test.reason)


# ----------------------------- The widened sun ---------------------------------

def widened_twin(ctx) -> None:
    """``ctx.widened``: the context on its map with the sun widened
    (envmaps/sun.py, :func:`~mcillum.envmaps.sun.widen`), for the estimators
    whose test on the real map the budget left inconclusive, that passed
    without the sun, and that do not sample the emitters (an estimator that
    does finds the sun by construction); with `path`, on seed streams of its
    own; None unless there are such estimators."""
    def split(n):
        return getattr(_holder(ctx, n), "sun", None)
    # (split_follows: those whose real-sun test may have stopped for this
    # twin; none where there is no sun to widen)
    tested = [n for n in ctx.estimators if n != REFERENCE
              and _outcome(ctx, n) == "inconclusive" and split(n) is not None
              and split(n).sunless_outcome == "pass" and split_follows(ctx, n)]
    if not tested:
        return
    widened_map, facts = sun.widened(ctx.resolved["envmap"])
    ctx.widened = ctx.derive([*tested, REFERENCE], label=f"{ctx.id} widened sun",
                             streams={"renders": "widened",
                                      "sequential": "widened_sequential"},
                             envmap=widened_map)
    ctx.widened.disc = True
    for name in tested:
        split(name).widened = facts


def widened_reference(ctx) -> None:
    """`path`'s reference of the widened twin (common.build_reference), then
    rendered on until its spp no longer caps the test's budget
    (sequential.REFERENCE_LEAD): the disc is hit often enough for the budget
    to decide, and a reference of the usual precision stopped sun_sky's at
    half of it (image mean ±4.5 % at 131 072 samples per pixel)."""
    common.build_reference(ctx)
    ref = ctx.reference
    spp, k = common.first_look(ctx)
    needed = sequential.budget(spp * k, terms(ctx)[1]) / sequential.REFERENCE_LEAD
    if ref.spp < needed:
        variance = float(ref.variance_of_mean.mean())     # (as references.ensure reads it)
        ctx.reference = references.ensure(ctx, variance * ref.spp / needed)


def split_widened(ctx) -> None:
    """Each estimator of the widened twin tested there by the same rules of
    evidence, but for the pixels that see the disc only through a sliver
    (checks/sun.py: partly_hidden): the disc is hit often over the image, so its
    image mean decides."""
    sub = ctx.widened
    if sub is None:
        return
    spp, _ = common.first_look(sub)
    for name in sub.estimators[:-1]:        # those tested (the last is path, the reference)
        test = settled_test(sub, name, sub.stacks[spp][name].images)
        split = _holder(ctx, name).sun
        split.widened_outcome, split.widened_reason = test.outcome, test.reason
        split.widened_test = test.test


# ------------------------------ Estimator facts --------------------------------

def samples_emitters(name: str) -> bool:
    """Does estimator ``name`` sample the emitters (it reaches point lights)?
    Then it finds the sun by construction: it has no unseen sun to plead,
    and no widened sun is needed to decide it."""
    return "delta_emitter" in registry.facts(name).reachable


def directions(ctx, name: str) -> int:
    """Directions per camera sample of estimator ``name`` (N for a point set)."""
    return getattr(ctx.integrators[name].made, "directions", 1)


def expected_sun_hits(name: str, samples: int, solid_angle: float) -> float | None:
    """Direct hits on a sun of ``solid_angle`` that estimator ``name`` expects
    in ``samples`` directions traced from a pixel (camera samples × the
    directions per sample of a point-set estimator), at most N·Ω·max p
    (None: unbounded, its registry facts give no largest pdf)."""
    pdf = registry.facts(name).max_direction_pdf
    return None if pdf is None else samples * solid_angle * pdf
