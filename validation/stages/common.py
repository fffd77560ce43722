"""The stages every run shares: the scene and its estimators, kept renders,
the reference, and letting the scene go; the windows of a film a
crop renders (a confirming batch's path, sequential.py).

A stage is ``stage(context) -> None``: it reads what earlier stages put on the
:class:`~.context.Context` and adds what it finds. :mod:`~mcillum.validation.pipeline`
lists which stages a scene comparison (scene.py, speed.py, quadrature.py), a
failure case and a point of a parameter sweep (cases.py) run, in order. The
stages gather evidence (renders, reference, numbers, tests); the verdicts
are the checks' (:mod:`~mcillum.validation.checks`).
"""

from __future__ import annotations

import copy
import dataclasses
import gc
import hashlib
import json
import os

import numpy as np

from mcillum.errors import NoSignal
from mcillum.integrators.core import registry, scene_checks

from ..plan import scenes
from ..results import ReferenceSummary
from ..run import jobs, references, renders, stacks

REFERENCE = registry.REFERENCE


# ----------------------------- Scene and estimators ----------------------------

def load(ctx) -> None:
    """The scene with the plan's resolution and $-parameters (a bundled
    scene takes the resolution as $res, a user's is loaded at the plan's
    film); its cache key. A user's scene's content (what a hemisphere pdf
    cannot reach) is read off the loaded scene, as the estimators read it."""
    try:
        info = scenes.info(ctx.scene_name)
    except ValueError as err:
        raise ValueError(f"{ctx.id}: {err}") from None
    film = getattr(ctx.plan, "film", None)
    defines = ctx.defines if film is not None else {"res": ctx.res, **ctx.defines}
    ctx.resolved = renders.resolve_defines(info.path, **defines)
    ctx.scene = renders.load_resolved(info.path, ctx.resolved, film=film)
    if info.contains is None:
        kinds = {p.kind for p in scene_checks.unreachable(ctx.scene)}
        info = dataclasses.replace(info, contains=tuple(k for k in scene_checks.KINDS
                                                        if k in kinds))
    ctx.info = info
    ctx.params = dict(getattr(ctx.plan, "integrator_settings", None)
                      or {"max_depth": ctx.max_depth})
    ctx.scene_key = references.cache_key(info.path, ctx.resolved, ctx.params,
                                         ctx.run.variant, film=film,
                                         seed_set=ctx.run.seed_set)
    ctx.render_key = references.render_key(info.path, ctx.resolved, ctx.params,
                                           ctx.run.variant, film=film,
                                           seed_set=ctx.run.seed_set)
    ctx.scene_spec = jobs.SceneSpec(os.path.abspath(info.path),
                                    tuple(sorted(ctx.resolved.items())), ctx.scene_key, film)


def choose_estimators(ctx) -> None:
    """The estimators asked for whose registry facts say they reach every
    kind of content the scene holds (at the plan's max_depth), each given
    those of the scene's integrator settings it takes (`path`, the
    reference, takes them all)."""
    ctx.integrators = {}
    for name in ctx.estimators:
        facts = registry.facts(name)
        if facts.renders(ctx.info.contains, ctx.max_depth):
            ctx.integrators[name] = made = jobs.make_taking(name, ctx.params)
            left = [k for k in ctx.params if k not in dict(made.params)]
            if left:
                ctx.scene_notes.append(
                    f"{name} takes no {', '.join(left)}: rendered without "
                    f"{'it' if len(left) == 1 else 'them'}; the reference with "
                    + ", ".join(f"{k} {ctx.params[k]}" for k in left))
        elif not ctx.info.bundled:     # (a bundled scene's header says so already)
            missing = [scene_checks.KIND_NAMES[k] for k in ctx.info.contains
                       if k not in facts.reaches]
            why = (f"the scene holds {', '.join(missing)}" if missing else
                   f"it defines max_depth {', '.join(map(str, facts.depths or ()))} only, "
                   f"not {ctx.max_depth}")
            ctx.scene_notes.append(f"{name} does not render this scene: {why}")


def cropped(ctx, window: tuple[int, int, int, int]):
    """A copy of ``ctx`` (its scene loaded) whose renders are only
    ``window`` = (x, y, width, height) of its film, kept under their own key
    (path beside a confirming batch, where only some pixels are read:
    stages/sequential.py)."""
    film = tuple(int(v) for v in ctx.scene.sensors()[0].film().size())
    sub = copy.copy(ctx)
    sub.scene_spec = dataclasses.replace(ctx.scene_spec, film=film, crop=window)
    sub.scene = renders.load_resolved(ctx.info.path, ctx.resolved,
                                      film=sub.scene_spec.load_film)
    sub.render_key = f"{ctx.render_key}-crop{'.'.join(map(str, window))}"
    return sub


