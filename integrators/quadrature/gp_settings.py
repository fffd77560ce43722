"""Settings of Bayesian Monte Carlo chosen for the quadrature: the rule
(variant-free numpy; the scene's side is gp_scene.py).

Maximum likelihood (gp_quadrature.fit) picks the ℓ that best explains the
lighting, not the ℓ that integrates it best: under the courtyard map at
N = 64 it picks ℓ = 0.10, below the nodes' spacing, and the estimate is 18×
worse than Fibonacci averaging at 64 spp. The rule here scores every
candidate (mapping, noise, ℓ) by the error it gives a pixel on integrals
whose answer is known (held-out integrals of the scene's own map) and keeps
the best where it beats the safe candidate by more than its noise.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .gp_quadrature import GOLDEN, MAPPINGS, Weights, lobe_directions, set_shift, weights

#: σ_n²/σ² tried by :func:`choose`: an interpolating GP, a smoothing one, and
#: one that is nearly an equal-weight average (the heavy-tailed maps' best).
NOISES = (1e-3, 1e-1, 10.0)
#: The ℓ tried (radians), those at or above the floor of the N used: one
#: grid for every N, so kernel means are shared (beyond 2, k̃ is nearly
#: flat on the hemisphere).
LENGTH_SCALES = np.geomspace(0.08, 2.0, 15)


#: Lobe exponents the glossy set is tabulated for, four per octave from 1 to
#: 1024: a shading point takes the nearest to its lobe's n (in log n). The
#: GP then models L_i·cos^{n − n_q}·cos θ, which an exponent an octave off
#: makes vary as much as the lobe itself: the weights erred by 2-4 % on it.
STEPS_PER_OCTAVE = 4
EXPONENTS = tuple(2.0 ** (k / STEPS_PER_OCTAVE) for k in range(10 * STEPS_PER_OCTAVE + 1))
#: The glossy set's ℓ tried, in lobe widths √(2/(n + 1)) (the kernel then
#: spans as many of the lobe's nodes whatever its width).
LOBE_LENGTH_SCALES = (0.5, 0.71, 1.0, 1.41, 2.0, 2.83)


def nearest_exponent(n: float) -> float:
    """The EXPONENTS entry nearest ``n`` in log n (the first below it, the last above)."""
    k = int(np.clip(np.round(np.log2(max(float(n), 1.0)) * STEPS_PER_OCTAVE), 0,
                    len(EXPONENTS) - 1))
    return EXPONENTS[k]


def lobe_width(exponent: float) -> float:
    """√(2/(n + 1)): about the rms angle of the lobe cosⁿ α (1 for n = 1)."""
    return float(np.sqrt(2.0 / (exponent + 1.0)))


def length_scale_floor(n: int) -> float:
    """Half the spacing of n nodes on the hemisphere, ½·√(2π/n) (0.31 at
    N = 16, 0.16 at N = 64): below it the posterior mean falls back to the
    prior mean between the nodes."""
    return 0.5 * float(np.sqrt(2 * np.pi / n))


def length_scale_grid(n: int) -> np.ndarray:
    """The ℓ tried at N = n: LENGTH_SCALES from :func:`length_scale_floor` up."""
    return LENGTH_SCALES[LENGTH_SCALES >= length_scale_floor(n)]


def sphere_directions(m: int) -> np.ndarray:
    """m near-uniform directions on the whole sphere (a Fibonacci sphere)."""
    j = np.arange(m)
    z = 1.0 - (2.0 * j + 1.0) / m
    phi = 2.0 * np.pi * np.mod(j / GOLDEN, 1.0)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (s, t) of each unit normal, rows of (M, 3) (Duff et
    al. 2017: continuous except at n = −z)."""
    n = np.asarray(normals, np.float64)
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def held_out_directions(normals: np.ndarray, n: int, mapping: str, sets: int,
                        turns: int, exponent: float = 1.0) -> np.ndarray:
    """The nodes about each of M unit normals at every (set, turn) of a grid
    of sets × turns shading points: sample k takes set s = k mod ``sets``
    (:func:`set_shift`) and turn t = k div ``sets``, turned about the normal
    by frac(m/Φ + (t + (s + ½)/sets)/turns) of 2π (evenly spaced turns, each
    set's own offset). World directions (M, sets·turns, n, 3). With
    ``mapping`` "lobe", the nodes of the Phong lobe of ``exponent`` about
    each of the M unit axes given as ``normals``."""
    m, k = len(normals), np.arange(sets * turns)
    shifts = np.array([set_shift(s, sets, n) for s in range(sets)])[k % sets]
    u = np.mod((np.arange(n) + 0.5) / n + shifts[:, None], 1.0)         # (K, n)
    turn = np.mod(np.mod(np.arange(m) / GOLDEN, 1.0)[:, None]
                  + (k // sets + (k % sets + 0.5) / sets) / turns, 1.0)  # (m, K)
    v = np.mod(np.arange(n) / GOLDEN + turn[..., None], 1.0)
    u = np.broadcast_to(u, (m, len(k), n))
    local = lobe_directions(u, v, exponent) if mapping == "lobe" else MAPPINGS[mapping](u, v)
    return to_frames(local, normals)


def to_frames(local: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Directions given about +z turned into the frame of each of M unit
    ``axes`` (:func:`tangent_frames`): ``local`` (M or 1, ..., 3) → (M, ..., 3)."""
    axes = np.asarray(axes, np.float64)
    s, t = tangent_frames(axes)
    shape = (len(axes),) + (1,) * (local.ndim - 2) + (3,)
    return (local[..., :1] * s.reshape(shape) + local[..., 1:2] * t.reshape(shape)
            + local[..., 2:] * axes.reshape(shape))


def held_out_errors(values: np.ndarray, truth: np.ndarray, a: np.ndarray,
                    spp: int = 1) -> np.ndarray:
    """The relative squared error a pixel of ``spp`` shading points gets from
    the weights ``a`` (sets, n), per held-out normal.

    ``values`` (M, K, n) is the map at the nodes of the K = sets × turns
    shading points of :func:`held_out_directions` about each of M normals,
    ``truth`` (M,) their integrals. Per normal, with e_k = Σ_j a_{k mod
    sets, j} Y_kj − I, a pixel whose spp shading points draw set and turn at
    random errs by b² + v/spp: b, the mean of e over the grid, is the part
    spp does not average away (a quadrature's errors about one normal are
    correlated), v the variance over the grid. The grid's evenly spaced
    turns make its mean a quadrature in the turn, not a random sample of it:
    no correction for noise, which at K ≪ spp would swamp v/spp. Normals
    whose integral is below 1e-6 of the largest are left out.
    """
    values, truth = np.asarray(values, np.float64), np.asarray(truth, np.float64)
    a = np.atleast_2d(np.asarray(a, np.float64))
    k = values.shape[1]
    keep = truth > 1e-6 * truth.max()
    err = np.einsum("mkn,kn->mk", values[keep], a[np.arange(k) % len(a)]) - truth[keep, None]
    mse = np.square(err.mean(axis=1)) + err.var(axis=1) / spp
    return mse / np.square(truth[keep])


def held_out_relmse(values: np.ndarray, truth: np.ndarray, a: np.ndarray,
                    spp: int = 1) -> float:
    """:func:`held_out_errors`, mean over the normals."""
    return float(np.mean(held_out_errors(values, truth, a, spp)))


def set_weights(n: int, length_scale: float, noise: float, prior_mean: str, mapping: str,
                sets: int, exponent: float = 1.0) -> list[Weights]:
    """:func:`weights` of each of ``sets`` shifted sets (:func:`set_shift`)."""
    return [weights(n, length_scale, noise, prior_mean, mapping, set_shift(s, sets, n),
                    exponent) for s in range(sets)]


def calibration_factor(values: np.ndarray, truth: np.ndarray, tables: list[Weights]) -> float:
    """κ that makes the posterior variance predict, on the held-out set, the
    part of a pixel's error that spp does not average away.

    Per shading point the renderer predicts p = c_s·σ̂², σ̂² from its N
    values by moments (gp_quadrature.Weights: error factor c, amplitude
    divisor); per normal that part is b², the squared mean of the shading
    points' errors (held_out_errors). κ = Σ b²/I² ÷ Σ mean(p)/I² over the
    normals; 1 where the posterior variance is 0 everywhere. (The part that
    does average away the renderer measures itself: the spread of a pixel's
    camera samples.)"""
    values, truth = np.asarray(values, np.float64), np.asarray(truth, np.float64)
    keep = truth > 1e-6 * truth.max()
    y, t = values[keep], truth[keep]
    k = y.shape[1]
    which = np.arange(k) % len(tables)
    a = np.array([w.weights for w in tables])[which]
    c = np.array([w.error_factor / w.amplitude_divisor for w in tables])[which]
    b = (np.einsum("mkn,kn->mk", y, a) - t[:, None]).mean(axis=1)
    if tables[0].prior_mean == "constant":
        spread = np.sum(np.square(y - y.mean(axis=2, keepdims=True)), axis=2)
    else:
        spread = np.sum(np.square(y), axis=2)
    predicted = np.mean(c * spread, axis=1)
    denominator = float(np.sum(predicted / t ** 2))
    return float(np.sum(b ** 2 / t ** 2) / denominator) if denominator > 0 else 1.0


@dataclass(frozen=True)
class Candidate:
    mapping: str
    noise: float
    length_scale: float
    relmse: float                # held_out_relmse; inf where the solve failed


@dataclass(frozen=True)
class Choice:
    """The candidate with the least held-out error, and every one tried."""

    mapping: str
    noise: float
    length_scale: float
    relmse: float
    candidates: tuple[Candidate, ...]
    #: calibration_factor of the choice: what its posterior variance is scaled by
    calibration: float = 1.0


#: How many standard errors a candidate must beat the safe one by (the
#: held-out set sees a map's small bright patches rarely: on `forest` its
#: ranking of candidates 13 % apart flips with the held-out set's size).
SIGNIFICANCE = 2.0


def choose(values: dict, truth: np.ndarray, n: int, noises=NOISES, length_scales=None,
           prior_mean: str = "constant", sets: int = 1, spp: int = 1,
           exponent: float = 1.0) -> Choice:
    """The (mapping, noise, ℓ) whose weights give a pixel of ``spp`` shading
    points the least error on the held-out set (:func:`held_out_errors`),
    where it beats the safe candidate significantly; else the safe one.

    The safe candidate is the first mapping's with the largest noise and ℓ:
    nearly equal weights, which lose little to plain averaging anywhere. A
    candidate replaces it only if its mean error over the held-out normals
    is lower by more than SIGNIFICANCE standard errors of the paired
    per-normal differences (with one normal, never). ``values`` maps each mapping tried to its
    (M, K, n) node values (at :func:`held_out_directions` with ``sets``);
    ``noises`` and ``length_scales`` (default :func:`length_scale_grid`)
    are the candidates (one value each where the user fixed it); a mapping
    "lobe" scores the Phong lobe of ``exponent``. Raises ValueError if no
    candidate can be solved.
    """
    grid = length_scale_grid(n) if length_scales is None else np.asarray(length_scales)
    rows, errors = [], []
    with warnings.catch_warnings():
        # (conditioning: the jitter added is part of the candidate being scored)
        warnings.simplefilter("ignore", RuntimeWarning)
        for mapping, y in values.items():
            for noise in noises:
                for ell in grid:
                    try:
                        a = [w.weights for w in set_weights(n, float(ell), float(noise),
                                                            prior_mean, mapping, sets,
                                                            exponent)]
                        e = held_out_errors(y, truth, np.array(a), spp)
                    except ValueError:
                        e = None
                    errors.append(e)
                    rows.append(Candidate(mapping, float(noise), float(ell),
                                          float(np.mean(e)) if e is not None else np.inf))
    first = next(iter(values))
    safe = max((i for i, c in enumerate(rows) if c.mapping == first and errors[i] is not None),
               key=lambda i: (rows[i].noise, rows[i].length_scale), default=None)
    if safe is None:
        raise ValueError(f"bayesian_hemisphere: no candidate hyperparameters could be "
                         f"solved at N = {n}; give `length_scale` and `noise` explicitly")
    best = min(range(len(rows)), key=lambda i: rows[i].relmse)
    d = errors[safe] - errors[best]
    if best != safe and (len(d) < 2 or
                         d.mean() <= SIGNIFICANCE * d.std(ddof=1) / np.sqrt(len(d))):
        best = safe
    c = rows[best]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        tables = set_weights(n, c.length_scale, c.noise, prior_mean, c.mapping, sets, exponent)
    return Choice(c.mapping, c.noise, c.length_scale, c.relmse, tuple(rows),
                  calibration_factor(values[c.mapping], truth, tables))
