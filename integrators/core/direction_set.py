"""The loop shared by the estimators that trace a *set* of N directions from
one shading point (fibonacci_hemisphere, bayesian_hemisphere).

A camera ray finds its first surface; from there N directions ω_1 … ω_N
(a point set, not N independent samples) are traced once each, and the
direct illumination is a weighted sum of what they find:

    L_r(ω_o) ≈ Σ_j a_j · L_i(ω_j),   L_i = environment radiance where ω_j
                                      escapes, emission where it hits an
                                      area light, 0 otherwise.

How the set is drawn and weighted is the subclass's: :meth:`draw_set` takes
the per-shading-point randomness, :meth:`direction` gives ω_j and its weight,
:meth:`finish` turns the running sums into the pixel's value and AOVs.
The camera ray and the shading point are shared by all N directions, which
makes a traced direction cheaper here than a path vertex of the MC
estimators.

Only direct illumination is defined (``max_depth`` 2; 1 shows the emitters
the camera sees). Scenes with content a continuous hemisphere set cannot
reach (delta lights and lobes, transmission) are refused as by the
hemisphere estimators.

This module must be (re)imported after a variant is set (see
``mcillum.integrators.register``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .estimator import IlluminationEstimator

#: The path depths these estimators define.
DEPTHS = (1, 2)


def read_directions(props: mi.Properties, default: int = 64) -> int:
    """The ``directions`` parameter N (an integer ≥ 1)."""
    n = props.get("directions", default)
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"directions must be an integer >= 1 (<integer name=\"directions\" "
                         f"value=\"64\"/>), got {n!r}")
    return n


def frac(x):
    """x − ⌊x⌋ (Dr.Jit has no fmod)."""
    return x - dr.floor(x)


class DirectionSetEstimator(IlluminationEstimator):
    r"""
    Base class of the estimators of N directions per shading point (not
    registered as a plugin). Subclasses set the facts as the other
    estimators do and implement :meth:`draw_set`, :meth:`direction` and
    :meth:`finish` (and :meth:`aov_names` if they write AOVs).

    .. pluginparameters::

     * - directions
       - |int|
       - N, directions traced from each shading point. (Default: 64)
     * - max_depth
       - |int|
       - 2: direct illumination; 1: only emitters seen by the camera. Other
         values are refused. (Default: 2)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content a hemisphere set cannot reach instead of refusing
         the scene; the image is then biased and a warning says so.
         (Default: |false|)
    """

    #: (max_depth values it defines, read by the registry and the profiles)
    depths = DEPTHS
    #: The Monte Carlo estimator it is compared with at equal rays.
    equal_rays_baseline = "cosine_hemisphere"

    def __init__(self, props: mi.Properties):
        if "max_depth" not in props:
            props["max_depth"] = 2
        super().__init__(props)
        if self.max_depth not in DEPTHS:
            depth = -1 if self.max_depth == 0xFFFFFFFF else self.max_depth
            raise ValueError(
                f"{self.plugin_name}: max_depth = {depth} is not supported: N directions "
                "per shading point estimate direct illumination only (2), or show the "
                "emitters the camera sees (1); for longer paths use cosine_hemisphere, "
                "mis or path")
        self.directions = read_directions(props)

    # --------------------------- The point set ---------------------------

    def draw_set(self, sampler, si, bsdf, ctx, active):
        """Per-shading-point randomness of the set (a tuple of Dr.Jit values)."""
        raise NotImplementedError

    def direction(self, j, drawn, si, bsdf, ctx, active):
        """(ω_j in the local frame, Y-factor f_r cos θ / p as Spectrum, weight
        a_j): the pixel gets Σ a_j · factor_j · L_i(ω_j)."""
        raise NotImplementedError

    def finish(self, total, s1, s2, y0, drawn, active):
        """(L_r, AOV list) from Σ a_j Y_j, Σ d_j, Σ d_j² and Y_0, where
        Y_j = factor_j · L_j and d_j = Y_j − Y_0, and the set's ``drawn``.
        With :attr:`second_set_sums`, s1, s2 and y0 are pairs: those of
        the directions before :meth:`second_set_start` and those from it."""
        return total, []

    #: Keep Σ d_j, Σ d_j² and Y_0 separately for a second set of directions
    #: (from :meth:`second_set_start` on) and pass :meth:`finish` both.
    second_set_sums = False

    def second_set_start(self, drawn):
        """Index of the first direction of the second set (with
        :attr:`second_set_sums`)."""
        return mi.UInt32(self.directions)

    def finish_aovs(self) -> int:
        """How many AOV values :meth:`finish` returns."""
        return 0

    def sample_aovs(self, L, aovs):
        """The AOV values of a camera sample whose radiance is ``L`` (default:
        those :meth:`finish` gave)."""
        return aovs

    def aov_names(self):
        return []

    def chosen_settings(self, scene, spp: int) -> dict | None:
        """How the settings this estimator uses on ``scene`` at ``spp`` were
        chosen (keys: source, mapping, noise, length_scale, spp,
        candidates, and optionally glossy: the settings of the sets at a
        glossy point, validation/results/quadrature.GlossySettings' fields);
        None where it has none to choose."""
        return None

    # ----------------------------- Estimator -----------------------------

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        self.check_wrapped(scene)           # (a wrapper may call sample() alone)
        ctx = mi.BSDFContext()
        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        n_aovs = self.finish_aovs()

        # ------------------ Camera ray (emitters hidden) ------------------

        pi, valid_ray = self.camera_hit(scene, ray, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All)

        # ------------------ Emission seen by the camera -------------------

        L = mi.Spectrum(0)
        emitter = si.emitter(scene)
        if emitter != None:
            L += emitter.eval(si, active & (not self.hide_emitters))
        valid_ray |= active & si.is_valid()
        aovs = [mi.Float(0)] * n_aovs

        # ------------------ N directions from the surface -----------------

        shade = active & si.is_valid() & (self.max_depth >= 2)
        if shade:  # (masked in JIT variants, a plain branch in scalar)
            bsdf = si.bsdf(ray)
            drawn = self.draw_set(sampler, si, bsdf, ctx, shade)
            # Σ a_j Y_j, and Σ d_j, Σ d_j² of d_j = Y_j − Y_0 (shifted by the
            # first sample: the spread of N equal values is then exactly 0)
            total, s1, s2, y0 = mi.Spectrum(0), mi.Spectrum(0), mi.Spectrum(0), mi.Spectrum(0)
            # (the same sums of a second set, where the subclass keeps them apart)
            t1, t2, z0 = mi.Spectrum(0), mi.Spectrum(0), mi.Spectrum(0)
            second = self.second_set_start(drawn) if self.second_set_sums else None
            j = mi.UInt32(0)
            while dr.hint(shade & (j < self.directions), max_iterations=self.directions,
                          label=f"mcillum direction set ({self.plugin_name})"):
                wo, factor, a = self.direction(j, drawn, si, bsdf, ctx, shade)
                # Y_j = f_r cos θ / p · L_i(ω_j): what the ray along ω_j finds
                ray_j = si.spawn_ray(si.to_world(wo))
                si_j = scene.ray_intersect(ray_j, shade)
                Y = mi.Spectrum(0)
                emitter_j = si_j.emitter(scene)
                if emitter_j != None:
                    Y = factor * emitter_j.eval(si_j, shade)
                total += a * Y
                y0 = dr.select(j == 0, Y, y0)
                if dr.hint(self.second_set_sums, mode='scalar'):
                    in_first = j < second
                    z0 = dr.select(j == second, Y, z0)
                    s1 += dr.select(in_first, Y - y0, 0.0)
                    s2 += dr.select(in_first, dr.square(Y - y0), 0.0)
                    t1 += dr.select(in_first, 0.0, Y - z0)
                    t2 += dr.select(in_first, 0.0, dr.square(Y - z0))
                else:
                    s1 += Y - y0
                    s2 += dr.square(Y - y0)
                j += 1
            if dr.hint(self.second_set_sums, mode='scalar'):
                s1, s2, y0 = (s1, t1), (s2, t2), (y0, z0)
            L_r, found = self.finish(total, s1, s2, y0, drawn, shade)
            L += L_r
            aovs = list(found)

        L = dr.select(valid_ray, L, 0)
        return L, valid_ray, self.sample_aovs(L, aovs)

    def to_string(self) -> str:
        return (f"{type(self).__name__}[directions={self.directions}, max_depth="
                f"{self.max_depth}, hide_emitters={self.hide_emitters}]")
