"""What `guided_path`'s training paths leave (:class:`Records`: per vertex
where it was, where its continuation went and the light it found; per pixel
the moments of its samples), and their sums per voxel and cell
(:class:`Tally`), which the spatial tree and its leaves' directional
structure are rebuilt from at every training iteration. Nothing here
depends on the variant: Mitsuba's types are looked up when called."""

from __future__ import annotations

import itertools

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy import sparse

from .spatial import GRID, anchor_of_voxel, guide_frame, on_plane, voxel_of
from .tables import square_cell

TRAIN_DEPTH = 8            # vertices of a training path that are recorded
MAX_RECORDS = 1 << 22      # vertex records per launch (longer iterations split)


def channel_mean(x):
    """The mean of ``x``'s channels. (dr.mean of a JIT array of three
    channels traces its lanes' count as a literal: in a render's kernel,
    every new spp compiled it anew.)"""
    return sum(x[i] for i in range(len(x))) * (1.0 / len(x))


class Records:
    """What the paths of one launch leave: with ``depth`` > 0, per vertex
    its voxel, the point its continuation hit (far along it where it
    escaped), the normal of its guide frame, the throughput after it, the
    radiance gathered before its continuation and after the emission the
    continuation hit; always, per path its radiance, whose moments per pixel
    :meth:`pixel_moments` sums (radiance and throughput as their mean over
    the channels: only learning and the passes' weights read them). Device
    buffers in JIT variants, dicts in scalar ones. A JIT wavefront holds
    each pixel's ``spp`` samples side by side (Mitsuba's sampling
    integrator: lane // spp is the pixel)."""

    def __init__(self, lanes: int, depth: int, spp: int, grid=None, far: float = 0.0):
        self.lanes, self.depth, self.spp, self.grid, self.far = lanes, depth, spp, grid, far
        self.pixels = lanes // spp
        if dr.is_jit_v(mi.Float):
            n = lanes * depth
            self.path = dr.zeros(mi.Float, lanes)           # each path's radiance
            if depth:
                self.voxel = dr.zeros(mi.UInt32, n)         # voxel + 1; 0: none
                self.beta, self.L = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
                self.hit = dr.zeros(mi.Float, n)
                self.x = [dr.zeros(mi.Float, n) for _ in range(3)]    # the vertex
                self.y = [dr.zeros(mi.Float, n) for _ in range(3)]    # the point hit
                self.g = [dr.zeros(mi.Float, n) for _ in range(3)]    # the frame's normal
        else:
            self.rows, self.path_L, self.lanes_taken = {}, {}, itertools.count()

    @property
    def fields(self) -> tuple:
        """The device arrays a launch scatters into, in order."""
        vertices = ("voxel", "beta", "L", "hit", "x", "y", "g") if self.depth else ()
        return ("path", *vertices)

    def arrays(self) -> tuple:
        """The device arrays of :attr:`fields` (JIT variants), flat."""
        out = []
        for f in self.fields:
            a = getattr(self, f)
            out += a if isinstance(a, list) else [a]
        return tuple(out)

    def hold(self, arrays) -> None:
        """Make ``arrays`` (as :meth:`arrays` returns them) these records'."""
        arrays = list(arrays)
        for f in self.fields:
            if isinstance(getattr(self, f), list):
                setattr(self, f, arrays[:3])
                del arrays[:3]
            else:
                setattr(self, f, arrays.pop(0))

    # ------------------------- In the kernel -------------------------------

    def lane(self, ray):
        """Which path this lane traces."""
        if dr.is_jit_v(mi.Float):
            return dr.arange(mi.UInt32, dr.width(ray))
        return next(self.lanes_taken)   # (scalar: one path per call)

    def vertex(self, lane, depth, si, wo_world, pdf, delta, β, L, active) -> None:
        """Record the vertex ``si`` whose continuation is ``wo_world``."""
        if not self.depth:
            return
        # one to the other side of the guide frame is not learned
        g = guide_frame(si).n
        voxel = voxel_of(si.p, self.grid)
        # (until the continuation hits something: far along it)
        far = si.p + wo_world * self.far
        # (no `~` on masks: in scalar variants they are Python bools)
        keep = dr.select(delta, False, active & (depth < self.depth) & (pdf > 0)
                         & (dr.dot(g, wo_world) > 0))
        if not dr.is_jit_v(mi.Float):
            if keep:
                L_ = channel_mean(L)
                self.rows[(lane, depth)] = [voxel, channel_mean(β), L_, L_, mi.Point3f(si.p),
                                            mi.Point3f(far), mi.Vector3f(g)]
            return
        i = lane * self.depth + depth
        dr.scatter(self.voxel, voxel + 1, i, keep)
        dr.scatter(self.beta, channel_mean(β), i, keep)
        dr.scatter(self.L, channel_mean(L), i, keep)
        dr.scatter(self.hit, channel_mean(L), i, keep)       # (until an emission is hit)
        for k in range(3):
            dr.scatter(self.x[k], si.p[k], i, keep)
            dr.scatter(self.y[k], far[k], i, keep)
            dr.scatter(self.g[k], g[k], i, keep)

    def emission(self, lane, depth, si, L, active) -> None:
        """Record what the continuation of the vertex before ``si`` hit."""
        # Emission the continuation hit is direct light, which next-event
        # estimation samples too (exactly, under an importance-sampled map):
        # the density learns what arrives indirectly, so that q does not take
        # the emitter sample's MIS weight where it samples best; the direct
        # part sets the BSDF's share of the mixture (guide.mixture_share).
        # Where the continuation hit a surface, that point is where the
        # vertex's light came from (parallax).
        if not self.depth:
            return
        if not dr.is_jit_v(mi.Float):
            row = self.rows.get((lane, depth - 1)) if depth >= 1 else None
            if active and row is not None:
                row[3] = channel_mean(L)
                if si.is_valid():
                    row[5] = mi.Point3f(si.p)
            return
        i = lane * self.depth + depth - 1
        here = active & (depth >= 1) & (depth <= self.depth)
        dr.scatter(self.hit, channel_mean(L), i, here)
        for k in range(3):
            dr.scatter(self.y[k], si.p[k], i, here & si.is_valid())

    def path_radiance(self, lane, L) -> None:
        """Record the path's radiance ``L``."""
        if not dr.is_jit_v(mi.Float):
            if self.depth:
                self.path_L[lane] = channel_mean(L)
            return
        dr.scatter(self.path, channel_mean(L), lane)

    # ------------------------- After the launch ----------------------------

    def pixel_moments(self):
        """[(Σ L, Σ L², samples)] per pixel, of its even and of its odd
        samples, as :class:`.moments.PixelMoments` adds them; None in scalar
        variants, which trace a pixel's samples in no fixed order."""
        if not dr.is_jit_v(mi.Float):
            return None
        n = self.spp
        # (summed on the device, after the launch, a pixel's lanes block by
        # block in a fixed order: numpy's sums along rows of a few samples
        # took 30 ms a pass at 256² beside Dr.Jit's threads; summed in the
        # render's kernel, every new spp compiled that kernel; summed by
        # atomic adds, their order varied, the images' weights with it, and
        # a render was not its own replay bit for bit)
        lane = dr.arange(mi.UInt32, self.lanes)
        odd = lane % dr.opaque(mi.UInt32, n) % 2 == 1
        sums = []
        for x in (self.path, dr.square(self.path)):
            whole = dr.block_reduce(dr.ReduceOp.Add, x, n, mode="evaluated")
            odds = dr.block_reduce(dr.ReduceOp.Add, dr.select(odd, x, 0.0), n,
                                   mode="evaluated")
            sums.append((np.array(whole - odds, np.float64), np.array(odds, np.float64)))
        (first_even, first_odd), (second_even, second_odd) = sums
        first = np.stack([first_even, first_odd], axis=1)
        second = np.stack([second_even, second_odd], axis=1)
        return [(first[:, h], second[:, h], (n + 1 - h) // 2) for h in (0, 1)]

    def learned(self, res: int, parallax: bool = True):
        """(voxel, cell, L_i, L_d, distance) as numpy, one row per vertex whose
        path went on (β > 0: where f = 0 the path died and L_i is unknown),
        each over the throughput after the vertex (which includes f cos/p).
        The cell is that of the direction from the vertex's anchor
        (:func:`anchor_of`) to the point its continuation hit, in its guide
        frame; a vertex whose hit point lies below that frame's horizon seen
        from the anchor is left out. The distance is the anchor's to that
        point. L_i is the radiance the path gathered after the emission its
        continuation hit: the light that arrives indirectly. L_d is that
        emission, MIS-weighted as the path added it: the continuation's share
        of the direct light."""
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
                np.zeros(0))
        if not self.depth:
            return none
        if not dr.is_jit_v(mi.Float):
            return self._learned_scalar(res, parallax, none)
        # (on the device: only the rows kept cross to the host)
        i = dr.compress(self.voxel > 0)
        if dr.width(i) == 0:                  # (e.g. only delta lobes were hit)
            return none
        beta, hit = dr.gather(mi.Float, self.beta, i), dr.gather(mi.Float, self.hit, i)
        li = dr.maximum(dr.gather(mi.Float, self.path, i // self.depth) - hit, 0) / beta
        ld = dr.maximum(hit - dr.gather(mi.Float, self.L, i), 0) / beta
        voxel = dr.gather(mi.UInt32, self.voxel, i) - 1
        x, y = (mi.Point3f(*[dr.gather(mi.Float, a, i) for a in b]) for b in (self.x, self.y))
        g = mi.Vector3f(*[dr.gather(mi.Float, a, i) for a in self.g])
        cell, dist, above = anchored_cell(voxel, x, y, g, self.grid, res, parallax)
        alive = dr.compress((beta > 0) & dr.isfinite(li) & dr.isfinite(ld) & above)
        out = [dr.gather(type(a), a, alive) for a in (voxel, cell, li, ld, dist)]
        dr.eval(out)                           # (one launch for the five)
        voxel, cell, li, ld, dist = (np.array(a) for a in out)
        return voxel.astype(np.int64), cell.astype(np.int64), li, ld, dist

    def _learned_scalar(self, res, parallax, none):
        if not self.rows:
            return none
        lane = np.array([k[0] for k in self.rows])
        voxel, beta, L, hit, x, y, g = zip(*self.rows.values())
        voxel, beta, L, hit = (np.array(c) for c in (voxel, beta, L, hit))
        path = np.array([self.path_L[int(x)] for x in lane])
        found = [anchored_cell(v, a, b, n, self.grid, res, parallax)
                 for v, a, b, n in zip(voxel, x, y, g)]
        cell, dist, above = (np.array(c) for c in zip(*found))
        with np.errstate(divide="ignore", invalid="ignore"):
            li, ld = np.maximum(path - hit, 0) / beta, np.maximum(hit - L, 0) / beta
        alive = (beta > 0) & np.isfinite(li) & np.isfinite(ld) & above.astype(bool)
        return (voxel[alive].astype(np.int64), cell[alive].astype(np.int64), li[alive],
                ld[alive], dist[alive].astype(float))


def anchored_cell(voxel, x, y, g, grid, res: int, parallax: bool = True):
    """(cell, distance, above) of the direction from the anchor of vertex
    ``x`` (its voxel's, on its plane) to the point ``y``, in the guide frame
    of normal ``g``: its cell of the res² square (:func:`square_cell`), the
    anchor's distance to ``y``, and whether it lies above the frame's
    horizon. Without ``parallax`` the anchor is ``x`` itself."""
    d = y - (on_plane(anchor_of_voxel(voxel, grid), x, g) if parallax else x)
    dist = dr.norm(d)
    w = mi.Frame3f(g).to_local(d / dr.maximum(dist, 1e-30))
    return square_cell(mi.warp.cosine_hemisphere_to_square(w), res), dist, w.z > 0


class Tally:
    """A render's training records, as :meth:`.guide.Guide.learn` reads them: per
    voxel the records' count (which grows the tree) and Σ L_i / distance
    (with Σ L_i, their light's distance) and, per node of a tree and cell of
    the res² square, their count, Σ L_i and Σ L_i², and per node Σ L_d
    (:meth:`node_sums`). Its tree never splits a voxel, and a record's cell
    is taken from its voxel's anchor, whatever the tree, so records summed
    per voxel and cell serve any tree: the records are kept
    as they come while they are fewer than the voxels' cells, and folded
    into such sums once they outnumber them, so that a long training's
    memory stays bounded (24 bytes per cell of a voxel a record fell in,
    24 KiB a voxel at res 32; 32 bytes per record kept). Pooling the
    records into one array and reading them all again at every pass made
    the learning stage's longest training (the Cornell box at 16², 14 M
    records) twice as slow; summing every few records into every cell of
    every voxel made small renders 5× slower
    (docs/measurements.md#2026-12-06-guided-path-learns-sums-records)."""

    def __init__(self, res: int):
        self.res = res
        self.records = 0
        self.voxel_counts = np.zeros(GRID ** 3)        # records per voxel
        # per voxel Σ L_i / distance: with Σ L_i, the distance of its light
        self.voxel_near = np.zeros(GRID ** 3)
        self._kept = []                                # (voxel, cell, L_i, L_d) not yet folded
        self._kept_records = 0
        # the folded sums: per row (a voxel) and cell (count, Σ L_i, Σ L_i²),
        # per row Σ L_d; rows to spare, grown by doubling
        self._row = np.full(GRID ** 3, -1, np.int64)   # each voxel's row; -1: none yet
        self._voxels = np.zeros(0, np.int64)           # the voxel of each row
        self._sums = np.zeros((3, 0, res * res))
        self._direct = np.zeros(0)

    def add(self, voxel, cell, li, ld, distance=None) -> None:
        """Add records (:meth:`Records.learned`): per record its voxel, its
        direction's cell, L_i, L_d and the distance of its light from the
        voxel's anchor (None: far)."""
        if not len(voxel):
            return
        self.voxel_counts += np.bincount(voxel, minlength=GRID ** 3)
        if distance is not None:
            self.voxel_near += np.bincount(voxel, weights=li / np.maximum(distance, 1e-30),
                                           minlength=GRID ** 3)
        self.records += len(voxel)
        self._kept.append((voxel, cell, li, ld))
        self._kept_records += len(voxel)
        if self._kept_records > np.count_nonzero(self.voxel_counts) * self.res ** 2:
            self._fold()

    def node_sums(self, node_of_voxel: np.ndarray, nodes: int):
        """(count, Σ L_i, Σ L_i²) per node and cell (nodes, res²) and Σ L_d
        per node, of the records in the voxels each node's entry of
        ``node_of_voxel`` (GRID³) names."""
        nb = self.res * self.res
        out = [np.zeros((nodes, nb)) for _ in range(3)]
        direct = np.zeros(nodes)
        rows = len(self._voxels)
        if rows:        # (a voxel's rows summed into its node's: a sparse sum)
            node = node_of_voxel[self._voxels]
            into = sparse.csr_matrix((np.ones(rows), (node, np.arange(rows))),
                                     shape=(nodes, rows))
            for a, s in zip(out, self._sums[:, :rows]):
                a += into @ s
            direct += np.bincount(node, weights=self._direct[:rows], minlength=nodes)
        for voxel, cell, li, ld in self._kept:
            _sum_by(out, direct, node_of_voxel[voxel], cell, li, ld)
        return (*out, direct)

    def _fold(self) -> None:
        """Sum the kept records into the per-voxel rows."""
        seen = np.flatnonzero(self.voxel_counts)
        new = seen[self._row[seen] < 0]
        if len(new):
            self._row[new] = len(self._voxels) + np.arange(len(new))
            self._voxels = np.concatenate([self._voxels, new])
            if len(self._voxels) > self._sums.shape[1]:
                rows = max(len(self._voxels), 2 * self._sums.shape[1])
                grown = np.zeros((3, rows, self._sums.shape[2]))
                grown[:, :self._sums.shape[1]] = self._sums
                direct = np.zeros(rows)
                direct[:len(self._direct)] = self._direct
                self._sums, self._direct = grown, direct
        rows = len(self._voxels)
        for voxel, cell, li, ld in self._kept:
            _sum_by(self._sums[:, :rows], self._direct[:rows], self._row[voxel], cell, li, ld)
        self._kept, self._kept_records = [], 0


def _sum_by(sums, direct, index, cell, li, ld) -> None:
    """Add records to ``sums`` (count, Σ L_i, Σ L_i²), each (n, res²), at
    row ``index`` and column ``cell`` of each record, and their L_d to
    ``direct`` (n,) at ``index``."""
    n, nb = sums[0].shape
    key = index * nb + cell
    for a, w in zip(sums, (None, li, li * li)):
        a += np.bincount(key, weights=w, minlength=n * nb).reshape(n, nb)
    direct += np.bincount(index, weights=ld, minlength=n)
