"""Path guiding: a path tracer (as `mis`) whose continuation direction comes
from a one-sample mixture of the BSDF and a directional distribution learned
from the renderer's own paths while it renders (after Müller et al. 2017,
"Practical Path Guiding for Efficient Light-Transport Simulation")."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core import registry
from ..core.estimator import IlluminationEstimator, over_pdf
from ..mc.bsdf_sampling import sample_bsdf_direction
from ..mc.emitter_sampling import emitter_direction_pdf, sample_emitter_direction
from .guide import (FAR, GRID, MAX_RECORDS, PASSES, PAYS_BELOW, SLOTS_PER_CELL, TRAIN_DEPTH,
                    TRAIN_FRACTION, UNSEEN_ABOVE, Guide, PixelMoments, Records, Tally, anchor_of,
                    grid_of, measured_ratios, on_plane, pass_seed, square_cell, take,
                    training_passes, voxel_of)

# ----------------------------- Strategy ---------------------------------
# The learned part is a piecewise-constant density on the unit square, warped
# to the hemisphere by the cosine warp (Shirley-Chiu's concentric map, as
# mi.warp.square_to_cosine_hemisphere) in a frame built from the shading
# normal alone, turned to the side the path arrived from: a uniform pmf is
# cosine sampling, and a pmf ∝ the mean L_i over each of the res² cells makes
# p ∝ L_i cos θ (the product a diffuse vertex wants). Directions on the
# other side get density 0: the BSDF's share covers them.
#     p(ω) = pmf[cell(ω)] · res² · cos θ / π
# It is the density seen from the vertex's anchor c (guide.anchor_of), as
# if the light lay on a sphere about c of radius r (the leaf's learned
# distance, at least 2|x − c|): a vertex x draws ω_c, then ω towards
# y = c + r ω_c (parallax), and
#     p_x(ω) = p(ω_c) · t² / (r² cos θ_y),   y = x + t ω on the sphere,
# cos θ_y the angle between ω and the sphere's normal ω_c at y.


def guide_frame(si) -> mi.Frame3f:
    """The frame of the shading normal turned to the side of ``si.wi``: it
    depends on the normal and side only (Frame3f's coordinate system), so
    every surface of one orientation in a cell shares it."""
    return mi.Frame3f(si.sh_frame.n * dr.select(si.wi.z >= 0, 1.0, -1.0))


def to_guide(si, w_world: mi.Vector3f) -> mi.Vector3f:
    """World direction → the guide's frame at ``si`` (the side the path
    arrived from is z > 0)."""
    return guide_frame(si).to_local(w_world)


def from_guide(si, w: mi.Vector3f) -> mi.Vector3f:
    """The inverse of :func:`to_guide`."""
    return guide_frame(si).to_world(w)


def anchor_radius(x: mi.Point3f, c: mi.Point3f, d: mi.Float) -> mi.Float:
    """Radius of the sphere about the anchor ``c`` that the vertex ``x``
    maps through: the learned distance ``d``, at least twice x's distance
    from c (x then lies inside it, and cos θ_y ≥ √3/2); 0 where no distance
    was learned (ω_c = ω)."""
    return dr.select(d > 0, dr.maximum(d, 2 * dr.norm(x - c)), 0.0)


def from_anchor(x: mi.Point3f, w_c: mi.Vector3f, c: mi.Point3f, d: mi.Float) -> mi.Vector3f:
    """The direction from ``x`` to the point of the sphere about ``c``
    (:func:`anchor_radius`) in direction ``w_c`` from its centre."""
    r = anchor_radius(x, c, d)
    return dr.select(r > 0, dr.normalize(c + r * w_c - x), w_c)


def to_anchor(x: mi.Point3f, w: mi.Vector3f, c: mi.Point3f, d: mi.Float) -> tuple:
    """(ω_c, dω_c/dω): the inverse of :func:`from_anchor` and its Jacobian.
    From x inside the sphere the ray x + t ω leaves it once: t = −b + √(b² −
    (|o|² − r²)), o = x − c, b = ω·o."""
    r = anchor_radius(x, c, d)
    o = x - c
    b = dr.dot(w, o)
    t = -b + dr.safe_sqrt(dr.square(b) - (dr.squared_norm(o) - dr.square(r)))
    w_c = (o + t * w) / dr.maximum(r, 1e-30)
    jacobian = dr.square(t) / dr.maximum(dr.square(r) * dr.dot(w, w_c), 1e-30)
    on = r > 0
    return dr.select(on, w_c, w), dr.select(on, jacobian, 1.0)


def sample_guide(slot, row, res: int, u1: mi.Float, u2: mi.Point2f):
    """(ω in the guide frame, upper side; cell): the cell of slot ⌊u1·S⌋ of
    pmf ``row``'s S = SLOTS_PER_CELL·res² equal-probability slots (one
    gather: each cell owns as many slots as its quantized pmf, see
    :func:`guide_tables`); ``u2`` uniform in the cell, then the cosine warp."""
    slots = SLOTS_PER_CELL * res * res
    k = dr.minimum(mi.UInt32(u1 * slots), slots - 1)
    c = take(slot, row * slots + k)
    u = mi.Point2f((mi.Float(c % res) + u2.x) / res, (mi.Float(c // res) + u2.y) / res)
    return mi.warp.square_to_cosine_hemisphere(u), c


def guide_pdf(pmf, row, res: int, w: mi.Vector3f) -> mi.Float:
    """Solid-angle density of :func:`sample_guide` at ``w`` (guide frame,
    upper side; 0 below): pmf · res² · cos θ / π."""
    cell = square_cell(mi.warp.cosine_hemisphere_to_square(w), res)
    return dr.select(w.z > 0, take(pmf, row * (res * res) + cell) * (res * res) * w.z
                     * dr.inv_pi, 0.0)


def invert_guide(first, pmf, row, res: int, w: mi.Vector3f):
    """(u1, u2) that :func:`sample_guide` maps to ``w`` (u1 the middle of its
    cell's slots)."""
    u = mi.warp.cosine_hemisphere_to_square(w)
    c = square_cell(u, res)
    i = row * (res * res) + c
    slots = SLOTS_PER_CELL * res * res
    u1 = (mi.Float(take(first, i)) + 0.5 * take(pmf, i) * slots) / slots
    return u1, mi.Point2f(u.x * res - mi.Float(c % res), u.y * res - mi.Float(c // res))


# ----------------------------- One pass ---------------------------------


def launch_pass(scene, integrator, sensor, spp: int, seed, guide, records):
    """One pass of ``integrator``, a function of its arguments alone: (the
    image, the arrays of the training ``records`` after the pass scattered
    into them, or None where it records nothing). What it reads (``guide``,
    :meth:`Guide.device`'s arrays, or None) and writes are arguments, so
    Dr.Jit can freeze it and a replay launches the recorded kernels with
    another guide and seed (validation/run/replays.py)."""
    integrator._guide = guide
    if records is not None:
        integrator._records.hold(records)
    image = IlluminationEstimator.render(integrator, scene, sensor, seed, spp)
    # (the sampler's state now depends on the whole pass: left so, a
    # recording would evaluate it, a second kernel 0.6x the pass's, as
    # mi.render's own re-seeding says)
    sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
    sensor.sampler().seed(0, 1)
    return image, (None if records is None else integrator._records.arrays())


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
       - Share of each render's samples per pixel spent learning, in passes
         of 1, 2, 4, … spp (in [0, 1)). (Default: 0.125)
     * - train_passes
       - |int|
       - Training passes at most (each traces the whole kernel once more;
         0: no learning). (Default: 2)
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
       - Average the training passes' images into the result, each weighted
         by its spp (|false|: the result is the last pass alone). (Default: |true|)
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

    **Learning.** Each call of ``render`` learns afresh, in at most
    ``train_passes`` training passes of doubling spp (``train_fraction`` of
    the samples), each drawn with what the passes before it learned. Every
    path vertex records its
    voxel (of a 32³ grid over the scene's bounds), where its continuation
    hit and L_i along it: the radiance the path gathered after it, less the
    emission the continuation hit (next-event estimation has that), over the
    throughput. Its cell is that of the direction to the point hit from its
    anchor (``parallax``), and the leaf learns the distance of its light
    from the anchors (a harmonic mean weighted by L_i, so the nearest bright
    light sets it). From the pooled records a binary tree splits the grid while
    a node holds more than ``spatial_threshold``·√R of them; each leaf's pmf is
    its cells' mean L_i, so the density is ∝ indirect L_i cos θ, with the
    means taken over a quadtree that refines where light concentrates (cells
    above ``directional_threshold`` of the leaf's light) and stays coarse
    where records are few. Where nothing arrives indirectly the first pass
    learns nothing and training stops; where what was learned is predicted
    to leave more than ``max_variance_ratio`` of BSDF sampling's variance of
    the indirect light (a smooth sky, light mostly direct) it stops too, and
    the rest of the samples render as ``mis``; so does a render whose guided
    pass measured that it did not pay on its own paths (the light mostly
    direct to the camera's first hits, where the indirect light's gain is a
    small share of a pixel's). Every pass's image is
    unbiased, whatever density drew it, so the result (``combine_passes``)
    is their average weighted by spp: the mean of all the render's samples,
    none of the training samples lost; its wall time includes the learning.
    Nested in another integrator (``moment``, which calls ``sample`` only)
    nothing is learned and it renders as ``mis``.

    Russian roulette starts at ``rr_depth`` as ``path``'s, and reads what
    ``roulette`` says.

    .. tabs::

        .. code-tab:: xml

            <integrator type="guided_path">
                <integer name="max_depth" value="8"/>
                <float name="train_fraction" value="0.125"/>
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
    records_paths = False                      # (True during training passes)
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
        self.train_fraction = float(props.get("train_fraction", TRAIN_FRACTION))
        self.train_passes = props.get("train_passes", PASSES)
        self.spatial_threshold = float(props.get("spatial_threshold", 20.0))
        self.directional_res = int(props.get("directional_res", 32))
        self.directional_threshold = float(props.get("directional_threshold", 0.01))
        self.combine_passes = bool(props.get("combine_passes", True))
        self.parallax = bool(props.get("parallax", True))
        self.roulette = str(props.get("roulette", "unguided"))
        self.max_variance_ratio = float(props.get("max_variance_ratio", PAYS_BELOW))
        if not 0 < self.bsdf_fraction <= 1:
            raise ValueError(f"bsdf_fraction = {self.bsdf_fraction} is invalid: it must lie "
                             "in (0, 1] (the BSDF's share keeps the mixture unbiased)")
        if not 0 <= self.train_fraction < 1:
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
        self._guide = None                  # device arrays of the current guide
        self._records = None
        self._images = []                   # (during a render: its training images)
        #: The last render's learning: per training pass its spp, the records
        #: learned from so far, the tree's leaves, those that learned and
        #: their mean BSDF share α.
        self.training: list[dict] = []

    # ---------------------------- Render ---------------------------------

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if getattr(self, "_in_pass", False):
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        sensor_ = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        spp = spp or sensor_.sampler().sample_count()
        self.check_scene(scene)
        self._guide, self.training = None, []
        self._grid = grid_of(scene.bbox())
        self._far = FAR * max(GRID / float(k) for k in self._grid[1])   # (× the grid's size)
        pixels = int(dr.prod(sensor_.film().crop_size()))
        depth = int(min(self.max_depth, TRAIN_DEPTH))
        tally = Tally(self.directional_res)   # the records of every pass so far
        self._images = []                   # (spp, image) of every training render
        unguided = PixelMoments()           # the pixels' samples drawn without a guide
        try:
            for i, n in enumerate(training_passes(spp, self.train_fraction,
                                                  self.train_passes)):
                drawn = unguided if self._guide is None else PixelMoments()
                measured, paid = self._train(scene, sensor, pass_seed(seed, i), n, pixels,
                                             depth, tally, drawn, unguided)
                entry = {"spp": n, "records": tally.records, "leaves": None,
                         "trained_leaves": None, "bsdf_share": None, "variance_ratio": None,
                         "measured_ratio": measured}
                self.training.append(entry)
                if not paid:
                    # (what it would learn now is not learned: nothing reads it)
                    self._guide = None
                    break
                guide = Guide.learn(tally, self.spatial_threshold, self.directional_threshold)
                ratio = guide.variance_ratio(self.bsdf_fraction)
                entry.update(leaves=guide.leaves, trained_leaves=guide.trained_leaves,
                             bsdf_share=guide.bsdf_share(self.bsdf_fraction),
                             variance_ratio=ratio)
                if not guide.trained_leaves:
                    break           # (nothing arrives indirectly: the rest renders as mis)
                # (a guide that cuts little of the variance costs more than it
                # buys: sky_sphere and probe_spheres predict 0.86-0.98 and
                # render 1.3-2.4x path's time for no lower error)
                if not ratio <= self.max_variance_ratio:
                    self._guide = None
                    break
                self._guide = guide.device(self.bsdf_fraction)
            rest = spp - sum(t["spp"] for t in self.training)
            image = self._launch(scene, sensor, seed, rest, develop, evaluate)
            if not (develop and self.combine_passes and self._images):
                return image                # (an undeveloped film holds the last pass)
            # ------------------ Combine the passes ------------------
            # Σ n_i·image_i / spp: unbiased, as each pass is. Against the last
            # pass alone (a share f of the spp trained, variances v0 before
            # learning and v1 after) it is better unless v0 > v1·(2−f)/(1−f),
            # 2.1× at f = ⅛; the learned density cut variance by 1.9× at most
            # (docs/measurements.md, 2026-12-03).
            # (the weights opaque: as literals, every new spp compiled a
            # kernel, and a timed render that compiles is rendered again)
            def weight(n):
                return dr.opaque(mi.Float, n / spp)
            total = image * weight(rest)
            for n, im in self._images:
                total += im * weight(n)
            return total
        finally:
            # (a wrapper calling sample() alone later renders as mis, not
            # with this scene's guide)
            self._records, self.records_paths, self._guide = None, False, None
            self._images = []

    def _train(self, scene, sensor, seed, spp, pixels, depth, tally, moments, unguided):
        """One training pass of ``spp`` (in pieces of at most MAX_RECORDS
        vertices), sampling with the guide learned so far; its pixels'
        moments are added to ``moments`` (:class:`PixelMoments`; for a pass
        drawn without a guide, ``unguided`` itself), its vertices' records
        (:meth:`Records.learned`) to ``tally`` unless the pass did not pay.
        Every record estimates L_i whatever density drew it, so the
        passes' records are pooled. Returns (the measured share of the
        unguided pass's relative variance, NaN where not measured; whether
        the pass paid)."""
        pieces = max(1, -(-pixels * spp * depth // MAX_RECORDS))
        sizes = [n for n in (spp // pieces + (k < spp % pieces) for k in range(pieces)) if n]
        measured, paid = float("nan"), True
        for k, n in enumerate(sizes):
            self._records, self.records_paths = Records(pixels * n, depth), True
            self._images.append(
                (n, self._launch(scene, sensor, pass_seed(seed, 1000 + k), n, True, True)))
            moments.add(self._records.pixel_moments(pixels))
            if k == len(sizes) - 1 and moments is not unguided:
                # (the guide that drew this pass did not pay on its own
                # paths, and they found no light the unguided ones missed:
                # the Cornell box at 128² × 24-96 spp measured 0.84-1.02 and
                # guided at 0.6-0.8× path's efficiency; NaN, which pays, in
                # scalar variants)
                measured, means = measured_ratios(unguided, moments)
                paid = not (measured > self.max_variance_ratio and means <= UNSEEN_ABOVE)
                if not paid:
                    break
            tally.add(*self._records.learned(self._grid, self.directional_res, self.parallax))
        self.records_paths = False
        return measured, paid

    def _launch(self, scene, sensor, seed, spp, develop, evaluate):
        """One pass: Mitsuba's render, or :attr:`frozen_pass` replaying it
        (a developed film only)."""
        if self.frozen_pass is None or not develop:
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        guide, records = self._guide, self._records
        try:
            # (an opaque seed: one recording per spp, not one per seed)
            image, arrays = self.frozen_pass(
                scene, self, sensor, spp, dr.opaque(mi.UInt32, seed), guide,
                records.arrays() if self.records_paths else None)
        finally:
            self._guide, self._records = guide, records    # (not the recording's)
        if arrays is not None:
            records.hold(arrays)
        return image

    # ------------------------- Training records ---------------------------

    def path_index(self, ray):
        if dr.is_jit_v(mi.Float):
            return dr.arange(mi.UInt32, dr.width(ray))
        return next(self._records.lanes_taken)   # (scalar: one path per call)

    def record_vertex(self, lane, depth, si, wo_world, pdf, delta, β, L, active):
        rec = self._records
        # one to the other side of the guide frame is not learned
        g = guide_frame(si).n
        voxel = voxel_of(si.p, self._grid)
        # (until the continuation hits something: far along it)
        far = si.p + wo_world * self._far
        # (no `~` on masks: in scalar variants they are Python bools)
        keep = dr.select(delta, False, active & (depth < rec.depth) & (pdf > 0)
                         & (dr.dot(g, wo_world) > 0))
        if not dr.is_jit_v(mi.Float):
            if keep:
                rec.rows[(lane, depth)] = [voxel, dr.mean(β), dr.mean(L), dr.mean(L),
                                           mi.Point3f(si.p), mi.Point3f(far), mi.Vector3f(g)]
            return
        i = lane * rec.depth + depth
        dr.scatter(rec.voxel, voxel + 1, i, keep)
        dr.scatter(rec.beta, dr.mean(β), i, keep)
        dr.scatter(rec.L, dr.mean(L), i, keep)
        dr.scatter(rec.hit, dr.mean(L), i, keep)       # (until an emission is hit)
        for k in range(3):
            dr.scatter(rec.x[k], si.p[k], i, keep)
            dr.scatter(rec.y[k], far[k], i, keep)
            dr.scatter(rec.g[k], g[k], i, keep)

    def record_emission(self, lane, depth, si, L, active):
        # Emission the continuation hit is direct light, which next-event
        # estimation samples too (exactly, under an importance-sampled map):
        # the density learns what arrives indirectly, so that q does not take
        # the emitter sample's MIS weight where it samples best; the direct
        # part sets the BSDF's share of the mixture (mixture_share).
        # Where the continuation hit a surface, that point is where the
        # vertex's light came from (parallax).
        rec = self._records
        if not dr.is_jit_v(mi.Float):
            row = rec.rows.get((lane, depth - 1)) if depth >= 1 else None
            if active and row is not None:
                row[3] = dr.mean(L)
                if si.is_valid():
                    row[5] = mi.Point3f(si.p)
            return
        i = lane * rec.depth + depth - 1
        here = active & (depth >= 1) & (depth <= rec.depth)
        dr.scatter(rec.hit, dr.mean(L), i, here)
        for k in range(3):
            dr.scatter(rec.y[k], si.p[k], i, here & si.is_valid())

    def record_path(self, lane, L):
        rec = self._records
        if not dr.is_jit_v(mi.Float):
            rec.path_L[lane] = dr.mean(L)
            return
        dr.scatter(rec.path, dr.mean(L), lane)

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
        # (docs/measurements.md, 2026-12-06).
        if self._guide is None or self.roulette == "throughput":
            return mi.Float(1)
        p_bsdf = bsdf.pdf(ctx, si, wo)
        return dr.select((pdf > p_bsdf) & (p_bsdf > 0), pdf / p_bsdf, 1.0)

    def continuation_pdf(self, si, bsdf, wo_world, bsdf_pdf):
        if self._guide is None:
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
