"""Settings of Bayesian Monte Carlo chosen for the quadrature: the scene's
side (Mitsuba). The environment map evaluated and integrated about the
normals the camera sees, handed to the rule in gp_settings.py, and the
maximum-likelihood ℓ that ``length_scale = likelihood`` asks for.

What ``auto`` does (bayesian_hemisphere.py): each candidate (ℓ from half the
nodes' spacing, ½√(2π/N), to 2; σ_n²/σ² of 0.001, 0.1 and 10; both mappings)
is scored by the relative squared error a pixel of the render's spp would
get on known integrals, the scene's environment map integrated against
cos θ/π about the normals of 64 surface points the camera sees (exactly, by
the map's own importance sampling), every set at evenly spaced turns. The
least error wins where it beats the safe candidate (largest σ_n² and ℓ:
nearly equal weights) by more than two standard errors of the paired
per-normal differences; else the safe one. Chosen once per map, N, spp and
camera view, and cached."""

from __future__ import annotations

import hashlib

import drjit as dr
import mitsuba as mi
import numpy as np

from . import gp_quadrature, gp_settings
from ..bsdfs.phong import covering_exponent
from .gp_settings import sphere_directions

#: The settings ``auto`` stands for where the scene has no environment map,
#: or a constant one, to choose them by.
DEFAULT_LENGTH_SCALE, DEFAULT_NOISE, DEFAULT_MAPPING = 0.5, 1e-3, "cosine"
#: Environment samples that fingerprint a map (and that ``likelihood`` fits ℓ to).
FIT_SAMPLES = 512


def environment_values(env, d: np.ndarray) -> np.ndarray:
    """The environment's radiance towards unit directions ``d`` (m, 3),
    averaged over channels: (m,)."""
    m = len(d)
    if dr.is_jit_v(mi.Float):
        si = dr.zeros(mi.SurfaceInteraction3f, m)
        si.wi = -mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])
        si.wavelengths = _visible(si.wavelengths)
        values = np.array(env.eval(si), dtype=float)    # (channels, m), or (channels,)
        values = np.broadcast_to(values.reshape(values.shape[0], -1), (values.shape[0], m)).T
    else:
        values = []
        for x, y, z in d:
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.wi = -mi.Vector3f(x, y, z)
            si.wavelengths = _visible(si.wavelengths)
            values.append(np.array(env.eval(si), dtype=float).ravel())
        values = np.array(values)
    return values.reshape(m, -1).mean(axis=1)


def environment_samples(scene, m: int = FIT_SAMPLES):
    """(directions, radiance averaged over channels) of the scene's environment
    at m directions; None if the scene has none."""
    env = scene.environment()
    if env is None:
        return None
    d = sphere_directions(m)
    return d, environment_values(env, d)


def informative_samples(scene):
    """(environment_samples, None) where the scene's map varies; (None, why
    not) where it has none or a constant one (nothing to fit or score)."""
    samples = environment_samples(scene)
    if samples is None:
        return None, "no environment map"
    y = samples[1]
    if np.ptp(y) <= 1e-6 * max(float(np.abs(y).max()), 1e-30):    # (float32 texels)
        return None, "the environment is constant: nothing to choose by"
    return samples, None


def _visible(wavelengths):
    """Wavelengths across the visible range (spectral variants evaluate the
    map at these; RGB and mono variants ignore them)."""
    if not mi.is_spectral:
        return wavelengths
    return type(wavelengths)(*(mi.Float(450.0 + 200.0 * i / (len(wavelengths) - 1))
                               for i in range(len(wavelengths))))


# ------------------------- The held-out integrals ------------------------
# Known answers to score hyperparameters on (gp_settings.choose): the map
# integrated against cos θ/π about the normals of the surfaces the camera sees
# at HELD_OUT_NORMALS film positions (the lighting that matters is the one
# about those: forest's best setting for the whole sphere is 2.3× worse than
# another for the lone sphere's front), by TRUTH_SAMPLES of the
# emitter's own importance sampling (a sun is found, not waited for); and the
# map at the N nodes of HELD_OUT_SAMPLES shading points about each normal:
# every set, each at evenly spaced turns.