#: Windows a control renders at most; where the pixels read need more, or
#: the windows would cover half the film, it renders the whole film.
WINDOWS = 4
#: Pixels read beyond which the whole film is rendered without looking for
#: windows (merging boxes costs the cube of their number).
WINDOW_PIXELS = 64


def windows(pixels, border: int = 0) -> list[tuple[int, int, int, int]] | None:
    """(x, y, width, height) windows of a film that hold every pixel of
    ``pixels`` (H, W) with ``border`` pixels around it (what the film's
    reconstruction filter reaches: a window's edge pixels must see the
    samples a whole film gives them), clipped to the film, overlapping ones
    merged; None where more than :data:`WINDOWS` are needed or they would
    cover half the film, or more than :data:`WINDOW_PIXELS` pixels are
    read (render the film)."""
    pixels = np.asarray(pixels, bool)
    height, width = pixels.shape
    if pixels.sum() > WINDOW_PIXELS:
        return None
    rows, cols = (a.tolist() for a in np.nonzero(pixels))
    boxes = [(max(0, x - border), max(0, y - border), min(width, x + border + 1),
              min(height, y + border + 1)) for y, x in zip(rows, cols)]
    merged = True
    while merged:
        merged = False
        for i, a in enumerate(boxes):
            for j in range(i + 1, len(boxes)):
                b = boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]),
                                max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    area = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in boxes)
    if not boxes or len(boxes) > WINDOWS or 2 * area > height * width:
        return None
    return [(x0, y0, x1 - x0, y1 - y0) for x0, y0, x1, y1 in boxes]


def release(ctx) -> None:
    """Drop the loaded scene when nothing more is rendered from it: every
    live scene's shapes, BSDFs and emitters stay in Dr.Jit's instance
    registry, which every virtual call of a kernel dispatches over, and slow
    every later render in this process, and so the timings of the speed
    stage and of a sweep's points. Collected now: a scene that a reference
    cycle still reached lived until Python's collector came round (a
    refusal kept with its traceback was such a cycle: cases._refusal), and
    six such scenes made a traced render of another 3.5× slower (5.5 →
    19.6 ms; docs/measurements.md#2026-12-05-ms-floor-recording-lingering)."""
    ctx.scene = None
    gc.collect()


# ----------------------------------- Renders ------------------------------------

def compile_kernels(ctx) -> None:
    """Each integrator's first render (its kernel compiles or loads from
    Dr.Jit's cache), timed apart; once per context, and only when something
    is rendered. (A timed render that compiled is rendered again warm,
    renders.timed_render: the first one's time is the one kept here.)"""
    if ctx.compile_seconds:
        return
    seed = ctx.run.stream("compile").seed()
    batch = [ctx.job(integ, 1, seed) for integ in ctx.integrators.values()]
    ctx.compile_seconds = {n: out.first_seconds for n, out in
                           zip(ctx.integrators, ctx.render(batch, None, timed=True))}


def first_look(ctx) -> tuple[int, int]:
    """(spp, K) of a context's renders at one spp: a failure case's (or a
    sweep point's) spp and seeds; for a scene comparison, the top rung of its
    ladder (its sun split's twins, stages/sun_split.py)."""
    if ctx.is_case:
        return ctx.plan.spp, ctx.plan.seeds
    return ctx.plan.ladder[-1], ctx.plan.renders


def kept_file(ctx, what: str) -> str:
    """A file name for ``what`` that differs between contexts sharing an id
    (the points of a sweep, a case's sunless twin)."""
    tag = json.dumps(ctx.defines, sort_keys=True, default=str)
    return f"{what}-{hashlib.sha256(tag.encode()).hexdigest()[:8]}"


def stream_renders(ctx, stream: str, name: str, params: dict, spp: int, k: int, block: int,
                   timed: bool = False):
    """K renders of estimator ``name`` with ``params`` (over the plan's) at
    ``spp``, seeded from block ``block`` of seed stream ``stream``, kept in
    the run directory (stacks.kept: a re-run loads them): the quadrature
    and learning stages' extra renders."""
    integrator = jobs.make(name, {**ctx.params, **params})
    tag = "-".join(f"{key}{value}" for key, value in sorted(params.items()))
    return stacks.kept(ctx, f"{stream}{block}-{name}", f"{stream} {tag}",
                       {name: integrator}, {name: spp}, k,
                       ctx.run.stream(stream, block).take(k), label=ctx.label,
                       timed=timed)[name]


