"""Reference images from Mitsuba's `path`, rendered only as far as needed.

A reference is the mean of independent passes (seed stream "reference",
plan/seeds.py) of `path` at the same max_depth, scene and resolution as the
estimators. Its per-pixel
variance of the mean comes from the spread of the pass means (batch means).
:func:`ensure` adds passes until the reference's standard error is at most a
given fraction of the smallest error it will be compared against (see
:func:`target_variance`), or a cap on spp or seconds is hit: the result then
says so in ``capped``, and so does the cache, so that a re-run chasing the
same (or a looser) target uses it as it is instead of rendering again.

Cache: ``<cache>/references/<key>.exr`` with the mean ("RGB"), the summed
squared deviations of pass means ("m2.RGB") and the bookkeeping in its header.
The key hashes everything that changes the image: the scene file and every
file it references (includes, envmaps, meshes, textures: their bytes), the
$-parameters, integrator parameters, variant and mitsuba/drjit versions.
Writes are atomic (temporary file + rename). A header checksum over the
pixels detects a corrupt entry, which is then rendered anew, never used. A
cached reference with too few passes is *extended*, not re-rendered.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mcillum import files

from ..plan import scenes
from ..stats import metrics
from ..stats.statistics import Moments
from . import jobs, renders

#: The variance of a mean of n passes has a relative standard error of
#: √(2/(n − 1)): 25 % at 32 passes. Fewer passes underestimate a silhouette
#: pixel's variance often enough to fail correct estimators
#: (docs/measurements.md#2026-12-01-figures-moved-out-code).
MIN_PASSES = 32
#: Samples of one pass at least (pixels × spp): at 8² px a 64-spp pass of
#: `path` took 2.5-3 ms, most of it a launch's fixed cost (38-46 µs per spp
#: against 6-19 µs at 1 024; docs/measurements.md#2026-12-03-quick-profile-cost-reference).
PASS_SAMPLES = 1 << 16
#: A reference expected to need many passes renders passes of at least its
#: expected spp over this: a traced launch's fixed cost (1.6 ms on the lone
#: sphere at 32², where a 64-spp pass took 5.3 ms) is paid fewer times, and
#: 256 passes still estimate each pixel's variance to ±9 %.
PASSES_WANTED = 256
#: ... and a reference whose pixels' variances are read only on average
#: (the speed stage's, for the share its noise adds to a relMSE: over
#: thousands of pixels 64 passes read it to well under 1 %), of this: at
#: 128² a 16-spp pass of `path` cost a quarter of its time in the launch
#: (docs/measurements.md#2026-12-05-error-bars-calibrated-below).
AVERAGE_PASSES_WANTED = 64
FORMAT_VERSION = 1


@dataclass
class Reference:
    mean: np.ndarray          # (H, W, C) float64
    m2: np.ndarray            # Σ (pass mean − mean)², per pixel
    passes: int
    spp_per_pass: int
    seconds: float            # total render time of all passes
    image_means: np.ndarray   # (passes, C): each pass's mean over the image
    key: str = ""
    capped: str | None = None
    cached_passes: int = 0    # passes found in the cache at the start
    meta: dict = field(default_factory=dict)

    @property
    def spp(self) -> int:
        return self.passes * self.spp_per_pass

    @property
    def pass_variance(self) -> np.ndarray:
        """Per-pixel sample variance of one pass."""
        return self.m2 / max(self.passes - 1, 1)

    @property
    def variance_of_mean(self) -> np.ndarray:
        return self.pass_variance / self.passes

    @property
    def image_mean_se(self) -> float:
        m = self.image_means.mean(axis=1)
        return float(m.std(ddof=1) / np.sqrt(len(m))) if len(m) > 1 else float("nan")

    def moments(self) -> Moments:
        return Moments(self.mean, self.pass_variance, self.passes,
                       self.image_means.mean(axis=0), self.image_means.var(axis=0, ddof=1))


#: A reference whose every pixel channel is at most this carries no signal
#: (stages/common.py: require_signal): float32's smallest normal number.
#: Radiance has no unit mcillum knows (a scene's emitters may be scaled by
#: 1e-6 and be right), so no larger floor is safe; below this one a film
#: pixel holds underflow, not light.
SIGNAL_FLOOR = float(np.finfo(np.float32).tiny)


def has_signal(ref: "Reference") -> bool:
    """Does some pixel channel of the reference's mean exceed SIGNAL_FLOOR?"""
    mean = np.asarray(ref.mean, np.float64)[..., :3]
    return bool(np.any(np.nan_to_num(mean, nan=0.0) > SIGNAL_FLOOR))