HELD_OUT_NORMALS = 64
#: Shading points per held-out normal, at least: sets × turns, turns >= 4.
HELD_OUT_SAMPLES = 64
TRUTH_SAMPLES = 1 << 14
#: Shifted node sets a render draws from (``sets``).
DEFAULT_SETS = 16


def held_out_normals(scene, m: int = HELD_OUT_NORMALS) -> np.ndarray:
    """The shading normals, turned towards the camera, of the surfaces seen
    through a 4√m × 4√m grid of film positions of the first sensor, m of
    them evenly spaced in the grid's order where more rays hit (a small
    object in view still gives m); a Fibonacci sphere of m directions where
    fewer than m/8 rays hit a surface."""
    return held_out_surface(scene, m)[0]


def held_out_surface(scene, m: int = HELD_OUT_NORMALS):
    """(normals, origins) of :func:`held_out_normals`: the origins (M, 3) are
    the surface points, moved off the surface along the normal, that the
    held-out rays leave from (None with the Fibonacci sphere)."""
    n, d, p = _film_hits(scene, m, (3, 3, 3),
                         lambda si, ray: (si.is_valid(), si.sh_frame.n, ray.d, si.p))
    if len(n) < max(1, m // 8):
        return sphere_directions(m), None
    n = n * np.where(np.sum(n * d, axis=1) > 0, -1.0, 1.0)[:, None]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, off_surface(p, n)


def _film_hits(scene, m: int, dims: tuple, probe) -> list[np.ndarray]:
    """What ``probe(si, ray)`` reads at the surfaces the first sensor sees
    through a 4√m × 4√m grid of film positions. It returns (mask, values...),
    each value of ``dims`` components (3 or 1); the rows where the mask
    holds, at most m evenly spaced in the grid's order, come back as one
    array per value, (M, 3) or (M,). Scalar variants trace one ray at a
    time and probe only valid hits (an invalid one has no BSDF to ask)."""
    side = 4 * int(round(m ** 0.5))
    g = (np.arange(side) + 0.5) / side
    x, y = [a.ravel() for a in np.meshgrid(g, g)]
    sensor = scene.sensors()[0]

    def column(value, dim, count):
        # (a value the same for every ray, as an orthographic camera's
        # direction, comes back as one entry)
        a = np.array(value, dtype=float).reshape(dim, -1).T
        return np.broadcast_to(a, (count, dim))

    if dr.is_jit_v(mi.Float):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
        mask, *values = probe(scene.ray_intersect(ray), ray)
        keep = np.broadcast_to(np.array(mask, dtype=bool).reshape(-1), (len(x),))
        found = [column(v, dim, len(x))[keep] for v, dim in zip(values, dims)]
    else:
        rows = []
        for px, py in zip(x, y):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px, py), mi.Point2f(0.5, 0.5))
            si = scene.ray_intersect(ray)
            if si.is_valid():
                mask, *values = probe(si, ray)
                if mask:
                    rows.append([column(v, dim, 1) for v, dim in zip(values, dims)])
        found = [np.concatenate([r[i] for r in rows]) if rows else np.zeros((0, dim))
                 for i, dim in enumerate(dims)]
    if len(found[0]) > m:
        pick = np.linspace(0, len(found[0]) - 1, m).round().astype(int)
        found = [f[pick] for f in found]
    return [f if dim == 3 else f[:, 0] for f, dim in zip(found, dims)]


