"""Bayesian Monte Carlo (Gaussian-process quadrature) of direct illumination on
diffuse and glossy surfaces, with the posterior standard deviation of every
pixel."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..bsdfs.phong import covering_exponent, phong_lobe_pdf, sample_phong_lobe
from ..core import registry, scene_checks
from ..core.direction_set import DirectionSetEstimator
from ..core.estimator import over_pdf
from . import gp_settings
from .fibonacci_hemisphere import MAPPINGS, fibonacci_point
from .gp_scene import (DEFAULT_LENGTH_SCALE, DEFAULT_MAPPING, DEFAULT_NOISE, DEFAULT_SETS,
                       choose_hyperparameters, choose_lobe_settings, likelihood_length_scale)

PRIOR_MEANS = ("constant", "zero")

# ----------------------------- Strategy ---------------------------------
# Directions: one of `sets` spherical-Fibonacci sets, u shifted between the
# unshifted set's neighbours (gp_quadrature.set_shift), cosine- or
# uniform-mapped, turned about the normal by one random angle per shading
# point: the turn leaves every θ_j, hence z and Q, unchanged, so each set's
# weights a = Q⁻¹z (with the constant-mean correction) are the same at every
# pixel. Drawing the set at random makes a pixel average several sets'
# errors: one fixed set's error about a normal is the same for every turn,
# and spp would not average it away.
#
# Glossy lobes: a second set of N_b = ⌊N/2⌋ nodes about the mirror direction
# r, mapped by a Phong lobe cosⁿ α whose n is read off the BSDF (its glossy
# density at r is (n + 1)/(2π) for a Phong lobe; lowered where the lobe's
# tails are heavier, as GGX's are: phong.covering_exponent), rounded to the
# nearest of gp_settings.EXPONENTS so that its weights are tabulated like
# the diffuse set's. The two sets
# split the integral, not the samples: the lobe set integrates f_glossy cos L
# where r·ω > 0 against p_n, the diffuse set everything else against cos θ/π.

#: (The lobe exponents tabulated: gp_settings.EXPONENTS.)
STEPS_PER_OCTAVE, EXPONENTS = gp_settings.STEPS_PER_OCTAVE, gp_settings.EXPONENTS


def lobes(ctx: mi.BSDFContext, flags) -> mi.BSDFContext:
    """``ctx`` restricted to the lobes of ``flags`` (what it enables of them)."""
    return mi.BSDFContext(ctx.mode, ctx.type_mask & +flags, ctx.component)


def lobe_index(exponent):
    """Index into EXPONENTS of the tabulated exponent nearest ``exponent`` in
    log n (the first below it, the last above)."""
    k = dr.round(dr.log2(dr.maximum(exponent, 1.0)) * STEPS_PER_OCTAVE)
    return mi.UInt32(dr.clip(k, 0.0, len(EXPONENTS) - 1.0))


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


class Unwalked:
    """A plain holder of Python records. Dr.Jit walks a Python plugin's
    attributes (lists, dicts, dataclasses) at every symbolic call it traces;
    an object of another class it does not enter."""

    def __init__(self, value=None):
        self.value = value


# ------------------------------ Plugin ----------------------------------


class BayesianHemisphereIntegrator(DirectionSetEstimator):
    r"""
    .. _integrator-bayesian_hemisphere:

    Bayesian Monte Carlo estimator (:monosp:`bayesian_hemisphere`)
    --------------------------------------------------------------

    .. pluginparameters::

     * - directions
       - |int|
       - N, directions per shading point. (Default: 64)
     * - length_scale
       - |float| or |string|
       - ℓ of the kernel (radians); ``auto`` chooses it for the quadrature
         (below), ``likelihood`` fits it by maximum marginal likelihood to
         512 samples of the scene's environment map (the lighting's own
         scale). (Default: ``auto``)
     * - noise
       - |float| or |string|
       - σ_n²/σ², the noise added to the kernel's diagonal, relative to the
         prior variance (regularises Q; large values tend to equal
         weights); ``auto`` chooses it. (Default: ``auto``)
     * - prior_mean
       - |string|
       - ``constant`` (the mean of the N samples) or ``zero``. (Default: ``constant``)
     * - mapping
       - |string|
       - Where the nodes lie: ``cosine`` (cos θ = √(1 − u), denser near the
         normal) or ``uniform`` (cos θ = 1 − u); the integral is against
         cos θ/π either way; ``auto`` chooses. (Default: ``auto``)
     * - sets
       - |int|
       - Node sets, u shifted between the first set's neighbours, that each
         shading point draws one of at random; 1: one fixed set. (Default: 16)
     * - max_depth
       - |int|
       - 2: direct illumination; 1: only emitters seen directly; others are
         refused. (Default: 2)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content this strategy cannot reach instead of refusing the
         scene; the image is then biased and a warning says so. (Default: |false|)

    Treats the incident radiance over the hemisphere as a Gaussian process,
    L_i ~ GP(L̄, σ² k), k(ω, ω′) = exp((ω·ω′ − 1)/ℓ²), and integrates its
    posterior mean against p(ω) = cos θ / π (Rasmussen & Ghahramani 2003;
    Marques et al. 2013). With z_j = ∫ k(ω, ω_j) p(ω) dω and
    Q = K + σ_n² I, a diffuse surface of albedo ρ gets

        L_r ≈ ρ Σ_j a_j L_i(ω_j),   a = Q⁻¹z + (1 − Σ Q⁻¹z)/N

    (the second term: the constant prior mean L̄ = mean of the samples). The
    directions are one of ``sets`` spherical-Fibonacci sets (shifted in
    u), drawn at random and turned about the normal by a random angle per
    shading point, so each set's z and Q, hence a, are the same everywhere:
    computed once per (N, ℓ, σ_n², set) in float64 and cached. A fixed set
    errs the same way at every turn about a normal, an error spp does not
    average away; drawing among shifted sets averages several sets' errors.

    ``auto`` settings are chosen for the quadrature, not for the lighting:
    each candidate (ℓ from half the nodes' spacing, ½√(2π/N), to 2; σ_n²/σ²
    of 0.001, 0.1 and 10; both mappings) is scored by the relative squared
    error a pixel of the render's spp would get on known integrals, the
    scene's environment map integrated against cos θ/π about the normals
    of 64 surface points the camera sees (exactly, by the
    map's own importance sampling), every set at evenly spaced turns. The
    least error wins where it beats the safe candidate (largest σ_n² and ℓ:
    nearly equal weights) by more than two standard errors of the paired
    per-normal differences; else the safe one. Chosen once per map, N, spp
    and camera view, and cached; ``source`` says how they were chosen and
    ``choice`` holds every candidate's score. Without an environment map,
    or with a constant one, ``auto`` means ℓ = 0.5, σ_n²/σ² = 0.001 and
    cosine nodes.

    The estimate is biased by design (it is a posterior mean, not an
    average of samples), and accurate where the lighting is smooth at scale
    ℓ; a sun or a hard shadow breaks the prior. Every camera sample also
    gives the posterior variance κ · c · σ̂², c = aᵀQa − 2aᵀz + ∫∫kpp and
    σ̂² the prior variance estimated from the N samples by moments. The GP's
    own c·σ̂² is off by orders of magnitude (× 1400 on the lone sphere under
    ``sg`` with the settings chosen), so κ is fitted on the held-out
    integrals, given settings or chosen: the factor that makes it predict
    the part of the error spp does not average away, the squared mean error
    per normal (1 without a map to fit on). It is written as the AOV
    ``posterior_var`` (per channel; one ``Y`` channel in
    mono and spectral variants), which the film averages over the pixel's
    camera samples, beside ``sample_sq``, the film's mean of L². The pixel's
    error bar (``mcillum render`` stores it as the EXR layer
    ``posterior_std``) is √(posterior_var + s²/spp), s² = spp/(spp − 1) ·
    (mean L² − (mean L)²) the spread of its camera samples: the posterior
    variance is not divided by spp, because the samples of one pixel
    integrate nearly the same lighting and a quadrature's errors there are
    correlated; the footprint of the pixel (and the turn of each sample's
    set) adds the independent part. How well it predicts the error is
    measured per scene (``calibrated`` in the validation report).

    Glossy lobes (``phong``, ``roughconductor``, ``roughplastic``, ...): at
    a shading point whose BSDF has one, N_b = ⌊N/2⌋ of the directions (for
    N ≥ 4) form a second set about the mirror direction r, mapped by a
    Phong lobe p_n(ω) = (n + 1)/(2π) cosⁿ α whose exponent is read off the
    BSDF (n = 2π p_glossy(r) − 1, exact for ``phong``; lowered where the
    lobe falls slower than cosⁿ α, so that a GGX lobe's power-law tails lie
    inside p_n: ``phong.covering_exponent``) and rounded to one of 41
    tabulated exponents (four per octave, 1 to 1024). The sets split
    the integral, not the samples: the lobe set integrates f_glossy cos θ L_i
    where r·ω > 0 against p_n, the other N − N_b directions everything else
    against cos θ/π, each with its own BMC weights and posterior variance
    (they add). The diffuse set's settings are chosen as above for N − N_b
    nodes; the lobe set's ℓ (in lobe widths √(2/(n + 1)), 0.5 to 2.83) and
    σ_n²/σ² by the same rule on held-out lobes: the map integrated against
    the lobe about the mirror directions of the glossy surfaces the camera
    sees, at the median of their exponents (without a map to score on: one
    lobe width and 1e-3). The GP then models L_i·f cos/p_n on the lobe,
    smooth where the lobe is a Phong lobe of the tabulated exponent.

    .. tabs::

        .. code-tab:: xml

            <integrator type="bayesian_hemisphere">
                <integer name="directions" value="64"/>
                <float name="length_scale" value="0.5"/>
            </integrator>
    """

    plugin_name = "bayesian_hemisphere"
    display_name = "Bayesian Monte Carlo (GP quadrature)"
    colour = "#8c564b"
    max_direction_pdf = None                   # the lobe set follows the BSDF
    listing_order = 70
    unbiased = False
    #: (its render() reads the scene to choose its settings: not recordable)
    freezable = False

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        ell = props.get("length_scale", "auto")
        if not (ell in ("auto", "likelihood") or (isinstance(ell, (int, float))
                                                  and not isinstance(ell, bool) and ell > 0)):
            raise ValueError(f"{self.plugin_name}: length_scale must be a number > 0, "
                             f"'auto' or 'likelihood', got {ell!r}")
        noise = props.get("noise", "auto")
        if not (noise == "auto" or (isinstance(noise, (int, float))
                                    and not isinstance(noise, bool) and noise >= 0)):
            raise ValueError(f"{self.plugin_name}: noise must be a number >= 0 "
                             f"(σ_n²/σ², e.g. 0.001) or 'auto', got {noise!r}")
        self.prior_mean = props.get("prior_mean", "constant")
        if self.prior_mean not in PRIOR_MEANS:
            raise ValueError(f"{self.plugin_name}: prior_mean must be one of "
                             f"{', '.join(PRIOR_MEANS)}, got {self.prior_mean!r}")
        mapping = props.get("mapping", "auto")
        if mapping != "auto" and mapping not in MAPPINGS:
            raise ValueError(f"{self.plugin_name}: mapping must be one of "
                             f"{', '.join(MAPPINGS)} or 'auto', got {mapping!r}")
        self.sets = props.get("sets", DEFAULT_SETS)
        if isinstance(self.sets, bool) or not isinstance(self.sets, int) or self.sets < 1:
            raise ValueError(f"{self.plugin_name}: sets must be an integer >= 1 (shifted "
                             f"node sets drawn from; 1: one fixed set), got {self.sets!r}")
        if self.prior_mean == "constant" and self.directions < 2:
            raise ValueError(f"{self.plugin_name}: directions = {self.directions} with "
                             "prior_mean 'constant' leaves nothing to estimate the prior "
                             "variance from; use directions >= 2 or prior_mean 'zero'")
        #: What was asked for ('auto', 'likelihood' or a value), per setting.
        self.asked = {"length_scale": ell, "noise": noise, "mapping": mapping}
        #: Whether any setting is chosen for the scene rather than given.
        self.chooses = any(v in ("auto", "likelihood") for v in self.asked.values())
        #: How the settings in use were chosen; the held-out scores (a
        #: gp_settings.Choice) where they were chosen by them.
        self.source, self.choice = "given", None
        #: Directions of the lobe set at a glossy shading point (0: none, the
        #: diffuse set then integrates the lobe too).
        self.lobe_directions = self.directions // 2 if self.directions >= 4 else 0
        #: The SplitSettings in use where the scene last checked has glossy
        #: lobes (None: it has none, no tables for them), the lobe's
        #: gp_settings.Choice and the exponent it was scored at.
        self.split, self.lobe_choice, self.lobe_exponent = None, None, None
        self._use(float(ell) if isinstance(ell, (int, float)) else DEFAULT_LENGTH_SCALE,
                  noise if noise != "auto" else DEFAULT_NOISE,
                  mapping if mapping != "auto" else DEFAULT_MAPPING)

    # -------------------- Hyperparameters and weights ---------------------

    # (the held-out scores are read by reports, never by a kernel: kept out
    # of Dr.Jit's walk, they cost 14 ms less a launch on probe_spheres)
    choice = property(lambda self: self._choice.value,
                      lambda self, v: setattr(self, "_choice", Unwalked(v)))
    lobe_choice = property(lambda self: self._lobe_choice.value,
                           lambda self, v: setattr(self, "_lobe_choice", Unwalked(v)))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not getattr(self, "_in_pass", False):
            # (the settings are chosen for the pixel's sample count)
            sensor_ = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
            self._spp = spp or sensor_.sampler().sample_count()
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def check_scene(self, scene) -> None:
        super().check_scene(scene)
        ell, noise, mapping = (self.asked[k] for k in ("length_scale", "noise", "mapping"))
        if ell == "likelihood":
            ell = likelihood_length_scale(scene, DEFAULT_NOISE if noise == "auto" else noise)
        # (nested in a wrapper, render() was not called: the scene's own count)
        spp = getattr(self, "_spp", None) or scene.sensors()[0].sampler().sample_count()
        glossy = self.lobe_directions > 0 and any(
            p.kind == "glossy_bsdf" for p in scene_checks.unreachable(scene))

        def settings(n):
            # Settings given are scored too, as the only candidate: their posterior
            # variance is calibrated on the same held-out integrals.
            c, how = choose_hyperparameters(scene, n, ell, noise, mapping, self.prior_mean,
                                            self.sets, spp)
            if c is None:
                return None, how, (
                    ell if isinstance(ell, (int, float)) else DEFAULT_LENGTH_SCALE,
                    DEFAULT_NOISE if noise == "auto" else noise,
                    DEFAULT_MAPPING if mapping == "auto" else mapping, 1.0)
            return c, how, (c.length_scale, c.noise, c.mapping, c.calibration)

        self.choice, how, chosen = settings(self.directions)
        self.source = how if self.chooses else "given"
        # (the diffuse set of a glossy point has N − N_b nodes: its own choice;
        # the lobe set's ℓ, in lobe widths, and noise are chosen on held-out lobes)
        split, self.lobe_choice = None, None
        if glossy:
            diffuse = settings(self.directions - self.lobe_directions)[2]
            self.lobe_choice, scored_at = choose_lobe_settings(
                scene, self.lobe_directions, self.prior_mean, self.sets, spp)
            self.lobe_exponent = scored_at if self.lobe_choice is not None else None
            c = self.lobe_choice
            lobe = (LOBE_LENGTH_SCALE, LOBE_NOISE, diffuse[3]) if c is None else (
                c.length_scale / gp_settings.lobe_width(scored_at), c.noise, c.calibration)
            split = SplitSettings(*diffuse, *lobe)
        self._use(*chosen, split=split)

    def chosen_settings(self, scene, spp: int) -> dict:
        self._spp = spp
        self.check_scene(scene)
        rows = [] if self.choice is None or len(self.choice.candidates) < 2 else [
            {"mapping": c.mapping, "noise": c.noise, "length_scale": c.length_scale,
             "relmse": c.relmse} for c in self.choice.candidates]
        glossy, s = None, self.split
        if s is not None:
            glossy = {"lobe_directions": self.lobe_directions, "diffuse_mapping": s.mapping,
                      "diffuse_noise": s.noise, "diffuse_length_scale": s.length_scale,
                      "lobe_length_scale": s.lobe_length_scale, "lobe_noise": s.lobe_noise,
                      "lobe_calibration": s.lobe_calibration,
                      "lobe_exponent": self.lobe_exponent}
        return {"source": self.source, "mapping": self.mapping, "noise": self.noise,
                "length_scale": self.length_scale, "spp": int(spp),
                "calibration": self.calibration, "candidates": rows, "glossy": glossy}

    def _use(self, length_scale: float, noise: float, mapping: str,
             calibration: float = 1.0, split: SplitSettings | None = None) -> None:
        """Take these settings and their weights (cached per setting), the
        posterior variance scaled by ``calibration``. With ``split``, the
        weights of both sets at glossy shading points too."""
        now = (length_scale, noise, mapping, calibration, split)
        if now == tuple(getattr(self, k, None) for k in ("length_scale", "noise", "mapping",
                                                          "calibration", "split")):
            return
        self.length_scale, self.noise, self.mapping = float(length_scale), float(noise), mapping
        self.calibration, self.split = float(calibration), split
        self._use_table()

    @property
    def glossy(self) -> bool:
        """Whether glossy points get two sets (the scene checked has glossy lobes)."""
        return self.split is not None

    def _use_table(self):
        # The weight tables stay local: Dr.Jit walks a Python plugin's
        # attributes (Unwalked), and the lobe tables' 656 records cost 0.18 s
        # a launch there.
        n, n_b = self.directions, self.lobe_directions
        with warnings.catch_warnings():
            if self.chooses:
                # (a chosen setting's extra jitter is part of what was scored)
                warnings.simplefilter("ignore", RuntimeWarning)
            tables = gp_settings.set_weights(n, self.length_scale, self.noise,
                                             self.prior_mean, self.mapping, self.sets)
            self._a, self._c, self._d = self._flat(tables, self.calibration)
            if self.glossy:
                # the diffuse set of a glossy point, and the lobe set per exponent
                s = self.split
                split_tables = gp_settings.set_weights(
                    n - n_b, s.length_scale, s.noise, self.prior_mean, s.mapping, self.sets)
                # (ℓ in lobe widths: the same relative kernel at every exponent)
                lobe_tables = [
                    t for e in EXPONENTS for t in gp_settings.set_weights(
                        n_b, s.lobe_length_scale * gp_settings.lobe_width(e), s.lobe_noise,
                        self.prior_mean, "lobe", self.sets, e)]
                self._a2, self._c2, self._d2 = self._flat(split_tables, s.calibration)
                self._b, self._cb, self._db = self._flat(lobe_tables, s.lobe_calibration)

    def _flat(self, tables, calibration: float):
        """(weights, error factors × ``calibration``, amplitude divisors) of
        ``tables``, flat, as Dr.Jit arrays (lists in scalar variants)."""
        a = [float(x) for t in tables for x in t.weights]
        c = [float(t.error_factor) * calibration for t in tables]
        d = [float(t.amplitude_divisor) for t in tables]
        jit = dr.is_jit_v(mi.Float)
        return (mi.Float(a), mi.Float(c), mi.Float(d)) if jit else (a, c, d)

    def _gather(self, table, index, active):
        if dr.is_jit_v(mi.Float):
            return dr.gather(mi.Float, table, index, active)
        return table[int(index)] if active else 0.0

    # ----------------------------- The set -------------------------------

    def draw_set(self, sampler, si, bsdf, ctx, active):
        # the turn about the normal, and which of the shifted sets
        turn = sampler.next_1d(active)
        which = mi.UInt32(dr.minimum(sampler.next_1d(active) * self.sets, self.sets - 1))
        if dr.hint(not self.glossy, mode='scalar'):
            return turn, which
        # A glossy point: its lobe's exponent from the glossy density at the
        # mirror direction (0 there: no lobe towards the viewer, one set),
        # widened where the lobe's tails are heavier than a Phong lobe's
        glossy, r = lobes(ctx, mi.BSDFFlags.Glossy), mi.reflect(si.wi)
        peak = bsdf.pdf(glossy, si, r, active)
        lobe = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy) & (peak > 0)
        q = lobe_index(covering_exponent(lambda w: bsdf.pdf(glossy, si, w, lobe), r, peak))
        return turn, which, lobe, q, sampler.next_1d(active)

    def second_set_start(self, drawn):
        return dr.select(drawn[2], mi.UInt32(self.directions - self.lobe_directions),
                         mi.UInt32(self.directions))

    def direction(self, j, drawn, si, bsdf, ctx, active):
        if dr.hint(not self.glossy, mode='scalar'):
            turn, which = drawn
            # u shifted by gp_quadrature.set_shift(which, sets, N)
            shift = ((mi.Float(which) + 0.5) / self.sets - 0.5) / self.directions
            w_up = MAPPINGS[self.mapping][0](fibonacci_point(j, self.directions,
                                                             mi.Point2f(shift, turn)))
            wo = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))
            p = w_up.z * dr.inv_pi          # the measure cos θ / π, whatever the mapping
            # f cos θ / p = ρ for a diffuse BSDF: the GP models L_i, ρ scales it
            f_cos = bsdf.eval(ctx, si, wo, active)
            factor = over_pdf(f_cos, p)
            return wo, factor, self._gather(self._a, which * self.directions + j, active)
        return self._split_direction(j, drawn, si, bsdf, ctx, active)

    def _split_direction(self, j, drawn, si, bsdf, ctx, active):
        """ω_j, f cos/p and a_j where the scene has glossy lobes: at a glossy
        point, the diffuse set's N_a directions, then the lobe set's N_b."""
        turn, which, lobe, q, turn_b = drawn
        n_b = self.lobe_directions
        n_a = dr.select(lobe, mi.UInt32(self.directions - n_b), mi.UInt32(self.directions))
        in_a = j < n_a
        j_b = j - n_a

        # Diffuse set: cos θ / π about the normal, u shifted by set_shift(which, sets, N_a),
        # mapped as its weights were computed (the split's mapping at a glossy point)
        shift = ((mi.Float(which) + 0.5) / self.sets - 0.5) / mi.Float(n_a)
        u = fibonacci_point(j, n_a, mi.Point2f(shift, turn))
        w_up = dr.select(lobe, MAPPINGS[self.split.mapping][0](u), MAPPINGS[self.mapping][0](u))
        wo_a = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))
        # Lobe set: (n + 1)/(2π) cosⁿ α about the mirror direction r
        n_q = dr.exp2(mi.Float(q) / STEPS_PER_OCTAVE)
        shift_b = ((mi.Float(which) + 0.5) / self.sets - 0.5) / n_b
        r = mi.reflect(si.wi)
        w_lobe = sample_phong_lobe(fibonacci_point(j_b, n_b, mi.Point2f(shift_b, turn_b)), n_q)
        wo = dr.select(in_a, wo_a, mi.Frame3f(r).to_world(w_lobe))

        # The integrand of each set: f_glossy where r·ω > 0 belongs to the lobe set
        ctx_g, ctx_d = lobes(ctx, mi.BSDFFlags.Glossy), lobes(ctx, mi.BSDFFlags.Diffuse)
        f_g = bsdf.eval(ctx_g, si, wo, active)              # (eval includes cos θ)
        f_d = bsdf.eval(ctx_d, si, wo, active & in_a)
        # (no `~` on masks: in scalar variants they are Python bools)
        flat = dr.select(lobe, False, True)
        to_a = flat | (dr.dot(r, wo) <= 0)
        p_a = dr.abs(mi.Frame3f.cos_theta(wo)) * dr.inv_pi
        factor = dr.select(in_a, over_pdf(f_d + dr.select(to_a, f_g, 0.0), p_a),
                           over_pdf(f_g, phong_lobe_pdf(w_lobe, n_q)))
        a = dr.select(lobe, self._gather(self._a2, which * n_a + j, active & in_a & lobe),
                      self._gather(self._a, which * n_a + j, active & in_a & flat))
        b = self._gather(self._b, (q * self.sets + which) * n_b + j_b,
                         active & dr.select(in_a, False, True))
        return wo, factor, dr.select(in_a, a, b)

    second_set_sums = glossy         # (a glossy point keeps each set's sums apart)

    def finish(self, total, s1, s2, y0, drawn, active):
        which = drawn[1]
        if dr.hint(not self.glossy, mode='scalar'):
            var = self._set_variance(s1, s2, y0, self.directions, self._c, self._d, which,
                                     active)
        else:
            lobe, q = drawn[2], drawn[3]
            n_b = self.lobe_directions
            n_a = dr.select(lobe, mi.UInt32(self.directions - n_b), mi.UInt32(self.directions))
            # the two sets' posteriors are independent: their variances add
            var_a = dr.select(
                lobe, self._set_variance(s1[0], s2[0], y0[0], n_a, self._c2, self._d2, which,
                                         active & lobe),
                self._set_variance(s1[0], s2[0], y0[0], n_a, self._c, self._d, which,
                                   active & dr.select(lobe, False, True)))
            var_b = self._set_variance(s1[1], s2[1], y0[1], n_b, self._cb, self._db,
                                       q * self.sets + which, active & lobe)
            var = var_a + dr.select(lobe, var_b, 0.0)
        if dr.hint(mi.is_rgb, mode='scalar'):
            found = [var[0], var[1], var[2]]
        else:
            found = [dr.mean(var)]
        return total, found

    def _set_variance(self, s1, s2, y0, n, c, d, table, active):
        """κ·c·σ̂² of one set of n values, table ``table`` of c and d."""
        n = mi.Float(n)
        # σ̂² by moments: E[Σ(Y − Ȳ)²] = σ² (tr Q − 1ᵀQ1/N) (zero mean: E[ΣY²] = σ² tr Q);
        # Σ(Y − Ȳ)² = Σd² − (Σd)²/N and ΣY² = Σd² + 2Y₀Σd + N Y₀² for d = Y − Y₀
        if dr.hint(self.prior_mean == "constant", mode='scalar'):
            spread = s2 - dr.square(s1) / n
        else:
            spread = s2 + 2.0 * y0 * s1 + n * dr.square(y0)
        # (an inactive lane gathers d = 0; scalar variants evaluate both sides of a select)
        return (self._gather(c, table, active) * dr.maximum(spread, 0.0)
                / dr.maximum(self._gather(d, table, active), 1e-30))

    def finish_aovs(self) -> int:
        return 3 if mi.is_rgb else 1

    def sample_aovs(self, L, aovs):
        # L² as well: with the film's mean of L it gives the spread of the
        # pixel's camera samples (footprint, turn), the part of a pixel's
        # error that averages down with spp
        if dr.hint(mi.is_rgb, mode='scalar'):
            return [*aovs, dr.square(L[0]), dr.square(L[1]), dr.square(L[2])]
        return [*aovs, dr.square(dr.mean(L))]

    def aov_names(self):
        channels = "RGB" if mi.is_rgb else "Y"
        return [f"posterior_var.{c}" for c in channels] + [f"sample_sq.{c}" for c in channels]

    def to_string(self) -> str:
        return (f"BayesianHemisphereIntegrator[directions={self.directions}, "
                f"length_scale={self.length_scale:g} ({self.asked['length_scale']}), "
                f"noise={self.noise:g} ({self.asked['noise']}), "
                f"prior_mean={self.prior_mean}, mapping={self.mapping}]")


registry.register(BayesianHemisphereIntegrator)
