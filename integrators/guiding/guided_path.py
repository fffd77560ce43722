"""Path guiding: a path tracer (as `mis`) whose continuation direction comes
from a one-sample mixture of the BSDF and a directional distribution learned
from the renderer's own paths while it renders (after Müller et al. 2017,
"Practical Path Guiding for Efficient Light-Transport Simulation"). What it
learns is in the modules beside it: the grid and anchors (spatial), the
tree (guide), the directional quadtree (directional), the records (records),
the tables it samples (tables), the iterations (trainer)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core import registry
from ..core.estimator import IlluminationEstimator, over_pdf
from ..mc.bsdf_sampling import sample_bsdf_direction
from ..mc.emitter_sampling import emitter_direction_pdf, sample_emitter_direction
from .spatial import (FAR, GRID, anchor_of, from_anchor, from_guide, grid_of,  # noqa: F401
                      guide_frame, on_plane, to_anchor, to_guide, voxel_of)
from .tables import guide_pdf, invert_guide, sample_guide, take  # noqa: F401
from .trainer import PASSES, PAYS_BELOW, Trainer, launch_pass

# ------------------------------ Plugin ----------------------------------


class GuidedPathIntegrator(IlluminationEstimator):
    r"""
    .. _integrator-guided_path:

    Guided path tracer (:monosp:`guided_path`)
    ------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: unbounded; 1: emitters seen directly; 2: direct
         illumination). (Default: -1)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts, as in ``path``. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content this strategy cannot reach instead of refusing the
         scene; the image is then biased and a warning says so. (Default: |false|)
     * - bsdf_fraction
       - |float|
       - Probability of drawing the continuation from the BSDF rather than
         the learned distribution where all light arrives indirectly (in
         (0, 1]; 1 is ``mis``); where a share s of it does, 1 − (1 −
         bsdf_fraction)·s. (Default: 0.5)
     * - train_fraction
       - |float|
       - Share of each render's samples per pixel spent learning, in
         iterations that double (in [0, 1)). Not given: iterations of 1, 2,
         4, … spp while the rest of the budget could still draw one twice as
         long (Müller et al.'s rule: the share grows with the budget, a
         third to a half of the samples). (Default: not given)
     * - train_passes
       - |int|
       - Training iterations at most (each traces the whole kernel once
         more; 0: no learning). (Default: 16)
     * - spatial_threshold
       - |float|
       - A node of the spatial tree splits while more than this many times
         √R of the R training vertices (all passes so far) fell in it.
         (Default: 20)
     * - directional_res
       - |int|
       - Cells per side of the unit square each leaf's pmf is over (a power
         of 2), warped to the hemisphere by the cosine warp: res² cells of
         equal cosine-weighted solid angle, the finest the learned density
         resolves. (Default: 32)
     * - directional_threshold
       - |float|
       - A quadtree cell of a leaf's square is refined while it carries more
         than this share of the leaf's light (in [0, 1); 0: every cell that
         has the records). (Default: 0.01)
     * - max_variance_ratio
       - |float|
       - Guide only where it pays: after each training pass, the variance of
         the indirect light's estimate with the learned mixture is predicted
         from the records, as a share of BSDF sampling's (per leaf and cell
         the records' mean L_i and L_i²: ``Guide.variance_ratio``); after a
         pass drawn with a learned density, the relative variance of its
         pixels' samples is also measured, as a share of the unguided first
         pass's (``guide.measured_ratios``; JIT variants). Above this share
         the rest of the render is ``mis``, whose kernel costs less per
         sample: the predicted share always, the measured one unless the
         guided pass's mean is well above the unguided one's (those paths
         missed light the guide found, and their variance reads low). A
         large value keeps every learned density.
         (Default: 0.8)
     * - combine_passes
       - |bool|
       - Combine the training iterations' images with the last pass's, each
         weighted by its spp over its relative variance per sample (one
         number per image; |false|: the result is the last pass alone).
         (Default: |true|)
     * - parallax
       - |bool|
       - Learn and draw each leaf's density as seen from an anchor (the
         centre of the vertex's block of 8³ voxels, moved onto its tangent
         plane), with the light on a sphere about it at the leaf's learned
         distance, so that a small source seen from all over a leaf falls in
         the same cells (|false|: the density is the same direction set at
         every point of a leaf). (Default: |true|)
     * - roulette
       - |string|
       - What Russian roulette reads: ``unguided``, the throughput with the
         last continuation's weight the larger of its own and the one BSDF
         sampling gives that direction (a direction the learned density
         favours, towards bright light, has a small weight *because* its
         light is strong); ``throughput``, the throughput, as ``path``.
         (Default: ``unguided``)

    Next-event estimation and the power heuristic as ``mis``; the path
    continues along a direction drawn, with probability α, from the BSDF,
    else from the distribution learned in the spatial cell
    of the vertex, and is weighted by f cos / p with p the mixture's density,
    so the image is unbiased whatever was learned: the BSDF's share keeps p
    positive wherever f is. Vertices with a delta or glossy lobe (the learned
    density, ∝ L_i cos θ, knows nothing of a lobe), and cells where nothing
    was learned, use the BSDF alone. α is ``bsdf_fraction`` where
    the cell's light all arrives indirectly and grows to 1 with the share
    that the continuation hits directly on emitters, which the learned
    distribution leaves to the BSDF's sample and NEE.

    **Learning** (a :class:`.trainer.Trainer` per render). Each call of
    ``render`` learns afresh, in iterations of doubling spp, each drawn with
    what the iterations before it learned (the first with the BSDF alone).
    Every path vertex of an iteration records its voxel (of a 32³ grid over
    the scene's bounds), where its continuation hit and L_i along it: the
    radiance the path gathered after it, less the emission the
    continuation hit (next-event estimation has that), over the throughput.
    Its cell is that of the direction to the point hit from its anchor
    (``parallax``), and the leaf learns the distance of its light from the
    anchors (a harmonic mean weighted by L_i, so the nearest bright light
    sets it). After every iteration, from the records of all so far, a
    binary tree splits the grid while a node holds more than
    ``spatial_threshold``·√R of them; each leaf's pmf is its cells' mean
    L_i, so the density is ∝ indirect L_i cos θ, with the means taken over
    a quadtree that refines where light concentrates (cells above
    ``directional_threshold`` of the leaf's light) and stays coarse where
    records are few. Where nothing arrives indirectly the first iteration
    learns nothing and training stops; where what was learned is predicted
    to leave more than ``max_variance_ratio`` of BSDF sampling's variance
    of the indirect light (a smooth sky, light mostly direct) it stops too,
    and the rest of the samples render as ``mis``; so does a render whose
    guided iteration measured that it did not pay on its own paths. Every
    iteration's image is unbiased, whatever density drew it, so the result
    (``combine_passes``) weighs them all by inverse variance, none of the
    training samples lost; its wall time includes the learning. Nested in
    another integrator (``moment``, which calls ``sample`` only) nothing is
    learned and it renders as ``mis``.

    Russian roulette starts at ``rr_depth`` as ``path``'s, and reads what
    ``roulette`` says.

    .. tabs::

        .. code-tab:: xml

            <integrator type="guided_path">
                <integer name="max_depth" value="8"/>
                <integer name="train_passes" value="8"/>
            </integrator>
    """

    plugin_name = "guided_path"
    display_name = "path guiding (learned pdf)"
    colour = "#637939"
    reachable = frozenset({"delta_bsdf", "transmission", "delta_emitter"})
    max_direction_pdf = None                   # emitter samples find any source
    listing_order = 55
    use_nee = True
    use_mis = True
    records_paths = False                      # (True during a pass that records)
    learns = True                              # (the learning stage measures it)
    freezable = False                          # (it learns in Python between passes)
    freezes_passes = True                      # (... each pass is launch_pass)
    launch_pass = staticmethod(launch_pass)
    #: A frozen :func:`launch_pass` that every pass replays: the
    #: validation's untimed renders only (validation/run/replays.py); a
    #: timed render is traced, as a user's is.
    frozen_pass = None
    sample_emitter = staticmethod(sample_emitter_direction)
    emitter_pdf = staticmethod(emitter_direction_pdf)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.bsdf_fraction = float(props.get("bsdf_fraction", 0.5))
        # (None: a share of the budget that grows with it, trainer.budget_passes)
        self.train_fraction = (float(props["train_fraction"])
                               if "train_fraction" in props else None)
        self.train_passes = props.get("train_passes", PASSES)
        self.spatial_threshold = float(props.get("spatial_threshold", 20.0))
        self.directional_res = int(props.get("directional_res", 32))
        self.directional_threshold = float(props.get("directional_threshold", 0.01))
        self.combine_passes = bool(props.get("combine_passes", True))
        self.parallax = bool(props.get("parallax", True))
        self.roulette = str(props.get("roulette", "unguided"))
        self.max_variance_ratio = float(props.get("max_variance_ratio", PAYS_BELOW))
        self._check_properties()
        self._guide = None                  # what the pass being traced samples from
        self._records = None                # ... and records into
        self._delta_lights = False          # (the scene's emitters are all delta lights)
        #: The last render's learning: per training iteration its spp, the
        #: records learned from so far, the tree's leaves, those that
        #: learned, their mean BSDF share α, the predicted and measured
        #: variance ratios and the weight of its image in the result.
        self.training: list[dict] = []

    def _check_properties(self) -> None:
        """Raise ValueError naming the first property out of its range."""
        if not 0 < self.bsdf_fraction <= 1:
            raise ValueError(f"bsdf_fraction = {self.bsdf_fraction} is invalid: it must lie "
                             "in (0, 1] (the BSDF's share keeps the mixture unbiased)")
        if self.train_fraction is not None and not 0 <= self.train_fraction < 1:
            raise ValueError(f"train_fraction = {self.train_fraction} is invalid: use a "
                             "share of the samples in [0, 1) (0: no learning, as mis)")
        if isinstance(self.train_passes, bool) or not isinstance(self.train_passes, int) \
                or self.train_passes < 0:
            raise ValueError(f"train_passes = {self.train_passes!r} is invalid: use a "
                             "whole number of passes >= 0 (0: no learning, as mis)")
        if not self.spatial_threshold > 0:
            raise ValueError(f"spatial_threshold = {self.spatial_threshold} is invalid: "
                             "use a factor > 0 of the square root of the records, e.g. 20")
        if not 0 <= self.directional_threshold < 1:
            raise ValueError(f"directional_threshold = {self.directional_threshold} is "
                             "invalid: use a share of a cell's light in [0, 1), e.g. 0.01")
        if self.roulette not in ("unguided", "throughput"):
            raise ValueError(f"roulette = '{self.roulette}' is invalid: use 'unguided' (the "
                             "default) or 'throughput' (as path)")
        if not self.max_variance_ratio > 0:
            raise ValueError(f"max_variance_ratio = {self.max_variance_ratio} is invalid: use "
                             "a share > 0 of BSDF sampling's variance, e.g. 0.8")
        res = self.directional_res
        if res < 2 or res & (res - 1):
            raise ValueError(f"directional_res = {res} is invalid: use a power of 2 "
                             "(the cells are found by bisection), e.g. 8")

    # ---------------------------- Render ---------------------------------

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if getattr(self, "_in_pass", False):
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        sensor_ = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        spp = spp or sensor_.sampler().sample_count()
        self.check_scene(scene)
        grid = grid_of(scene.bbox())
        far = FAR * max(GRID / float(k) for k in grid[1])     # (× the grid's size)
        self._grid = grid                   # (read by the kernels as they are traced)
        self._delta_lights = all(mi.has_flag(e.flags(), mi.EmitterFlags.Delta)
                                 for e in scene.emitters())
        trainer = Trainer(self, scene, sensor, seed, spp, grid, far)
        self.training = trainer.log
        try:
            # Iterations of doubling spp, each drawn with what the ones
            # before it taught; the tree and densities rebuilt after each
            for n in trainer.schedule():
                if not trainer.iterate(n):
                    trainer.stop()          # (what it would teach now is not learned)
                    break
                if not trainer.learn():
                    break                   # (the rest renders as mis)
            # The rest of the budget with the last density, every image
            # weighed by its inverse variance
            return trainer.render_rest(develop, evaluate)
        finally:
            # (a wrapper calling sample() alone later renders as mis, not
            # with this scene's guide)
            self._records, self.records_paths, self._guide = None, False, None

    def launch(self, scene, sensor, seed, spp, develop, evaluate, guide, records):
        """One pass of ``spp`` drawn with ``guide`` (device arrays; None: as
        mis) recording into ``records`` (None: nothing): Mitsuba's render,
        or :attr:`frozen_pass` replaying it (a developed film only)."""
        self._guide, self._records, self.records_paths = guide, records, records is not None
        try:
            if self.frozen_pass is None or not develop:
                return super().render(scene, sensor, seed, spp, develop, evaluate)
            # (an opaque seed: one recording per spp, not one per seed)
            image, arrays = self.frozen_pass(
                scene, self, sensor, spp, dr.opaque(mi.UInt32, seed), guide,
                records.arrays() if records is not None else None)
            if arrays is not None:
                records.hold(arrays)
            return image
        finally:
            self._guide, self._records = guide, records    # (not the recording's)
            self.records_paths = False

    # ------------------------- Training records ---------------------------

    def path_index(self, ray):
        return self._records.lane(ray)

    def record_vertex(self, lane, depth, si, wo_world, pdf, delta, β, L, active):
        self._records.vertex(lane, depth, si, wo_world, pdf, delta, β, L, active)

    def record_emission(self, lane, depth, si, L, active):
        self._records.emission(lane, depth, si, L, active)

    def record_path(self, lane, L):
        self._records.path_radiance(lane, L)

    # ------------------------- Sample the next direction -------------------

    def mixture(self, si, bsdf):
        """(the BSDF's share α at this vertex, its leaf's row): α = 1
        for a BSDF with a delta or glossy lobe and where nothing was
        learned."""
        node = take(self._guide["leaf"], voxel_of(si.p, self._grid))
        alpha = take(self._guide["alpha"], node)
        # (the learned density ∝ L_i cos θ knows nothing of a lobe)
        flags = bsdf.flags()
        plain = mi.has_flag(flags, mi.BSDFFlags.Delta) | mi.has_flag(flags, mi.BSDFFlags.Glossy)
        alpha = dr.select(plain, 1.0, alpha)
        return alpha, node

    def sample_direction(self, scene, sampler, si, bsdf, ctx):
        u_pick, u1, u2 = sampler.next_1d(), sampler.next_1d(), sampler.next_2d()
        if self._guide is None:
            return sample_bsdf_direction(bsdf, ctx, si, u1, u2)
        g, res = self._guide, self.directional_res
        alpha, row = self.mixture(si, bsdf)
        from_bsdf = u_pick < alpha

        # Either technique's direction (both drawn: the lanes pick one)
        wo_b, w_b, pdf_b, delta_b, eta_b = sample_bsdf_direction(bsdf, ctx, si, u1, u2)
        wg, _ = sample_guide(g["slot"], row, res, u1, u2)
        c, d = self.anchor(si, row)
        wo_g = from_anchor(si.p, from_guide(si, wg), c, d)
        wo = dr.select(from_bsdf, wo_b, si.to_local(wo_g))

        # p = α p_bsdf + (1 - α) p_guide;  weight = f cos / p
        f_cos, p_bsdf = bsdf.eval_pdf(ctx, si, wo)
        p = alpha * p_bsdf + (1 - alpha) * self.guide_density(si, row, si.to_world(wo))
        # (α = 1 is BSDF sampling as it is, delta lobes included)
        plain = alpha >= 1
        weight = dr.select(plain, w_b, over_pdf(f_cos, p))
        pdf = dr.select(plain, pdf_b, p)
        delta = plain & delta_b
        eta = dr.select(from_bsdf, eta_b, 1.0)
        return wo, weight, pdf, delta, eta

    def roulette_factor(self, si, bsdf, ctx, wo, pdf):
        # max(1, p / p_bsdf): roulette reads the last continuation's weight as
        # the larger of f cos / p and f cos / p_bsdf. A direction the learned
        # density favours (towards a bright patch) has a small weight
        # because its light is strong, and roulette on that weight killed
        # exactly the paths that carried the light there; the BSDF's draws
        # keep their own weight. Only the last step's: carried on (∏ over
        # the path), paths ran on past the patch for 1.3× the time
        # (docs/measurements.md#2026-12-06-guided-path-densities-seen-anchors).
        if self._guide is None or self.roulette == "throughput":
            return mi.Float(1)
        p_bsdf = bsdf.pdf(ctx, si, wo)
        return dr.select((pdf > p_bsdf) & (p_bsdf > 0), pdf / p_bsdf, 1.0)

    def continuation_pdf(self, si, bsdf, wo_world, bsdf_pdf):
        # (where every emitter is a delta light an emitter sample's MIS
        # weight is 1, whatever this density: the learned one, two lookups
        # per vertex, cost 0.12× path's time per sample on sunlit_room_hole)
        if self._guide is None or self._delta_lights:
            return bsdf_pdf
        alpha, row = self.mixture(si, bsdf)
        return alpha * bsdf_pdf + (1 - alpha) * self.guide_density(si, row, wo_world)

    def anchor(self, si, row):
        """(anchor, learned distance of its light) of the vertex ``si`` in
        leaf ``row``."""
        if not self.parallax:
            return si.p, mi.Float(0.0)
        c = on_plane(anchor_of(si.p, self._grid), si.p, guide_frame(si).n)
        return c, take(self._guide["distance"], row)

    def guide_density(self, si, row, wo_world):
        """The learned density at world direction ``wo_world`` (0 where its
        direction from the anchor is on the side the path did not arrive
        from)."""
        c, d = self.anchor(si, row)
        w_c, jacobian = to_anchor(si.p, wo_world, c, d)
        return guide_pdf(self._guide["pmf"], row, self.directional_res,
                         to_guide(si, w_c)) * jacobian

    def to_string(self) -> str:
        return (super().to_string()[:-1] + f", bsdf_fraction={self.bsdf_fraction}, "
                f"train_fraction={self.train_fraction}]")


registry.register(GuidedPathIntegrator)
