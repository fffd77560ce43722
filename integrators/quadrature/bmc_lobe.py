"""The lobe set of the Bayesian hemisphere estimator (bayesian_hemisphere.py)
at glossy shading points.

At a shading point whose BSDF has a glossy lobe (``phong``,
``roughconductor``, ``roughplastic``, ...), N_b = ⌊N/2⌋ of the directions
(for N ≥ 4) form a second set about the mirror direction r, mapped by a
Phong lobe p_n(ω) = (n + 1)/(2π) cosⁿ α whose exponent is read off the BSDF
(n = 2π p_glossy(r) − 1, exact for ``phong``; lowered where the lobe falls
slower than cosⁿ α, so that a GGX lobe's power-law tails lie inside p_n:
``phong.covering_exponent``) and rounded to the nearest of 41 tabulated
exponents in log n (four per octave, 1 to 1024: gp_settings.EXPONENTS), so
that its weights are tabulated like the diffuse set's (bmc_weights.py).

The sets split the integral, not the samples: the lobe set integrates
f_glossy cos θ L_i where r·ω > 0 against p_n, the other N − N_b directions
everything else against cos θ/π, each with its own BMC weights and
posterior variance (they add). The diffuse set's settings are chosen as a
plain point's are, for N − N_b nodes; the lobe set's ℓ (in lobe widths
√(2/(n + 1)), 0.5 to 2.83) and σ_n²/σ² by the same rule on held-out lobes:
the map integrated against the lobe about the mirror directions of the
glossy surfaces the camera sees, at the median of their exponents
(gp_scene.choose_lobe_settings; without a map to score on:
:data:`LOBE_LENGTH_SCALE` and :data:`LOBE_NOISE`). The GP then models
L_i·f cos/p_n on the lobe, smooth where the lobe is a Phong lobe of the
tabulated exponent.
"""

from __future__ import annotations

from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..bsdfs.phong import covering_exponent, sample_phong_lobe
from . import gp_settings
from .fibonacci_hemisphere import fibonacci_point
from .gp_scene import choose_lobe_settings

#: (The lobe exponents tabulated: gp_settings.EXPONENTS.)
STEPS_PER_OCTAVE, EXPONENTS = gp_settings.STEPS_PER_OCTAVE, gp_settings.EXPONENTS

#: The lobe set's ℓ in lobe widths √(2/(n + 1)) and its σ_n²/σ² where
#: nothing is there to choose them by (no map, a constant one, no glossy
#: surface in view). On SG lighting of sharpness 4 and 32 inside a cos³⁰
#: lobe (a numpy study, 8 and 32 nodes) they gave 0.22-0.57× the squared
#: error of equal weights.
LOBE_LENGTH_SCALE, LOBE_NOISE = 1.0, 1e-3


class SplitSettings(NamedTuple):
    """The settings of a glossy point's two sets: the diffuse set's (for its
    N − N_b nodes) and the lobe set's (ℓ in lobe widths)."""

    length_scale: float
    noise: float
    mapping: str
    calibration: float
    lobe_length_scale: float
    lobe_noise: float
    lobe_calibration: float


def lobes(ctx: mi.BSDFContext, flags) -> mi.BSDFContext:
    """``ctx`` restricted to the lobes of ``flags`` (what it enables of them)."""
    return mi.BSDFContext(ctx.mode, ctx.type_mask & +flags, ctx.component)


def lobe_index(exponent):
    """Index into EXPONENTS of the tabulated exponent nearest ``exponent`` in
    log n (the first below it, the last above)."""
    k = dr.round(dr.log2(dr.maximum(exponent, 1.0)) * STEPS_PER_OCTAVE)
    return mi.UInt32(dr.clip(k, 0.0, len(EXPONENTS) - 1.0))


def split_settings(scene, diffuse: tuple, n_b: int, prior_mean: str, sets: int,
                   spp: int) -> tuple[SplitSettings, object, float | None]:
    """(the two sets' settings, the lobe set's gp_settings.Choice or None,
    the exponent it was scored at or None) on ``scene``: the diffuse set's
    ``diffuse`` (ℓ, σ_n²/σ², mapping, calibration) and the lobe set's,
    chosen on held-out lobes for ``n_b`` nodes."""
    choice, scored_at = choose_lobe_settings(scene, n_b, prior_mean, sets, spp)
    if choice is None:
        return SplitSettings(*diffuse, LOBE_LENGTH_SCALE, LOBE_NOISE, diffuse[3]), None, None
    return SplitSettings(*diffuse, choice.length_scale / gp_settings.lobe_width(scored_at),
                         choice.noise, choice.calibration), choice, scored_at


def draw_lobe(sampler, si, bsdf, ctx, active):
    """(whether the point has a lobe towards the viewer, its exponent's
    index, the lobe set's turn about r). The exponent is read off the
    glossy density at the mirror direction (0 there: no lobe, one set),
    lowered where the lobe's tails are heavier than a Phong lobe's."""
    glossy, r = lobes(ctx, mi.BSDFFlags.Glossy), mi.reflect(si.wi)
    peak = bsdf.pdf(glossy, si, r, active)
    lobe = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy) & (peak > 0)
    q = lobe_index(covering_exponent(lambda w: bsdf.pdf(glossy, si, w, lobe), r, peak))
    return lobe, q, sampler.next_1d(active)


def lobe_node(j_b, n_b: int, which, sets: int, turn_b, q, si):
    """(r, ω in r's frame, n) of node ``j_b`` of the lobe set: (n + 1)/(2π)
    cosⁿ α about the mirror direction r, u shifted by set ``which``'s
    shift (gp_quadrature.set_shift)."""
    n_q = dr.exp2(mi.Float(q) / STEPS_PER_OCTAVE)
    shift_b = ((mi.Float(which) + 0.5) / sets - 0.5) / n_b
    r = mi.reflect(si.wi)
    return r, sample_phong_lobe(fibonacci_point(j_b, n_b, mi.Point2f(shift_b, turn_b)), n_q), n_q
