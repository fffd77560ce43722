"""The weight tables of the Bayesian hemisphere estimator
(bayesian_hemisphere.py), laid out for its kernels, and the posterior
variance of one node set.

Each node set's turn about the normal leaves every θ_j, hence z and Q,
unchanged, so its BMC weights a = Q⁻¹z (with the constant-mean correction)
are the same at every pixel: gp_settings.set_weights computes them once per
(N, ℓ, σ_n², set) in float64 and caches them. Here they are flat Dr.Jit
arrays (lists in scalar variants) that a kernel gathers from: the weights of
set s at s·N + j, its error factor c = aᵀQa − 2aᵀz + ∫∫kpp (× the
calibration κ) and its amplitude divisor at s. At a glossy point the lobe
set's tables follow exponent after exponent (bmc_lobe.py): the table of
exponent q and set s is q·sets + s.

The GP's own posterior variance c·σ̂² is off by orders of magnitude (× 1400
on the lone sphere under ``sg`` with the settings chosen), so the plugin
scales it by κ, fitted on the held-out integrals
(gp_settings.calibration_factor; 1 without a map to fit on).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from . import gp_settings
from .bmc_lobe import EXPONENTS, SplitSettings


class Flat(NamedTuple):
    """One family of node sets' tables, flat (module doc)."""

    weights: object                 # a_j of table t at t·N + j
    error_factors: object           # κ·c per table
    divisors: object                # amplitude divisor per table


class Tables(NamedTuple):
    """Every table a render gathers from: the plain sets', and at glossy
    points the diffuse set's (N − N_b nodes) and the lobe set's (N_b)."""

    plain: Flat
    split: Flat | None = None       # None: the scene has no glossy lobes
    lobe: Flat | None = None


def flat(tables, calibration: float) -> Flat:
    """(weights, error factors × ``calibration``, amplitude divisors) of
    ``tables`` (gp_settings.Weights), flat, as Dr.Jit arrays (lists in
    scalar variants)."""
    a = [float(x) for t in tables for x in t.weights]
    c = [float(t.error_factor) * calibration for t in tables]
    d = [float(t.amplitude_divisor) for t in tables]
    jit = dr.is_jit_v(mi.Float)
    return Flat(mi.Float(a), mi.Float(c), mi.Float(d)) if jit else Flat(a, c, d)


def gather(table, index, active):
    """``table[index]`` where ``active``, else 0."""
    if dr.is_jit_v(mi.Float):
        return dr.gather(mi.Float, table, index, active)
    return table[int(index)] if active else 0.0


def build(n: int, n_b: int, length_scale: float, noise: float, mapping: str,
          prior_mean: str, sets: int, calibration: float,
          split: SplitSettings | None, quiet: bool) -> Tables:
    """The tables of ``n`` nodes at these settings, and with ``split`` those
    of a glossy point's two sets (``n - n_b`` and ``n_b`` nodes). ``quiet``
    silences the RuntimeWarning of a setting's extra jitter (a chosen
    setting's jitter is part of what was scored)."""
    with warnings.catch_warnings():
        if quiet:
            warnings.simplefilter("ignore", RuntimeWarning)
        plain = flat(gp_settings.set_weights(n, length_scale, noise, prior_mean, mapping,
                                             sets), calibration)
        if split is None:
            return Tables(plain)
        s = split
        split_tables = gp_settings.set_weights(n - n_b, s.length_scale, s.noise, prior_mean,
                                               s.mapping, sets)
        # (ℓ in lobe widths: the same relative kernel at every exponent)
        lobe_tables = [
            t for e in EXPONENTS for t in gp_settings.set_weights(
                n_b, s.lobe_length_scale * gp_settings.lobe_width(e), s.lobe_noise,
                prior_mean, "lobe", sets, e)]
        return Tables(plain, flat(split_tables, s.calibration),
                      flat(lobe_tables, s.lobe_calibration))


def set_variance(prior_mean: str, s1, s2, y0, n, tables: Flat, table, active):
    """κ·c·σ̂² of one set of ``n`` values (sums s1 = Σd, s2 = Σd² of
    d = Y − Y₀), from table ``table`` of ``tables``."""
    n = mi.Float(n)
    # σ̂² by moments: E[Σ(Y − Ȳ)²] = σ² (tr Q − 1ᵀQ1/N) (zero mean: E[ΣY²] = σ² tr Q);
    # Σ(Y − Ȳ)² = Σd² − (Σd)²/N and ΣY² = Σd² + 2Y₀Σd + N Y₀² for d = Y − Y₀
    if dr.hint(prior_mean == "constant", mode='scalar'):
        spread = s2 - dr.square(s1) / n
    else:
        spread = s2 + 2.0 * y0 * s1 + n * dr.square(y0)
    # (an inactive lane gathers d = 0; scalar variants evaluate both sides of a select)
    return (gather(tables.error_factors, table, active) * dr.maximum(spread, 0.0)
            / dr.maximum(gather(tables.divisors, table, active), 1e-30))


def split_variance(prior_mean: str, s1, s2, y0, n: int, n_b: int, drawn, sets: int,
                   tables: Tables, active):
    """The posterior variance where the scene has glossy lobes: at a glossy
    point (``drawn``: the set drawn, bayesian_hemisphere.draw_set) its
    diffuse set's (``n - n_b`` nodes; sums ``s1[0]``, …) plus its lobe
    set's (``n_b``; ``s1[1]``, …), elsewhere the plain set's of ``n``."""
    which, lobe, q = drawn[1], drawn[2], drawn[3]
    n_a = dr.select(lobe, mi.UInt32(n - n_b), mi.UInt32(n))
    # the two sets' posteriors are independent: their variances add
    var_a = dr.select(
        lobe, set_variance(prior_mean, s1[0], s2[0], y0[0], n_a, tables.split, which,
                           active & lobe),
        set_variance(prior_mean, s1[0], s2[0], y0[0], n_a, tables.plain, which,
                     active & dr.select(lobe, False, True)))
    var_b = set_variance(prior_mean, s1[1], s2[1], y0[1], n_b, tables.lobe,
                         q * sets + which, active & lobe)
    return var_a + dr.select(lobe, var_b, 0.0)