def off_surface(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Points moved off their surface along the normal, by 1e-4 of their
    distance from the origin (at least 1e-4): rays leaving them do not find
    the surface they start on."""
    scale = 1e-4 * np.maximum(1.0, np.linalg.norm(points, axis=1, keepdims=True))
    return points + scale * normals


def unoccluded(scene, origins: np.ndarray | None, directions: np.ndarray) -> np.ndarray:
    """Whether the rays from each of M ``origins`` (M, 3) along its
    ``directions`` (M, ..., 3) leave the scene, i.e. see the environment:
    bool, ``directions.shape[:-1]``. All True without ``origins`` (nothing
    occludes: the map alone) and in scalar variants, which do not trace
    them (a Python call per ray)."""
    shape = directions.shape[:-1]
    if origins is None or not dr.is_jit_v(mi.Float) or directions.size == 0:
        return np.ones(shape, dtype=bool)
    o = np.repeat(origins, int(np.prod(shape[1:])), axis=0).astype(np.float32)
    d = directions.reshape(-1, 3).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    return ~np.broadcast_to(np.array(scene.ray_test(ray), dtype=bool), (len(d),)).reshape(shape)


def held_out_truth(env, normals: np.ndarray, samples: int = TRUTH_SAMPLES,
                   scene=None, origins: np.ndarray | None = None) -> np.ndarray:
    """I(n) = ∫ L(ω) V(ω) max(0, ω·n)/π dω for each normal, channel mean,
    from ``samples`` draws of the emitter's sample_direction (L/p per draw)
    at the points of a Fibonacci lattice, shared by all normals. V is 1
    where the ray from the normal's origin escapes the ``scene`` (with
    ``origins``; else 1 everywhere: the map alone)."""
    u = np.stack(gp_quadrature.fibonacci_square(samples), axis=1)
    if dr.is_jit_v(mi.Float):
        it = dr.zeros(mi.Interaction3f, samples)
        it.wavelengths = _visible(it.wavelengths)
        ds, w = env.sample_direction(it, mi.Point2f(u[:, 0], u[:, 1]))
        d = np.array(ds.d, dtype=float).T
        w = np.array(w, dtype=float)
        w = np.broadcast_to(w.reshape(w.shape[0], -1), (w.shape[0], samples)).T
    else:
        d, w = [], []
        for x, y in u:
            it = dr.zeros(mi.Interaction3f)
            it.wavelengths = _visible(it.wavelengths)
            ds, weight = env.sample_direction(it, mi.Point2f(x, y))
            d.append(np.array(ds.d, dtype=float).ravel())
            w.append(np.array(weight, dtype=float).ravel())
        d, w = np.array(d), np.array(w)
    w = w.reshape(samples, -1).mean(axis=1)
    cos = np.maximum(normals @ d.T, 0.0)
    cos *= unoccluded(scene, origins, np.broadcast_to(d, (len(normals),) + d.shape))
    return cos @ w / (np.pi * samples)


def held_out_values(env, normals: np.ndarray, n: int, mapping: str, sets: int,
                    scene=None, origins: np.ndarray | None = None,
                    exponent: float = 1.0) -> np.ndarray:
    """The light at gp_settings.held_out_directions: (M, K, n), K = sets ×
    turns, turns = max(4, ⌈HELD_OUT_SAMPLES/sets⌉): the map where the ray
    from the normal's origin escapes the ``scene``, 0 where it is blocked
    (with ``origins``; else the map alone)."""
    turns = max(4, -(-HELD_OUT_SAMPLES // sets))
    world = gp_settings.held_out_directions(normals, n, mapping, sets, turns, exponent)
    values = environment_values(env, world.reshape(-1, 3)).reshape(world.shape[:-1])
    return values * unoccluded(scene, origins, world)


#: (map fingerprint, N, fixed settings) → gp_settings.Choice
_chosen: dict = {}
#: (map fingerprint, noise) → maximum-likelihood ℓ
_fitted: dict = {}


def likelihood_length_scale(scene, noise: float) -> float:
    """ℓ by maximum marginal likelihood over FIT_SAMPLES directions of the
    scene's environment (the lighting's own scale, not the quadrature's);
    DEFAULT_LENGTH_SCALE without a map or for a constant one."""
    samples, _ = informative_samples(scene)
    if samples is None:
        return DEFAULT_LENGTH_SCALE
    d, y = samples
    key = (hashlib.sha1(np.ascontiguousarray(y, np.float64).tobytes()).hexdigest(), noise)
    if key not in _fitted:
        _fitted[key] = gp_quadrature.fit(d, y, noise).length_scale
    return _fitted[key]


#: (view fingerprint, N, mappings, sets) → (truth, values): what every spp
#: shares; the last few only (a table of N = 256 holds 8 MB per mapping).
_held_out_cache: dict = {}
HELD_OUT_KEPT = 4


def _held_out(scene, view: str, normals, origins, n: int, mappings: tuple, sets: int):
    key = (view, n, mappings, sets)
    if key not in _held_out_cache:
        while len(_held_out_cache) >= HELD_OUT_KEPT:
            _held_out_cache.pop(next(iter(_held_out_cache)))
        env = scene.environment()
        _held_out_cache[key] = (
            held_out_truth(env, normals, scene=scene, origins=origins),
            {m: held_out_values(env, normals, n, m, sets, scene, origins) for m in mappings})
    return _held_out_cache[key]


def _view(samples, *arrays) -> str:
    """A fingerprint of the map (its samples) and of the held-out geometry."""
    h = hashlib.sha1(np.ascontiguousarray(samples[1], np.float64).tobytes())
    for a in arrays:
        if a is not None:
            h.update(np.round(a, 6).tobytes())
    return h.hexdigest()


def choose_hyperparameters(scene, n: int, length_scale, noise, mapping,
                           prior_mean: str = "constant", sets: int = DEFAULT_SETS,
                           spp: int = 1):
    """The settings ``auto`` leaves open, chosen by the error they give a
    pixel of ``spp`` samples on the scene's own held-out integrals
    (gp_settings.choose); cached per map, N, spp and fixed settings.
    Returns (Choice or None, how it was chosen): None where the scene has no
    environment or a constant one (nothing to score)."""
    samples, why = informative_samples(scene)
    if samples is None:
        return None, f"default ({why})"
    normals, origins = held_out_surface(scene)
    view = _view(samples, normals, origins)
    key = (view, n, length_scale, noise, mapping, prior_mean, sets, spp)
    if key not in _chosen:
        mappings = tuple(gp_quadrature.MAPPINGS) if mapping == "auto" else (mapping,)
        truth, values = _held_out(scene, view, normals, origins, n, mappings, sets)
        _chosen[key] = gp_settings.choose(
            values, truth, n,
            noises=gp_settings.NOISES if noise == "auto" else (noise,),
            length_scales=None if length_scale == "auto" else (length_scale,),
            prior_mean=prior_mean, sets=sets, spp=spp)
    seen = (", what occludes the map included"
            if origins is not None and dr.is_jit_v(mi.Float) else "")
    return _chosen[key], (f"least error at {spp} spp on the environment map's integrals "
                          f"about {len(normals)} normals the camera sees{seen}")


# ------------------------ The glossy set's settings -----------------------
# The same rule for the lobe set of a glossy surface: held-out axes are the
# mirror directions of the camera rays that hit glossy surfaces at the film
# positions of held_out_normals, the known answers the map integrated against
# the lobe about each (by LOBE_TRUTH_SAMPLES of the lobe's own lattice: the
# lobe is what is narrow), scored at the median of their lobes' exponents.

LOBE_TRUTH_SAMPLES = 1 << 12


def held_out_lobes(scene, m: int = HELD_OUT_NORMALS):
    """(axes (M, 3), exponents (M,), origins (M, 3)) at the glossy surfaces the
    first sensor sees through a 4√m × 4√m film grid, M ≤ m evenly spaced in
    the grid's order: the mirror direction of the camera ray about the
    shading normal, the exponent of the Phong lobe of the same density
    there, 2π·p_glossy(r) − 1, widened where the lobe's tails are heavier
    (phong.covering_exponent, as the estimator reads it), and the point
    held-out rays leave from
    (off_surface). Empty arrays where no glossy surface is seen."""
    ctx = mi.BSDFContext()
    ctx.type_mask = +mi.BSDFFlags.Glossy

    def lobe_at(si, ray):
        bsdf = si.bsdf(ray)
        r = mi.reflect(si.wi)
        peak = bsdf.pdf(ctx, si, r, si.is_valid())
        ok = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy) & (peak > 0)
        # (the side the camera sees: the normal turned towards it)
        n = si.to_world(mi.Vector3f(0, 0, dr.sign(si.wi.z)))
        exponent = covering_exponent(lambda w: bsdf.pdf(ctx, si, w, ok), r, peak)
        return ok, si.to_world(r), exponent, si.p, n

    axes, exponents, points, normals = _film_hits(scene, m, (3, 1, 3, 3), lobe_at)
    return axes / np.linalg.norm(axes, axis=1, keepdims=True), exponents, \
        off_surface(points, normals)


def held_out_lobe_truth(env, axes: np.ndarray, exponent: float,
                        samples: int = LOBE_TRUTH_SAMPLES, scene=None,
                        origins: np.ndarray | None = None) -> np.ndarray:
    """∫ L(ω) V(ω) (n + 1)/(2π) cosⁿ α dω about each axis (channel mean), by
    a shifted Fibonacci lattice of ``samples`` points mapped by the lobe; V
    as in :func:`held_out_truth` (1 without ``origins``)."""
    u, v = gp_quadrature.fibonacci_square(samples, 0.0)
    local = gp_quadrature.lobe_directions(u, np.mod(v + 0.5 / samples, 1.0), exponent)
    world = gp_settings.to_frames(local[None], axes)
    values = environment_values(env, world.reshape(-1, 3)).reshape(len(axes), samples)
    return (values * unoccluded(scene, origins, world)).mean(axis=1)


#: (view fingerprint, N_b, exponent, prior mean, sets, spp) → (Choice, exponent)
_lobe_chosen: dict = {}


def choose_lobe_settings(scene, n: int, prior_mean: str = "constant",
                         sets: int = DEFAULT_SETS, spp: int = 1):
    """The lobe set's (ℓ, σ_n²/σ²) for ``n`` nodes, chosen by gp_settings.choose
    on the held-out lobes at the median of their exponents (rounded to
    gp_settings.EXPONENTS), over LOBE_LENGTH_SCALES lobe widths and NOISES.
    Returns (Choice or None, the exponent scored at): None where the scene
    has no varying map or the camera sees no glossy surface."""
    samples, _ = informative_samples(scene)
    if samples is None:
        return None, None
    axes, exponents, origins = held_out_lobes(scene)
    if len(axes) == 0:
        return None, None
    exponent = gp_settings.nearest_exponent(float(np.median(exponents)))
    view = _view(samples, axes, origins)
    key = (view, n, exponent, prior_mean, sets, spp)
    if key not in _lobe_chosen:
        env = scene.environment()
        # (scalar variants evaluate the map in a Python loop: fewer points)
        truth = held_out_lobe_truth(env, axes, exponent, LOBE_TRUTH_SAMPLES
                                    if dr.is_jit_v(mi.Float) else 1 << 9, scene, origins)
        values = held_out_values(env, axes, n, "lobe", sets, scene, origins, exponent)
        width = gp_settings.lobe_width(exponent)
        _lobe_chosen[key] = gp_settings.choose(
            {"lobe": values}, truth, n, noises=gp_settings.NOISES,
            length_scales=[width * r for r in gp_settings.LOBE_LENGTH_SCALES],
            prior_mean=prior_mean, sets=sets, spp=spp, exponent=exponent), exponent
    return _lobe_chosen[key]