# ---------------------------------- Reference -----------------------------------

def build_reference(ctx) -> None:
    """`path` until its standard error is a fraction of the smallest error it is
    compared against: the least noisy render stack of a scene comparison
    (no finer than a tenth of the scene checks' ε of the image, but fine
    enough for the error bars of renders that carry them:
    references.target_for), or `path`'s own in a failure case (where the
    other stacks' tails would set no useful target)."""
    chosen = [(spp, s) for spp, by_name in ctx.stacks.items() for n, s in by_name.items()
              if not ctx.is_case or n == REFERENCE]
    epsilon = 0.0 if ctx.is_case else ctx.run.sequential.scene_epsilon
    # (error bars are calibrated at one rung: the reference resolves that one's)
    rung = references.bars_rung(list(ctx.stacks)) if ctx.stacks else None
    target = references.target_for([s.images for _, s in chosen],
                                   ctx.run.profile.reference_fraction, epsilon,
                                   [s.images for spp, s in chosen
                                    if spp == rung and "posterior_std" in s.aovs])
    # (path's own renders at the top rung say how many spp that takes: the
    # reference's pass size)
    own = ctx.stacks[max(ctx.stacks)].get(REFERENCE) if ctx.stacks else None
    expected = references.expected_spp(own.images, own.spp, target) if own is not None else 0.0
    ctx.reference = references.ensure(ctx, target, expected)


def require_signal(ctx) -> None:
    """Refuse a context whose reference carries no signal (every pixel
    channel at most references.SIGNAL_FLOOR): against a black reference
    every check passes whatever an estimator renders, so a scene without
    light, or whose camera looks away from it, would pass vacuously.
    Returns None where the reference carries signal.

    Raises :class:`~mcillum.errors.NoSignal` (the CLI's exit 2) for a
    user's scene file, naming it and what to check; RuntimeError for a
    bundled scene (the profile's scenes are all lit: a bug, not the
    user's)."""
    ref = ctx.reference
    if references.has_signal(ref):
        return
    h, w = ref.mean.shape[:2]
    black = (f"the reference (Mitsuba's path, {ref.spp} spp at {w}×{h}) is black in "
             f"every pixel (none above {references.SIGNAL_FLOOR:.3g}, float32's smallest "
             "normal number)")
    if ctx.info.bundled:
        raise RuntimeError(f"internal error: bundled scene '{ctx.id}' with "
                           f"{ctx.defines or 'its defaults'}: {black}; the profile's scenes "
                           "must be lit: fix the scene or the profile")
    scene = ctx.scene
    emitters = len(scene.emitters()) if scene is not None else None
    if emitters == 0:
        why = ("the scene has no emitter (no area light, point light or environment): add "
               "an emitter, or check the include or $-parameter that holds it")
    else:
        some = f"its {emitters} emitter{'s' if emitters != 1 else ''}" if emitters \
            else "its emitters"
        why = (f"{some} light{'s' if emitters == 1 else ''} nothing the sensor sees: "
               "check that the sensor looks at the lit part of the scene (its to_world / "
               f"lookat), that the emitters face it, and that max_depth {ctx.max_depth} "
               "reaches them")
    raise NoSignal(f"{ctx.info.path}: nothing to validate: {black}, and every estimator "
                   f"would pass against it whatever it renders; {why}")


def reference_summary(ref) -> ReferenceSummary:
    """What the results record of a reference (run.references.Reference)."""
    return ReferenceSummary(integrator=REFERENCE, spp=ref.spp, passes=ref.passes,
                            spp_per_pass=ref.spp_per_pass, seconds=ref.seconds,
                            cached_passes=ref.cached_passes,
                            rendered_passes=ref.meta.get("rendered_passes", 0),
                            target_variance=ref.meta.get("target_variance", 0.0),
                            achieved_variance=float(ref.variance_of_mean.mean()),
                            capped=ref.capped, key=ref.key)


def scene_summary(ctx) -> str:
    """The scene header's summary with the $-parameters it was rendered with
    (a map by the name it was given, not the checked file it became)."""
    return scenes.expand(ctx.info.path, ctx.info.summary, ctx.defines)
