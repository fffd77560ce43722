"""Bayesian Monte Carlo (Gaussian-process quadrature) of direct illumination on
diffuse surfaces, with the posterior standard deviation of every pixel."""

from __future__ import annotations

import hashlib

import drjit as dr
import mitsuba as mi
import numpy as np

from . import gp_quadrature, registry
from .direction_set import DirectionSetEstimator
from .fibonacci_hemisphere import GOLDEN, MAPPINGS, fibonacci_point

#: ℓ where the scene has no environment map to fit it to.
DEFAULT_LENGTH_SCALE = 0.5
#: Environment samples the marginal likelihood is maximised over.
FIT_SAMPLES = 512
PRIOR_MEANS = ("constant", "zero")

# ----------------------------- Strategy ---------------------------------
# Directions: the N-point spherical-Fibonacci set, cosine-mapped, rotated about
# the normal by one random angle per shading point (u_j kept, v_j shifted): the
# rotation leaves every θ_j, hence z and Q, unchanged. Weights: a = Q⁻¹z with
# the constant-mean correction (gp_quadrature.weights), the same at every pixel.


def rotated_point(j, n, turn) -> mi.Point2f:
    """Point j of the unshifted set, turned by ``turn`` (a fraction of 2π)."""
    return fibonacci_point(j, n, mi.Point2f(0.0, turn))


def sphere_directions(m: int) -> np.ndarray:
    """m near-uniform directions on the whole sphere (a Fibonacci sphere)."""
    j = np.arange(m)
    z = 1.0 - (2.0 * j + 1.0) / m
    phi = 2.0 * np.pi * np.mod(j / GOLDEN, 1.0)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def environment_samples(scene, m: int = FIT_SAMPLES):
    """(directions, radiance averaged over channels) of the scene's environment
    at m directions; None if the scene has none."""
    env = scene.environment()
    if env is None:
        return None
    d = sphere_directions(m)
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
    return d, values.reshape(m, -1).mean(axis=1)


def _visible(wavelengths):
    """Wavelengths across the visible range (spectral variants evaluate the
    map at these; RGB and mono variants ignore them)."""
    if not mi.is_spectral:
        return wavelengths
    return type(wavelengths)(*(mi.Float(450.0 + 200.0 * i / (len(wavelengths) - 1))
                               for i in range(len(wavelengths))))


_fitted: dict[str, float] = {}


