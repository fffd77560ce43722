"""The passes of one `guided_path` render (:class:`Trainer`): iterations
of doubling samples per pixel, each drawn with the density the iterations
before it taught and teaching the next, while the budget is better spent
learning; then the rest of the budget with the last density; then every
iteration's image combined by inverse variance. After Müller et al. 2017
("Practical Path Guiding") and Müller 2019 ("... in Production")."""

from __future__ import annotations

import hashlib

import drjit as dr
import mitsuba as mi

from ..core.estimator import IlluminationEstimator
from .guide import Guide
from .moments import (UNSEEN_ABOVE, PixelMoments, inverse_variance_weights, measured_ratios,
                      relative_variances)
from .records import MAX_RECORDS, TRAIN_DEPTH, Records, Tally

#: Training iterations at most, by default (each traces the kernel again).
PASSES = 16
#: Vertex records learned from per iteration at most: the rest of a long
#: iteration renders with its density but records nothing. A recording
#: launch cost 2.5× a guided one per sample at 256² (twelve scatters per
#: vertex) and its records as much again on the host; and the oracle bound
#: moved little from 2 M to 118 M training paths (learned density 7.8 →
#: 7.1 of cosine sampling's 56;
#: docs/measurements.md#2026-12-07-guided-path-trained-across-budget).
ITERATION_RECORDS = MAX_RECORDS
#: Guiding goes on while the learned mixture is predicted to leave at most
#: this share of BSDF sampling's variance of the indirect light
#: (Guide.variance_ratio), and while an iteration it drew measured at most
#: this share of the unguided iteration's relative variance per sample
#: (moments.measured_ratios): the guided kernel costs more than mis's per
#: sample, and the indirect light is only part of a pixel's variance.
PAYS_BELOW = 0.8
#: Samples an iteration needs before what it measured can stop the
#: guiding: sunlit_room under its hole at 64² measured 0.47 of the unguided
#: variance at 2 spp and 0.98 at 4 spp (16 384 samples), heavy tails
#: swinging the estimate; 2¹⁶ samples are 1 spp at 256², 4 at 128².
MEASURED_FROM = 1 << 16
#: Records a density needs before its predicted share may stop the
#: training: one learned from fewer is coarse and near uniform, and
#: predicts no gain where more records would find one (sunlit_room at 24²
#: learned from its first 1 spp, 576 paths, predicted 0.96 and never
#: guided; main's first pass of ⅛ of 256 spp had about this many).
JUDGED_FROM = 1 << 15


def budget_passes(spp: int, passes: int = PASSES) -> list[int]:
    """spp of the training iterations of a render of ``spp``: 1, 2, 4, …
    (at most ``passes``) while, after an iteration, the rest of the budget
    could still draw one twice as long (Müller et al.'s rule: the final
    render, with the best density, gets at least half the budget's samples
    but for the training's last iteration)."""
    out, used = [], 0
    while len(out) < passes and spp - used - 2 ** len(out) >= 2 ** (len(out) + 1):
        used += 2 ** len(out)
        out.append(2 ** (len(out)))
    return out


def training_passes(spp: int, fraction: float, passes: int = PASSES) -> list[int]:
    """spp of the training iterations where a share of the budget is given:
    ``fraction`` of ``spp`` (leaving at least one sample for the image) in
    at most ``passes`` iterations that double, the first at least 1 spp."""
    budget = max(int(min(fraction * spp, spp - 1)), 0)
    k = min(passes, (budget + 1).bit_length() - 1)   # 2^k - 1 ≤ budget
    if k == 0:
        return []
    unit = budget // (2 ** k - 1)
    out = [unit * 2 ** i for i in range(k)]
    out[-1] += budget - sum(out)
    return out


def pass_seed(seed: int, i: int) -> int:
    """Seed of launch ``i`` of the render with ``seed``: hashed, so that no
    other render's seed gives the same samples."""
    digest = hashlib.blake2s(f"guided_path {int(seed)} {i}".encode(), digest_size=4)
    return int.from_bytes(digest.digest(), "little")


