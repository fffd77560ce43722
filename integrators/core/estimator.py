"""The one estimator loop that every mcillum integrator shares.

Each vertex of a path estimates the illumination integral

    L_r(ω_o) = ∫_Ω L_i(ω_i) f_r(ω_i, ω_o) cos θ_i dω_i

with one sample ω ~ p, i.e. it multiplies the path throughput β by

    f_r(ω, ω_o) cos θ / p(ω)

and recurses along ω. Radiance is collected where a path *hits* an emitter
(an area light, or the environment when it escapes) and, for strategies with
``use_nee``, by one emitter sample per vertex (next-event estimation).

The direction strategy is :meth:`IlluminationEstimator.sample_direction`. By
default it is a small pure pair in the local shading frame supplied by the
subclass, ``sample_local(u) -> ω`` and ``pdf_local(ω) -> p`` on the upper
hemisphere (z > 0), mirrored to the side the ray came from, so two-sided BSDFs
hit from below are handled like those hit from above. BSDF sampling overrides
it. Emission at a hit is weighted by :meth:`hit_weight`: 1 without NEE; with
NEE, either only where NEE could not have sampled the light (camera rays and
after delta bounces) or by the power heuristic (``use_mis``).

Depth, Russian roulette, emitter hiding and the validity mask follow Mitsuba's
``path`` exactly, so ``path`` at the same ``max_depth`` is the reference.

This module must be (re)imported after a variant is set: its class derives
from that variant's ``mi.SamplingIntegrator`` (through checked_render.py, the
render's entry: the scene check, passes). ``mcillum.integrators.register()``
takes care of it.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import scene_checks
from .checked_render import CheckedRender

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


def over_pdf(value, pdf):
    """value / pdf where pdf > 0, else 0: a sample's weight f cos θ / p."""
    # (select the divisor too: scalar variants divide Python floats, which raise)
    return dr.select(pdf > 0, value / dr.select(pdf > 0, pdf, 1.0), 0.0)


def mis_weight(pdf_a, pdf_b):
    """Power heuristic p_a² / (p_a² + p_b²), 0 where undefined (as `path`)."""
    a, b = dr.square(pdf_a), dr.square(pdf_b)
    total = a + b
    # (select the divisor too: scalar variants divide Python floats, which raise)
    w = a / dr.select(total > 0, total, 1.0)
    return dr.detach(dr.select((total > 0) & dr.isfinite(w), w, 0))