# ------------------------------- Cache key -----------------------------------

def _renders_by():
    """The modules whose code decides an estimator's kept renders: the
    renderer, the pass splitter, the replays of recorded launches and
    mcillum's own BSDF, which scenes may use
    (Mitsuba's code is keyed by its version)."""
    from mcillum.integrators.core import passes
    from mcillum.integrators.bsdfs import phong
    from . import replays
    return (renders, passes, phong, replays)


def _filled_by():
    """The modules whose code decides a cached reference: this one (passes,
    precision) and those of :func:`_renders_by` (not the other way round: a
    change in how references are made keeps the estimators' renders)."""
    import sys

    return (sys.modules[__name__], *_renders_by())


def cache_key(scene_path: str, defines: dict, params: dict, variant: str,
              film: tuple[int, int] | None = None, code=None, seed_set: int = 0) -> str:
    """A hash of everything that decides a reference of the scene: its files'
    bytes, $-parameters, integrator parameters, variant, versions, seed set
    and the code of ``code`` (default: the modules that fill a reference)."""
    h = hashlib.sha256()
    for path in scenes.referenced_files(scene_path, defines):
        h.update(os.path.basename(path).encode())
        with open(path, "rb") as f:
            h.update(hashlib.sha256(f.read()).digest())
    desc = {"defines": {k: v for k, v in defines.items() if k != "envmap"},
            "params": params, "variant": variant, "mitsuba": mi.__version__,
            "drjit": dr.__version__, "integrator": "path", "format": FORMAT_VERSION,
            "code": files.code_hash(*(code if code is not None else _filled_by()))}
    if film is not None:                  # a user's scene at a reduced film
        desc["film"] = list(film)
    if seed_set:                          # another independent repeat (plan/seeds.py)
        desc["seed_set"] = seed_set
    h.update(json.dumps(desc, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]


def render_key(scene_path: str, defines: dict, params: dict, variant: str,
               film: tuple[int, int] | None = None, seed_set: int = 0) -> str:
    """:func:`cache_key` over the code of an estimator's renders only: the
    key of the renders a run directory keeps (run/stacks.py)."""
    return cache_key(scene_path, defines, params, variant, film, _renders_by(), seed_set)


# ------------------------------ Cache files ----------------------------------

def _checksum(mean: np.ndarray, m2: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(mean, np.float32).tobytes()
                          + np.ascontiguousarray(m2, np.float32).tobytes()).hexdigest()


def cache_path(cache_dir: str, key: str) -> str:
    return os.path.join(cache_dir, "references", f"{key}.exr")


def save(ref: Reference, cache_dir: str) -> str:
    path = cache_path(cache_dir, ref.key)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    mean, m2 = (np.ascontiguousarray(a, np.float32) for a in (ref.mean, ref.m2))
    meta = {"passes": ref.passes, "spp_per_pass": ref.spp_per_pass,
            "seconds": ref.seconds, "image_means": ref.image_means.tolist(),
            "checksum": _checksum(mean, m2), "format": FORMAT_VERSION, **ref.meta}
    return files.write_exr(path, mean, {"reference": json.dumps(meta)}, {"m2": m2})


def load(cache_dir: str, key: str) -> Reference | None:
    """The cached reference, or None if absent or corrupt (then it is deleted)."""
    path = cache_path(cache_dir, key)
    if not os.path.isfile(path):
        return None
    try:
        mean, header = files.read_exr(path)
        m2, _ = files.read_exr(path, "m2")
        meta = json.loads(header["reference"])
        if meta["checksum"] != _checksum(mean, m2) or meta["format"] != FORMAT_VERSION:
            raise ValueError("checksum or format mismatch")
        return Reference(mean.astype(np.float64), m2.astype(np.float64), meta["passes"],
                         meta["spp_per_pass"], meta["seconds"],
                         np.asarray(meta["image_means"], np.float64), key,
                         cached_passes=meta["passes"],
                         meta={k: meta[k] for k in ("capped", "caps", "target_variance") if k in meta})
    except Exception:
        os.unlink(path)  # corrupt or partial: never use it, render it anew
        return None


# ------------------------------- Rendering ------------------------------------

def target_variance(min_error: float, fraction: float = 0.1) -> float:
    """Largest mean per-pixel variance of the reference mean such that its
    standard error is ``fraction`` of ``min_error`` (an RMSE): (f·e)²."""
    return (fraction * min_error) ** 2


#: The reference need not resolve a relative bias finer than this share of
#: the checks' tolerance ε ("unbiased within ±ε"): a tenth.
RESOLUTION = 0.1
#: Of the variance of a render that carries error bars (the ``posterior_std``
#: AOV), the largest share the reference's variance may have: the bars'
#: calibration compares each pixel's error with its bar, the reference's
#: variance in both, and a larger share hides bars that are too narrow
#: (stages/quadrature.py).
BARS_SHARE = 0.1


def bars_rung(ladder) -> int:
    """The spp of the ladder rung whose renders' error bars are calibrated
    (stages/quadrature.py), and so the rung whose variance the reference must
    resolve to BARS_SHARE: the one below the top. Its renders have about 4×
    the top's variance, so the reference that resolves them costs a quarter
    (on the smooth maps, where a quadrature's error is smallest, it had hit
    the profile's 2²⁰-spp cap); a ladder of one rung calibrates at it."""
    ladder = sorted(ladder)
    return ladder[-2] if len(ladder) > 1 else ladder[-1]


#: An error below this share of the image is float32's, not the estimator's:
#: films summing 256 samples per pixel err by ~1e-5 (the full profile's
#: furnace read as infinitely over-confident at 1e-5 in the calibration,
#: stages/quadrature.py).
EXACT = 1e-4


def target_for(stacks, fraction: float = 0.1, epsilon: float = 0.0, bars=()) -> float:
    """:func:`target_variance` for the smallest error a reference is compared
    against: the RMSE of one render of the least noisy of ``stacks`` (each K
    independent renders, (K, H, W, C)), from its own spread. Zero-variance
    stacks (e.g. the cosine estimator in a furnace) have no error to resolve.

    With ``epsilon`` > 0 the target is no finer than RESOLUTION · ε of the
    image's rms (the least noisy stack's mean): an estimator whose error is
    far below what the checks resolve (a quadrature at 2 000× less variance
    than `path`) no longer drives the reference to its cap; its relMSE is
    read net of the reference's share, on the rungs where it is above it.
    It stays at most BARS_SHARE of the variance of each stack in ``bars``
    (renders with error bars), whose calibration needs it."""
    noise = sorted((metrics.variance_per_render(x[..., :3]), i) for i, x in enumerate(stacks))
    noise = [(v, i) for v, i in noise if v > 0]
    target = target_variance(np.sqrt(noise[0][0]) if noise else 0.0, fraction)
    if not len(stacks):
        return target
    least = stacks[noise[0][1] if noise else 0]
    square = float(np.mean(np.asarray(least, np.float64)[..., :3].mean(axis=0) ** 2))
    if epsilon > 0:
        target = max(target, (RESOLUTION * epsilon) ** 2 * square)
    for x in bars:
        v = metrics.variance_per_render(x[..., :3])
        # (bars on an exact render, float32's error, are not calibrated: no target)
        if v > EXACT ** 2 * square:
            target = min(target, BARS_SHARE * v)
    return target


def pass_spp(smallest: int, pixels: int, max_spp: int, expected: float = 0.0,
             wanted: int = PASSES_WANTED) -> int:
    """The samples per pixel of one pass: ``smallest`` (the profile's
    ``reference_spp_per_pass``), doubled until a pass holds PASS_SAMPLES
    samples over ``pixels`` pixels, so that small images are not rendered
    in launches that cost mostly their fixed cost, and, for a reference
    ``expected`` to need that many spp, while ``wanted`` passes of the
    doubled size would not exceed them; never so large that MIN_PASSES
    passes exceed ``max_spp`` (the profile's cap)."""
    spp = max(1, int(smallest))
    while (spp * max(pixels, 1) < PASS_SAMPLES or 2 * spp * wanted <= expected) and \
            2 * spp * MIN_PASSES <= max_spp:
        spp *= 2
    return spp


def expected_spp(renders, spp: int, target: float) -> float:
    """The spp a reference would need to reach ``target`` (see
    :func:`ensure`), judged from ``renders``, K renders of `path` at ``spp``
    ((K, H, W, C)): the variance of one sample is spp × a render's."""
    v = metrics.variance_per_render(np.asarray(renders)[..., :3])
    return float(v * spp / target) if target > 0 and np.isfinite(v) else 0.0


def ensure(ctx, target: float, expected: float = 0.0,
           wanted: int = PASSES_WANTED) -> Reference:
    """Load or render the reference of context ``ctx`` (its scene, $-parameters,
    max_depth, variant and cache; the pass size :func:`pass_spp` gives, the
    profile's caps) until
    mean(variance_of_mean) ≤ ``target``.

    ``expected``: the spp it is expected to need (:func:`expected_spp`),
    which with ``wanted``, the passes that would do, sets the pass size of
    a reference not yet begun (:func:`pass_spp`); one in the cache goes on
    in its own passes.

    Stops early at the profile's ``reference_max_spp`` total samples per pixel
    or ``reference_max_seconds`` of rendering in this call, and records which
    cap it hit in ``capped``.

    Passes are folded in one at a time, pass i with seed i of the "reference"
    stream, and the rules are read after each: the result does not depend on
    how many the executor renders at once (:func:`_batch`; passes beyond the
    stopping point are dropped), but for the time cap, which is read only
    before more passes are rendered (a time cap is not reproducible anyway).
    """
    profile = ctx.run.profile
    max_spp = profile.reference_max_spp
    w, h = ctx.scene.sensors()[0].film().crop_size()
    max_seconds, cache_dir = profile.reference_max_seconds, ctx.run.cache_dir
    key = ctx.scene_key                   # cache_key(), computed when the scene loaded
    ref = load(cache_dir, key)
    # (passes of one size: a cached reference goes on in its own)
    spp_per_pass = ref.spp_per_pass if ref is not None else \
        pass_spp(profile.reference_spp_per_pass, int(w) * int(h), max_spp, expected, wanted)
    integrator = jobs.make("path", ctx.params)
    stream = ctx.run.stream("reference")
    start, rendered = time.perf_counter(), 0

    def need_more(r):
        return r is None or r.passes < MIN_PASSES or \
            float(r.variance_of_mean.mean()) > target

    caps = [max_spp, max_seconds]
    if ref is not None and ref.meta.get("capped") and ref.meta.get("caps") == caps and \
            target >= ref.meta.get("target_variance", np.inf):
        # an earlier run hit these caps chasing this target or a stricter one:
        # a re-run does not chase it again (a time cap would render every run)
        ref.capped = ref.meta["capped"]

    outs = []                             # rendered, not yet folded in
    while need_more(ref) and not (ref is not None and ref.capped):
        if ref is not None and ref.spp + spp_per_pass > max_spp:
            ref.capped = f"spp cap {max_spp}"
            break
        if not outs:
            # (the clock is read before rendering more, never against passes
            # already rendered: those are folded in)
            if ref is not None and rendered and time.perf_counter() - start > max_seconds:
                ref.capped = f"time cap {max_seconds:g} s"
                break
            done = ref.passes if ref else 0
            n = _batch(ref, target, ctx.run.executor.parallelism, (max_spp // spp_per_pass) - done,
                       max_seconds - (time.perf_counter() - start))
            outs = ctx.render([ctx.job(integrator, spp_per_pass, stream.seed(done + i))
                               for i in range(n)], None)
        out = outs.pop(0)
        x = out.image[..., :3].astype(np.float64)
        rendered += 1
        if ref is None:
            ref = Reference(x, np.zeros_like(x), 1, spp_per_pass, out.seconds,
                            x.mean(axis=(0, 1))[None], key)
        else:  # Welford update of mean and M2 over pass means
            n = ref.passes + 1
            delta = x - ref.mean
            ref.mean = ref.mean + delta / n
            ref.m2 = ref.m2 + delta * (x - ref.mean)
            ref.passes, ref.seconds = n, ref.seconds + out.seconds
            ref.image_means = np.vstack([ref.image_means, x.mean(axis=(0, 1))])
        ctx.run.step(f"reference pass {ref.passes} ({ref.spp} spp)")
    ref.meta = {"target_variance": target, "rendered_passes": rendered}
    if ref.capped:
        ref.meta.update(capped=ref.capped, caps=caps)
    if rendered:
        save(ref, cache_dir)
    return ref


def _batch(ref: Reference | None, target: float, parallelism: int, room: int,
           seconds_left: float = np.inf) -> int:
    """How many passes to render at once: 1 with one worker; else the passes
    the reference still needs (to MIN_PASSES, then by variance ∝ 1/passes),
    at least one per worker, at most 64 per worker, ``room`` (the spp cap)
    and what fits in ``seconds_left`` (the time cap) at the passes' pace so far."""
    if parallelism <= 1:
        return 1
    passes = ref.passes if ref else 0
    if ref is not None and ref.seconds > 0:
        room = min(room, max(1, int(seconds_left * parallelism * passes / ref.seconds)))
    if passes < MIN_PASSES:
        need = MIN_PASSES - passes
    else:
        ratio = float(ref.variance_of_mean.mean()) / target if target > 0 else np.inf
        # (a noiseless target, or a variance that is not finite: until a cap)
        need = int(np.ceil(passes * ratio)) - passes if np.isfinite(ratio) else 64 * parallelism
    return max(1, min(max(need, parallelism), 64 * parallelism, room))