# ------------------------------ One pass ------------------------------------


def launch_pass(scene, integrator, sensor, spp: int, seed, guide, records):
    """One pass of ``integrator``, a function of its arguments alone: (the
    image, the arrays of the ``records`` after the pass scattered into them,
    or None where it records nothing). What it reads (``guide``,
    :meth:`.guide.Guide.device`'s arrays, or None) and writes are
    arguments, so Dr.Jit can freeze it and a replay launches the recorded
    kernels with another guide and seed (validation/run/replays.py)."""
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


class Trainer:
    """One render's iterations: what they drew (:attr:`images`, :attr:`moments`),
    what they taught (:attr:`tally`, :attr:`guide`) and the log of each
    (:attr:`log`, the plugin's ``training``). It launches passes through
    ``integrator.launch(scene, sensor, seed, spp, develop, evaluate, guide,
    records)`` and reads the integrator's settings."""

    def __init__(self, integrator, scene, sensor, seed: int, spp: int, grid, far: float):
        self.integrator, self.scene, self.sensor, self.seed = integrator, scene, sensor, seed
        self.spp, self.grid, self.far = spp, grid, far
        self.depth = int(min(integrator.max_depth, TRAIN_DEPTH))
        self.tally = Tally(integrator.directional_res)     # the records of every iteration
        self.guide = None                   # device arrays of the density drawing next
        self.unguided = PixelMoments()      # the pixels' samples drawn without a density
        self.images: list[tuple] = []       # (spp, image) of every iteration
        self.moments: list[PixelMoments] = []
        self.log: list[dict] = []

    def schedule(self) -> list[int]:
        """spp of the training iterations: a share of the budget that grows
        with it (:func:`budget_passes`), or the share asked for."""
        it = self.integrator
        if it.train_fraction is None:
            return budget_passes(self.spp, it.train_passes)
        return training_passes(self.spp, it.train_fraction, it.train_passes)

    @property
    def trained_spp(self) -> int:
        return sum(n for n, _ in self.images)

    # ------------------------------ Iterations --------------------------------

    def iterate(self, spp: int) -> bool:
        """Draw an iteration of ``spp`` with the current density, recording
        (at most :data:`ITERATION_RECORDS` vertices, in launches of at most
        MAX_RECORDS); its records join the tally unless the density that
        drew it did not pay on its own paths. Returns whether it paid."""
        it, i = self.integrator, len(self.log)
        moments = self.unguided if self.guide is None else PixelMoments()
        lanes = self.lanes_per_spp()
        per = max(1, MAX_RECORDS // (lanes * self.depth))      # spp per recorded launch
        recorded = min(spp, max(1, ITERATION_RECORDS // (lanes * self.depth)))
        sizes = [min(per, recorded - k) for k in range(0, recorded, per)]
        records, launches = [], []
        for k, n in enumerate(sizes + ([spp - recorded] if spp > recorded else [])):
            rec = Records(lanes * n, self.depth if k < len(sizes) else 0, n, self.grid, self.far)
            seed = pass_seed(pass_seed(self.seed, i), 1000 + k)
            part = it.launch(self.scene, self.sensor, seed, n, True, True, self.guide, rec)
            moments.add(rec.pixel_moments())
            launches.append((n, part))
            if rec.depth:
                records.append(rec.learned(it.directional_res, it.parallax))
        measured, means = float("nan"), float("nan")
        if moments is not self.unguided and spp * lanes >= MEASURED_FROM:
            # (the density that drew this iteration did not pay on its own
            # paths, and they found no light the unguided ones missed: the
            # Cornell box at 128² × 24-96 spp measured 0.84-1.02 and guided
            # at 0.6-0.8× path's efficiency; NaN, which pays, in scalar
            # variants)
            measured, means = measured_ratios(self.unguided, moments)
        paid = not (measured > it.max_variance_ratio and means <= UNSEEN_ABOVE)
        if paid:
            for r in records:
                self.tally.add(*r)
        self.images.append((spp, _mean(launches)))
        self.moments.append(moments)
        self.log.append({"spp": spp, "records": self.tally.records, "leaves": None,
                         "trained_leaves": None, "bsdf_share": None, "variance_ratio": None,
                         "measured_ratio": measured})
        return paid

    def learn(self) -> bool:
        """Rebuild the spatial tree and its leaves' densities from every
        record so far; the next iteration draws with them unless they are
        predicted to leave more than ``max_variance_ratio`` of BSDF
        sampling's variance (a guide that cuts little of the variance costs
        more than it buys: sky_sphere and probe_spheres predict 0.86-0.98
        and rendered 1.3-2.4× path's time for no lower error). Returns
        whether to train on: False where nothing arrives indirectly, or
        where a density learned from at least :data:`JUDGED_FROM` records
        does not pay; the rest then renders as mis."""
        it = self.integrator
        guide = Guide.learn(self.tally, it.spatial_threshold, it.directional_threshold)
        ratio = guide.variance_ratio(it.bsdf_fraction)
        self.log[-1].update(leaves=guide.leaves, trained_leaves=guide.trained_leaves,
                            bsdf_share=guide.bsdf_share(it.bsdf_fraction),
                            variance_ratio=ratio)
        if not guide.trained_leaves or not ratio <= it.max_variance_ratio:
            self.guide = None
            return bool(guide.trained_leaves) and self.tally.records < JUDGED_FROM
        self.guide = guide.device(it.bsdf_fraction)
        return True

    def stop(self) -> None:
        """Draw no more with a learned density (one did not pay)."""
        self.guide = None

    # ------------------------------ The result --------------------------------

    def render_rest(self, develop: bool, evaluate: bool):
        """The rest of the budget, with the last density (its pixels'
        moments recorded where it joins the training images)."""
        it = self.integrator
        rest = self.spp - self.trained_spp
        combine = develop and it.combine_passes and self.images
        rec = Records(self.lanes_per_spp() * rest, 0, rest) if combine else None
        image = it.launch(self.scene, self.sensor, self.seed, rest, develop, evaluate,
                          self.guide, rec)
        if not combine:
            return image                    # (an undeveloped film holds the last pass)
        moments = PixelMoments()
        moments.add(rec.pixel_moments())
        return self.combine((rest, image), moments)

    def combine(self, last, moments):
        """Every iteration's image and ``last`` (spp, image), weighted by
        inverse variance (:func:`moments.inverse_variance_weights`): unbiased,
        as each is, but for the little a whole image's weight depends on its
        own samples."""
        parts = [*self.images, last]
        spp = [n for n, _ in parts]
        lanes = self.lanes_per_spp()
        weights = inverse_variance_weights(spp, relative_variances([*self.moments, moments]),
                                           [lanes * n for n in spp])
        for entry, w in zip(self.log, weights):
            entry["weight"] = w
        # (the weights opaque: as literals, every new spp compiled a kernel,
        # and a timed render that compiles is rendered again)
        total = None
        for (_, image), w in zip(parts, weights):
            part = image * dr.opaque(mi.Float, w)
            total = part if total is None else total + part
        return total

    def lanes_per_spp(self) -> int:
        """Lanes of one sample per pixel (the film's crop and its filter's
        border)."""
        from ..core import passes
        sensor = self.scene.sensors()[self.sensor] if isinstance(self.sensor, int) \
            else self.sensor
        return passes.film_lanes(sensor.film())


def _mean(launches: list[tuple]):
    """The spp-weighted mean of (spp, image) launches of one density."""
    if len(launches) == 1:
        return launches[0][1]
    total = sum(n for n, _ in launches)
    out = None
    for n, image in launches:
        part = image * dr.opaque(mi.Float, n / total)
        out = part if out is None else out + part
    return out