class IlluminationEstimator(CheckedRender):
    r"""
    Base class of the mcillum estimators (not registered as a plugin).

    Subclasses set :attr:`plugin_name`, their facts (:attr:`display_name`,
    :attr:`colour`, :attr:`reachable`, :attr:`max_direction_pdf`,
    :attr:`listing_order`) and the strategy pair :meth:`sample_local` /
    :meth:`pdf_local`, and end their file with ``registry.register(cls)``;
    they inherit the parameters below.

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

     * - allow_unreachable
       - |bool|
       - Render scenes holding content this strategy cannot reach (delta
         lights or lobes, transmission) instead of refusing them. The image
         is then biased (that content is missing); a warning names it and
         :attr:`unreachable` lists it. (Default: |false|)
    """

    # ------------ Facts (read by registry.py; see its docstring) -----------

    #: Name under which the subclass is registered with Mitsuba.
    plugin_name = "illumination_estimator"
    #: A few words for people (tables, legends).
    display_name: str | None = None
    #: Its colour on every chart of a report.
    colour: str | None = None
    #: Kinds of scene content (scene_checks.KINDS) it renders although a
    #: continuous hemisphere pdf cannot reach them; it refuses the others.
    reachable: frozenset[str] = frozenset()
    #: Only diffuse BSDFs (weights that assume f_r constant): glossy lobes
    #: ("glossy_bsdf") are refused too. Every estimator that weights each
    #: direction by f cos / p reaches them.
    diffuse_only = False
    #: Largest density it puts on any direction (None: depends on the BSDF,
    #: or next-event estimation finds small sources anyway).
    max_direction_pdf: float | None = None
    #: Position in tables and charts (path, the reference, comes last).
    listing_order = 100
    #: The max_depth values it defines (None: any).
    depths: tuple[int, ...] | None = None
    #: False for an estimator biased by design (its bias is measured, not tested).
    unbiased = True
    #: Its render() is the same launches for any seed (no Python work
    #: between them, nothing made from host memory in sample()): the
    #: validation records it once and replays it. Read from the class that
    #: declares it only: a subclass (a twin, a user's variant) may not be.
    freezable = False

    #: One emitter sample per vertex (next-event estimation)?
    use_nee = False
    #: Weight NEE and BSDF-sampled emitter hits by the power heuristic?
    use_mis = False
    #: The emitter strategy pair, set by subclasses with ``use_nee``
    #: (see emitter_sampling.py): ``sample_emitter(scene, si, u, active) ->
    #: (ds, L_e/p)`` and ``emitter_pdf(scene, ref, ds, active) -> p``.
    sample_emitter = None
    emitter_pdf = None
    #: Call :meth:`record_vertex`, :meth:`record_emission` and
    #: :meth:`record_path` in the loop? Only an estimator that learns from its
    #: own paths (guided_path) does.
    records_paths = False

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        if mi.is_polarized:
            raise NotImplementedError(
                f"'{self.plugin_name}' does not track polarization (variant "
                f"'{mi.variant()}'); use an *_rgb, *_spectral or *_mono variant")
        self.max_depth, self.rr_depth = read_depths(props)
        self.allow_unreachable = props.get("allow_unreachable", False)
        if not isinstance(self.allow_unreachable, bool):
            raise TypeError("allow_unreachable must be a boolean (<boolean name="
                            "\"allow_unreachable\" value=\"true\"/>), got "
                            f"{type(self.allow_unreachable).__name__} "
                            f"{self.allow_unreachable!r}")
        #: What the last rendered scene held that this strategy misses (only
        #: non-empty with ``allow_unreachable``: the image lacks it).
        self.unreachable: list[scene_checks.Problem] = []

    # ------------------------- Strategy (pure) --------------------------

    @staticmethod
    def sample_local(u: mi.Point2f) -> mi.Vector3f:
        """Warp ``u`` ∈ [0,1)² to a direction on the upper hemisphere."""
        raise NotImplementedError

    @staticmethod
    def pdf_local(w: mi.Vector3f) -> mi.Float:
        """Solid-angle density of :meth:`sample_local` (0 where z ≤ 0)."""
        raise NotImplementedError

    #: Inverse of :meth:`sample_local` (direction → the u that maps to it),
    #: where the strategy has one.
    invert_local = None

    def sample_direction(self, scene, sampler, si, bsdf, ctx):
        """(ω local, weight f cos/p, pdf p, delta?, η) of the next direction.

        Default: ``sample_local``/``pdf_local`` on the hemisphere of ``si.wi``.
        """
        w_up = self.sample_local(sampler.next_2d())
        pdf = self.pdf_local(w_up)
        wo = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))
        f_cos = bsdf.eval(ctx, si, wo)                  # bsdf.eval includes cos θ
        weight = over_pdf(f_cos, pdf)
        return wo, weight, pdf, mi.Bool(False), mi.Float(1)

    # ---------- Scene validation (its render entry: checked_render.py) ----------

    def check_scene(self, scene) -> None:
        """Refuse a scene this strategy would render wrong (raise
        :class:`UnreachableContentError`), unless the user opted into the
        biased image: then record what it lacks in ``unreachable`` and warn,
        once per scene. :meth:`render` calls it before any work; callers may
        ask it without rendering."""
        reachable = self.reachable | (set() if self.diffuse_only else {"glossy_bsdf"})
        self.unreachable = scene_checks.check_reachable(
            scene, self.plugin_name, frozenset(reachable), self.allow_unreachable,
            warn=getattr(self, "_warned_for", None) != id(scene))
        if self.unreachable:
            self._warned_for = id(scene)

    # --------------------------- Estimator ------------------------------

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        self.check_wrapped(scene)           # (a wrapper may call sample() alone)
        if dr.hint(self.max_depth == 0, mode='scalar'):
            return mi.Spectrum(0), mi.Bool(False), []   # as `path`: no vertices

        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------

        ray = mi.Ray3f(ray)
        L = mi.Spectrum(0)                 # radiance accumulated so far
        β = mi.Spectrum(1)                 # path throughput ∏ f cos θ / p
        depth = mi.UInt32(0)               # index of the current vertex
        active = mi.Bool(active)

        # ------------------ Camera ray (emitters hidden) ------------------

        pi, valid_ray = self.camera_hit(scene, ray, active)

        # Which path this lane traces, for an estimator that learns from them
        lane = self.path_index(ray) if self.records_paths else None

        # Previous vertex, for MIS weights of emitter hits
        prev_si = dr.zeros(mi.Interaction3f)
        prev_pdf = mi.Float(1)
        prev_delta = mi.Bool(True)                 # camera rays count as delta
        η = mi.Float(1)

        while dr.hint(active, max_iterations=-1,
                      label=f"mcillum estimator ({self.plugin_name})"):
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All)

            # -------------------- Emission at the hit ---------------------

            # L += β · w · L_e(x, -ω): area light at a surface hit, environment
            # when the ray escaped (si.emitter() returns it for invalid si).
            emitter = si.emitter(scene)
            # (no `~` on masks here: in scalar variants they are Python bools)
            visible = active & ((not self.hide_emitters) | (depth > 0))
            if emitter != None:
                w_hit = self.hit_weight(scene, si, prev_si, prev_pdf, prev_delta)
                L += β * w_hit * emitter.eval(si, visible)
            if dr.hint(self.records_paths, mode='scalar'):
                self.record_emission(lane, depth, si, L, active)

            valid_ray |= active & si.is_valid()

            # Does the path get one more vertex?
            active_next = active & (depth + 1 < self.max_depth) & si.is_valid()

            # What Russian roulette multiplies β by (1: as `path`)
            rr_factor = mi.Float(1)

            if active_next:  # (masked in JIT variants, a plain branch in scalar)
                bsdf = si.bsdf(ray)

                # ---------------- Emitter sampling (NEE) -----------------

                if dr.hint(self.use_nee, mode='scalar'):
                    L += β * self.emitter_sample(scene, sampler, si, bsdf, bsdf_ctx)

                # ---------------- Sample the next direction ----------------

                # β ← β · f_r(ω, ω_o) cos θ / p(ω)
                wo, weight, pdf, delta, eta = self.sample_direction(
                    scene, sampler, si, bsdf, bsdf_ctx)
                β *= weight
                rr_factor = self.roulette_factor(si, bsdf, bsdf_ctx, wo, pdf)
                η *= eta
                prev_si = mi.Interaction3f(si)
                prev_pdf = pdf
                prev_delta = delta
                ray = si.spawn_ray(si.to_world(wo))
                if dr.hint(self.records_paths, mode='scalar'):
                    self.record_vertex(lane, depth, si, ray.d, pdf, delta, β, L, active_next)

            # --------------------- Stopping criterion ---------------------

            depth = dr.select(si.is_valid(), depth + 1, depth)

            # Russian roulette as `path`: survive with min(max β·r·η², .95)
            β_max = dr.max(mi.unpolarized_spectrum(β))
            rr_prob = dr.minimum(β_max * rr_factor * dr.square(η), 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d(active_next) < rr_prob
            β = dr.select(rr_active, β * dr.rcp(rr_prob), β)

            active = active_next & ((depth < self.rr_depth) | rr_continue) & (β_max != 0)
            pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active)

        if dr.hint(self.records_paths, mode='scalar'):
            self.record_path(lane, L)
        return dr.select(valid_ray, L, 0), valid_ray, []

    def camera_hit(self, scene, ray, active):
        """(preliminary intersection of the camera ray, valid_ray): the
        environment counts as "hit" (alpha = 1) unless emitters are hidden;
        with ``hide_emitters``, as `path` does, the ray looks through
        directly visible area emitters."""
        valid_ray = mi.Bool((not self.hide_emitters) and (scene.environment() is not None))
        pi = scene.ray_intersect_preliminary(ray, coherent=True, active=active)
        if self.hide_emitters:
            si0 = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
            skip = active & si0.is_valid() & (si0.emitter(scene) != None)  # noqa: E711
            pi_behind = self.skip_area_emitters(scene, si0.spawn_ray(ray.d), True, skip)
            pi = dr.select(skip, pi_behind, pi)
        return pi, valid_ray

    # ------------------------ NEE and MIS helpers ------------------------

    def hit_weight(self, scene, si, prev_si, prev_pdf, prev_delta):
        """Weight of emission found by following a sampled direction."""
        if dr.hint(not self.use_nee, mode='scalar'):
            return mi.Float(1)                  # the hit is the only estimate
        if dr.hint(not self.use_mis, mode='scalar'):
            # NEE already counted every light it can sample: keep only what it
            # cannot (seen by the camera, or through a delta lobe).
            return dr.select(prev_delta, 1.0, 0.0)
        ds = mi.DirectionSample3f(scene, si, prev_si)
        em_pdf = self.emitter_pdf(scene, prev_si, ds, dr.select(prev_delta, False, True))
        return dr.select(prev_delta, 1.0, mis_weight(prev_pdf, em_pdf))

    def emitter_sample(self, scene, sampler, si, bsdf, ctx):
        """f cos · L_e / p_e for one emitter sample (MIS-weighted if use_mis)."""
        active_em = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_weight = self.sample_emitter(scene, si, sampler.next_2d(), active_em)
        wo = si.to_local(ds.d)
        f_cos, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, active_em)
        w = mi.Float(1)
        if dr.hint(self.use_mis, mode='scalar'):
            # (the other technique is the continuation: its pdf at ω)
            p_cont = self.continuation_pdf(si, bsdf, ds.d, bsdf_pdf)
            w = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, p_cont))
        return dr.select(active_em & (ds.pdf != 0), f_cos * em_weight * w, 0)

    def roulette_factor(self, si, bsdf, ctx, wo, pdf):
        """What Russian roulette multiplies the throughput by after a
        continuation ``wo`` (local) of density ``pdf``: 1 by default, as
        `path`. Any factor > 0 leaves the image unbiased: β is divided by
        the survival probability it sets."""
        return mi.Float(1)

    def continuation_pdf(self, si, bsdf, wo_world, bsdf_pdf):
        """Density of :meth:`sample_direction` at world direction ``wo_world``
        for the MIS weight of an emitter sample; ``bsdf_pdf`` is the BSDF's
        there (the default: the continuation samples the BSDF)."""
        return bsdf_pdf

    # --------------- Learning from paths (records_paths only) ---------------

    def path_index(self, ray):
        """Index of each lane's path in the wavefront."""
        raise NotImplementedError

    def record_vertex(self, lane, depth, si, wo_world, pdf, delta, β, L, active):
        """A vertex that continued along ``wo_world`` (density ``pdf``), with
        the throughput β after it and the radiance L gathered before it."""
        raise NotImplementedError

    def record_emission(self, lane, depth, si, L, active):
        """The radiance gathered once the emission the last continuation hit
        is added (vertex ``depth`` - 1's direct light by that route), and
        where that continuation ended: ``si`` (invalid where it escaped)."""
        raise NotImplementedError

    def record_path(self, lane, L):
        """The radiance each path gathered in all."""
        raise NotImplementedError

    def to_string(self) -> str:
        depth = -1 if self.max_depth == UNBOUNDED else self.max_depth
        return (f"{type(self).__name__}[max_depth={depth}, rr_depth={self.rr_depth}, "
                f"hide_emitters={self.hide_emitters}]")
