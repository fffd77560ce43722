"""The one estimator loop that every mcillum integrator shares.

Each vertex of a path estimates the illumination integral

    L_r(ω_o) = ∫_Ω L_i(ω_i) f_r(ω_i, ω_o) cos θ_i dω_i

with one sample ω ~ p, i.e. it multiplies the path throughput β by

    f_r(ω, ω_o) cos θ / p(ω)

and recurses along ω. Radiance is collected only where a path *hits* an
emitter (an area light, or the environment when it escapes): there is no
next-event estimation, so the choice of p decides everything.

A strategy is a small pure trio in the local shading frame, supplied by the
subclass: ``sample_local(u) -> ω`` and ``pdf_local(ω) -> p`` on the upper
hemisphere (z > 0). The loop mirrors the hemisphere to the side the ray came
from, so two-sided BSDFs hit from below are handled like those hit from above.
Depth, Russian roulette, emitter hiding and the validity mask follow Mitsuba's
``path`` exactly, so ``path`` at the same ``max_depth`` is the reference.

This module must be (re)imported after a variant is set: its class derives
from that variant's ``mi.SamplingIntegrator``. ``integrators.register()``
takes care of it.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import scene_checks

#: ``max_depth = -1`` (unbounded) as a depth bound, as in Mitsuba's path.
UNBOUNDED = 0xFFFFFFFF


def read_depths(props: mi.Properties) -> tuple[int, int]:
    """Read ``max_depth`` and ``rr_depth`` with Mitsuba's defaults and checks."""
    max_depth = props.get("max_depth", -1)
    rr_depth = props.get("rr_depth", 5)
    for name, value in (("max_depth", max_depth), ("rr_depth", rr_depth)):
        if not isinstance(value, int) or isinstance(value, bool):
            raise TypeError(f"{name} must be an integer (<integer name=\"{name}\" "
                            f"value=\"...\"/>), got {type(value).__name__} {value!r}")
    if max_depth < -1:
        raise ValueError(
            f"max_depth = {max_depth} is invalid: use -1 (unbounded), 1 (emitters "
            "seen directly), 2 (direct illumination) or a larger path length")
    if rr_depth <= 0:
        raise ValueError(
            f"rr_depth = {rr_depth} is invalid: Russian roulette starts at a "
            "path depth >= 1 (default 5; a large value effectively disables it)")
    return (UNBOUNDED if max_depth == -1 else max_depth), rr_depth


class IlluminationEstimator(mi.SamplingIntegrator):
    r"""
    Base class of the mcillum estimators (not registered as a plugin).

    Subclasses set :attr:`plugin_name` and the strategy pair
    :meth:`sample_local` / :meth:`pdf_local`; they inherit the parameters below.

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth in the image (-1: unbounded). 1 renders only
         directly visible emitters; 2 is direct illumination (one bounce).
         (Default: -1)

     * - rr_depth
       - |int|
       - Depth from which Russian roulette may end paths, with survival
         probability min(max(β), 0.95) as in ``path``. (Default: 5)

     * - hide_emitters
       - |bool|
       - Hide directly visible emitters (area lights and the environment).
         (Default: |false|)
    """

    #: Name under which the subclass is registered (used in messages).
    plugin_name = "illumination_estimator"

    #: Kinds of :class:`scene_checks.Problem` this strategy handles anyway.
    reachable: frozenset[str] = frozenset()

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        if mi.is_polarized:
            raise NotImplementedError(
                f"'{self.plugin_name}' does not track polarization (variant "
                f"'{mi.variant()}'); use an *_rgb, *_spectral or *_mono variant")
        self.max_depth, self.rr_depth = read_depths(props)

    # ------------------------- Strategy (pure) --------------------------

    @staticmethod
    def sample_local(u: mi.Point2f) -> mi.Vector3f:
        """Warp ``u`` ∈ [0,1)² to a direction on the upper hemisphere."""
        raise NotImplementedError

    @staticmethod
    def pdf_local(w: mi.Vector3f) -> mi.Float:
        """Solid-angle density of :meth:`sample_local` (0 where z ≤ 0)."""
        raise NotImplementedError

    # ------------------------ Scene validation --------------------------

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        # Refuse scenes this strategy would render wrong, before any work.
        scene_checks.require_reachable(scene, self.plugin_name, self.reachable)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    # --------------------------- Estimator ------------------------------

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        if dr.hint(self.max_depth == 0, mode='scalar'):
            return mi.Spectrum(0), mi.Bool(False), []   # as `path`: no vertices

        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------

        ray = mi.Ray3f(ray)
        L = mi.Spectrum(0)                 # radiance accumulated so far
        β = mi.Spectrum(1)                 # path throughput ∏ f cos θ / p
        depth = mi.UInt32(0)               # index of the current vertex
        active = mi.Bool(active)

        # The environment counts as "hit" (alpha = 1) unless it is hidden.
        valid_ray = mi.Bool((not self.hide_emitters) and
                            (scene.environment() is not None))

        pi = scene.ray_intersect_preliminary(ray, coherent=True, active=active)

        # ---------------------- Hide area emitters -----------------------

        if dr.hint(self.hide_emitters, mode='scalar'):
            # As `path` does: look through directly visible area emitters.
            si0 = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
            skip = active & si0.is_valid() & (si0.emitter(scene) != None)
            pi_behind = self.skip_area_emitters(scene, si0.spawn_ray(ray.d), True, skip)
            pi = dr.select(skip, pi_behind, pi)

        while dr.hint(active, max_iterations=-1,
                      label=f"mcillum estimator ({self.plugin_name})"):
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All)

            # -------------------- Emission at the hit ---------------------

            # L += β · L_e(x, -ω): area light at a surface hit, environment
            # when the ray escaped (si.emitter() returns it for invalid si).
            emitter = si.emitter(scene)
            # (no `~` on masks here: in scalar variants they are Python bools)
            visible = active & ((not self.hide_emitters) | (depth > 0))
            if emitter != None:
                L += β * emitter.eval(si, visible)

            valid_ray |= active & si.is_valid()

            # Does the path get one more vertex?
            active_next = active & (depth + 1 < self.max_depth) & si.is_valid()

            # ------------------ Sample the next direction -------------------

            if active_next:  # (masked in JIT variants, a plain branch in scalar)
                # ω ~ p on the hemisphere on the side of ω_o (si.wi, local frame)
                w_up = self.sample_local(sampler.next_2d())
                pdf = self.pdf_local(w_up)
                wo = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))

                # β ← β · f_r(ω, ω_o) cos θ / p(ω)   (bsdf.eval includes cos θ)
                f_cos = si.bsdf(ray).eval(bsdf_ctx, si, wo)
                β *= dr.select(pdf > 0, f_cos / pdf, 0)

                ray = si.spawn_ray(si.to_world(wo))

            # --------------------- Stopping criterion ---------------------

            depth = dr.select(si.is_valid(), depth + 1, depth)

            # Russian roulette exactly as `path`: survive with min(max β, .95)
            β_max = dr.max(mi.unpolarized_spectrum(β))
            rr_prob = dr.minimum(β_max, 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d(active_next) < rr_prob
            β = dr.select(rr_active, β * dr.rcp(rr_prob), β)

            active = active_next & ((depth < self.rr_depth) | rr_continue) & (β_max != 0)
            pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active)

        return dr.select(valid_ray, L, 0), valid_ray, []

    def to_string(self) -> str:
        depth = -1 if self.max_depth == UNBOUNDED else self.max_depth
        return (f"{type(self).__name__}[max_depth={depth}, rr_depth={self.rr_depth}, "
                f"hide_emitters={self.hide_emitters}]")
