"""Bayesian Monte Carlo (Gaussian-process quadrature) of direct illumination on
diffuse and glossy surfaces, with the posterior standard deviation of every
pixel."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..bsdfs.phong import phong_lobe_pdf
from ..core import registry, scene_checks
from ..core.direction_set import DirectionSetEstimator
from ..core.estimator import over_pdf
from . import bmc_weights
from .bmc_lobe import SplitSettings, draw_lobe, lobe_node, lobes, split_settings
from .bmc_weights import gather, set_variance, split_variance
from .fibonacci_hemisphere import MAPPINGS, fibonacci_point
from .gp_scene import (DEFAULT_LENGTH_SCALE, DEFAULT_MAPPING, DEFAULT_NOISE, DEFAULT_SETS,
                       choose_hyperparameters, likelihood_length_scale)

PRIOR_MEANS = ("constant", "zero")

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
    computed once per (N, ℓ, σ_n², set) and cached (bmc_weights.py). A fixed set
    errs the same way at every turn about a normal, an error spp does not
    average away; drawing among shifted sets averages several sets' errors.

    ``auto`` settings are chosen for the quadrature, not for the lighting:
    by the error of each candidate on known integrals of the scene's
    environment map about normals the camera sees (gp_scene.py), once per
    map, N, spp and camera view; ``source`` says how they were chosen and
    ``choice`` holds every candidate's score. Without an environment map,
    or with a constant one, ``auto`` means ℓ = 0.5, σ_n²/σ² = 0.001 and
    cosine nodes.

    The estimate is biased by design (it is a posterior mean, not an
    average of samples), and accurate where the lighting is smooth at scale
    ℓ; a sun or a hard shadow breaks the prior. Every camera sample also
    gives the posterior variance κ · c · σ̂², c = aᵀQa − 2aᵀz + ∫∫kpp and
    σ̂² the prior variance estimated from the N samples by moments
    (bmc_weights.set_variance); κ, fitted on the held-out integrals, makes
    it predict the part of the error spp does not average away (the GP's own
    c·σ̂² is off by orders of magnitude: gp_settings.calibration_factor).
    It is written as the AOV
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
    N ≥ 4) form a second set about the mirror direction, mapped by a Phong
    lobe of the BSDF's exponent, with weights and settings of its own; the
    two sets split the integral, and their posterior variances add
    (bmc_lobe.py).

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
            split, self.lobe_choice, self.lobe_exponent = split_settings(
                scene, diffuse, self.lobe_directions, self.prior_mean, self.sets, spp)
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
        # The gp_settings records stay local: Dr.Jit walks a Python plugin's
        # attributes (Unwalked), and the lobe tables' 656 records cost 0.18 s
        # a launch there. (Their flat arrays, a few, are walked.)
        self._tables = bmc_weights.build(
            self.directions, self.lobe_directions, self.length_scale, self.noise,
            self.mapping, self.prior_mean, self.sets, self.calibration, self.split,
            quiet=self.chooses)

    # ----------------------------- The set -------------------------------

    def draw_set(self, sampler, si, bsdf, ctx, active):
        # the turn about the normal, and which of the shifted sets
        turn = sampler.next_1d(active)
        which = mi.UInt32(dr.minimum(sampler.next_1d(active) * self.sets, self.sets - 1))
        if dr.hint(not self.glossy, mode='scalar'):
            return turn, which
        return turn, which, *draw_lobe(sampler, si, bsdf, ctx, active)

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
            return wo, factor, gather(self._tables.plain.weights,
                                      which * self.directions + j, active)
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
        r, w_lobe, n_q = lobe_node(j_b, n_b, which, self.sets, turn_b, q, si)
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
        t = self._tables
        a = dr.select(lobe, gather(t.split.weights, which * n_a + j, active & in_a & lobe),
                      gather(t.plain.weights, which * n_a + j, active & in_a & flat))
        b = gather(t.lobe.weights, (q * self.sets + which) * n_b + j_b,
                   active & dr.select(in_a, False, True))
        return wo, factor, dr.select(in_a, a, b)

    second_set_sums = glossy         # (a glossy point keeps each set's sums apart)

    def finish(self, total, s1, s2, y0, drawn, active):
        which, t = drawn[1], self._tables
        if dr.hint(not self.glossy, mode='scalar'):
            var = set_variance(self.prior_mean, s1, s2, y0, self.directions, t.plain, which,
                               active)
        else:
            var = split_variance(self.prior_mean, s1, s2, y0, self.directions,
                                 self.lobe_directions, drawn, self.sets, t, active)
        if dr.hint(mi.is_rgb, mode='scalar'):
            found = [var[0], var[1], var[2]]
        else:
            found = [dr.mean(var)]
        return total, found

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