def fit_length_scale(scene, noise: float) -> tuple[float, str]:
    """ℓ by maximum marginal likelihood over the scene's environment (cached
    by the sampled values), and how it was chosen."""
    samples = environment_samples(scene)
    if samples is None:
        return DEFAULT_LENGTH_SCALE, "default (no environment map)"
    d, y = samples
    if np.ptp(y) <= 1e-6 * max(float(np.abs(y).max()), 1e-30):    # (float32 texels)
        return DEFAULT_LENGTH_SCALE, "default (the environment is constant: nothing to fit)"
    key = hashlib.sha1(np.ascontiguousarray(y, np.float64).tobytes() +
                       repr(noise).encode()).hexdigest()
    if key not in _fitted:
        _fitted[key] = gp_quadrature.fit(d, y, noise).length_scale
    return _fitted[key], "maximum marginal likelihood over the environment map"


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
       - ℓ of the kernel; ``auto`` fits it by maximum marginal likelihood to
         512 samples of the scene's environment map (0.5 without one).
         (Default: ``auto``)
     * - noise
       - |float|
       - σ_n²/σ², the noise added to the kernel's diagonal, relative to the
         prior variance (regularises Q). (Default: 0.001)
     * - prior_mean
       - |string|
       - ``constant`` (the mean of the N samples) or ``zero``. (Default: ``constant``)
     * - mapping
       - |string|
       - Where the nodes lie: ``cosine`` (cos θ = √(1 − u), denser near the
         normal) or ``uniform`` (cos θ = 1 − u); the integral is against
         cos θ/π either way. (Default: ``cosine``)
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
    directions are a spherical-Fibonacci set turned about the normal by a
    random angle per shading point, so z and Q, hence a, are the same
    everywhere: computed once per (N, ℓ, σ_n²) in float64 and cached.

    The estimate is biased by design (it is a posterior mean, not an
    average of samples), and accurate where the lighting is smooth at scale
    ℓ; a sun or a hard shadow breaks the prior. Every camera sample also
    gives the posterior variance c · σ̂², c = aᵀQa − 2aᵀz + ∫∫kpp and σ̂²
    the prior variance estimated from the N samples by moments; it is
    written as the AOV ``posterior_var`` (per channel; one ``Y`` channel in
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

    Only diffuse BSDFs: a scene with a glossy lobe is refused with the
    object named (use ``fibonacci_hemisphere``, which splits its directions
    between the lobes).

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
    diffuse_only = True                        # no glossy lobes
    max_direction_pdf = dr.inv_pi              # the set follows cos θ / π
    listing_order = 70
    unbiased = False

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        ell = props.get("length_scale", "auto")
        if not (ell == "auto" or (isinstance(ell, (int, float)) and not isinstance(ell, bool)
                                  and ell > 0)):
            raise ValueError(f"{self.plugin_name}: length_scale must be a number > 0 or "
                             f"'auto', got {ell!r}")
        self.length_scale_param = ell
        self.noise = props.get("noise", 1e-3)
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float)) \
                or self.noise < 0:
            raise ValueError(f"{self.plugin_name}: noise must be a number >= 0 "
                             f"(σ_n²/σ², e.g. 0.001), got {self.noise!r}")
        self.prior_mean = props.get("prior_mean", "constant")
        if self.prior_mean not in PRIOR_MEANS:
            raise ValueError(f"{self.plugin_name}: prior_mean must be one of "
                             f"{', '.join(PRIOR_MEANS)}, got {self.prior_mean!r}")
        self.mapping = props.get("mapping", "cosine")
        if self.mapping not in MAPPINGS:
            raise ValueError(f"{self.plugin_name}: mapping must be one of "
                             f"{', '.join(MAPPINGS)}, got {self.mapping!r}")
        if self.prior_mean == "constant" and self.directions < 2:
            raise ValueError(f"{self.plugin_name}: directions = {self.directions} with "
                             "prior_mean 'constant' leaves nothing to estimate the prior "
                             "variance from; use directions >= 2 or prior_mean 'zero'")
        self.length_scale = None if ell == "auto" else float(ell)
        self.length_scale_source = "given"
        if self.length_scale is not None:
            self._use_table()

    # -------------------- Hyperparameters and weights ---------------------

    def check_scene(self, scene) -> None:
        super().check_scene(scene)
        if self.length_scale_param == "auto":
            ell, self.length_scale_source = fit_length_scale(scene, self.noise)
            if ell != self.length_scale:
                self.length_scale = ell
                self._use_table()

    def _use_table(self):
        self.table = gp_quadrature.weights(self.directions, self.length_scale, self.noise,
                                           self.prior_mean, self.mapping)
        a = [float(x) for x in self.table.weights]
        self._a = mi.Float(a) if dr.is_jit_v(mi.Float) else a

    def _weight(self, j, active):
        if dr.is_jit_v(mi.Float):
            return dr.gather(mi.Float, self._a, j, active)
        return self._a[j]

    # ----------------------------- The set -------------------------------

    def draw_set(self, sampler, si, bsdf, ctx, active):
        return (sampler.next_1d(active),)               # the turn about the normal

    def direction(self, j, drawn, si, bsdf, ctx, active):
        w_up = MAPPINGS[self.mapping][0](rotated_point(j, self.directions, drawn[0]))
        wo = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))
        p = w_up.z * dr.inv_pi              # the measure cos θ / π, whatever the mapping
        # f cos θ / p = ρ for a diffuse BSDF: the GP models L_i, ρ scales it
        f_cos = bsdf.eval(ctx, si, wo, active)
        factor = dr.select(p > 0, f_cos / dr.select(p > 0, p, 1.0), 0.0)
        return wo, factor, self._weight(j, active)

    def finish(self, total, s1, s2, y0, active):
        n = self.directions
        # σ̂² by moments: E[Σ(Y − Ȳ)²] = σ² (tr Q − 1ᵀQ1/N) (zero mean: E[ΣY²] = σ² tr Q);
        # Σ(Y − Ȳ)² = Σd² − (Σd)²/N and ΣY² = Σd² + 2Y₀Σd + N Y₀² for d = Y − Y₀
        if dr.hint(self.prior_mean == "constant", mode='scalar'):
            spread = s2 - dr.square(s1) / n
        else:
            spread = s2 + 2.0 * y0 * s1 + n * dr.square(y0)
        var = self.table.error_factor * dr.maximum(spread, 0.0) / self.table.amplitude_divisor
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
                f"length_scale={self.length_scale_param}, noise={self.noise}, "
                f"prior_mean={self.prior_mean}, mapping={self.mapping}]")


registry.register(BayesianHemisphereIntegrator)
