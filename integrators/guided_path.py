"""Path guiding: a path tracer (as `mis`) whose continuation direction comes
from a one-sample mixture of the BSDF and a directional distribution learned
from the renderer's own paths while it renders (after Müller et al. 2017,
"Practical Path Guiding for Efficient Light-Transport Simulation")."""

from __future__ import annotations

import hashlib
import itertools
from collections import deque

import drjit as dr
import mitsuba as mi
import numpy as np

from . import registry
from .bsdf_sampling import sample_bsdf_direction
from .emitter_sampling import emitter_direction_pdf, sample_emitter_direction
from .estimator import IlluminationEstimator, over_pdf

# ----------------------------- Strategy ---------------------------------
# The learned part is a piecewise-constant density on the unit square, warped
# to the hemisphere by the cosine warp (Shirley-Chiu's concentric map, as
# mi.warp.square_to_cosine_hemisphere) in a frame built from the shading
# normal alone, on the side the path arrived from: a uniform pmf is cosine
# sampling, and a pmf ∝ the mean L_i over each of the res² cells makes
# p ∝ L_i cos θ (the product a diffuse vertex wants). Directions on the
# other side get density 0: the BSDF's share covers them.
#     p(ω) = pmf[cell(ω)] · res² · cos θ / π


def guide_frame(si) -> tuple:
    """(frame of the shading normal, side): the frame depends on the normal
    only (Frame3f's coordinate system), so every surface of one orientation
    in a cell shares it; side ±1 is the hemisphere of ``si.wi``."""
    n = si.sh_frame.n
    return mi.Frame3f(n), dr.select(si.wi.z >= 0, 1.0, -1.0)


def to_guide(si, w_world: mi.Vector3f) -> mi.Vector3f:
    """World direction → the guide's frame at ``si``, mirrored so that the
    side the path arrived from is z > 0."""
    frame, side = guide_frame(si)
    w = frame.to_local(w_world)
    return mi.Vector3f(w.x, w.y, w.z * side)


def from_guide(si, w: mi.Vector3f) -> mi.Vector3f:
    """The inverse of :func:`to_guide`."""
    frame, side = guide_frame(si)
    return frame.to_world(mi.Vector3f(w.x, w.y, w.z * side))


def square_cell(u: mi.Point2f, res: int) -> mi.UInt32:
    """Cell of square point ``u`` (row-major)."""
    ix = dr.minimum(mi.UInt32(dr.maximum(u.x * res, 0)), res - 1)
    iy = dr.minimum(mi.UInt32(dr.maximum(u.y * res, 0)), res - 1)
    return iy * res + ix


def sample_guide(slot, row, res: int, u1: mi.Float, u2: mi.Point2f):
    """(ω in the guide frame, upper side; cell): the cell of slot ⌊u1·S⌋ of
    pmf ``row``'s S = SLOTS_PER_CELL·res² equal-probability slots (one
    gather: each cell owns as many slots as its quantized pmf, see
    :func:`guide_tables`); ``u2`` uniform in the cell, then the cosine warp."""
    slots = SLOTS_PER_CELL * res * res
    k = dr.minimum(mi.UInt32(u1 * slots), slots - 1)
    c = _take(slot, row * slots + k)
    u = mi.Point2f((mi.Float(c % res) + u2.x) / res, (mi.Float(c // res) + u2.y) / res)
    return mi.warp.square_to_cosine_hemisphere(u), c


def guide_pdf(pmf, row, res: int, w: mi.Vector3f) -> mi.Float:
    """Solid-angle density of :func:`sample_guide` at ``w`` (guide frame,
    upper side; 0 below): pmf · res² · cos θ / π."""
    cell = square_cell(mi.warp.cosine_hemisphere_to_square(w), res)
    return dr.select(w.z > 0, _take(pmf, row * (res * res) + cell) * (res * res) * w.z
                     * dr.inv_pi, 0.0)


def invert_guide(first, pmf, row, res: int, w: mi.Vector3f):
    """(u1, u2) that :func:`sample_guide` maps to ``w`` (u1 the middle of its
    cell's slots)."""
    u = mi.warp.cosine_hemisphere_to_square(w)
    c = square_cell(u, res)
    i = row * (res * res) + c
    slots = SLOTS_PER_CELL * res * res
    u1 = (mi.Float(_take(first, i)) + 0.5 * _take(pmf, i) * slots) / slots
    return u1, mi.Point2f(u.x * res - mi.Float(c % res), u.y * res - mi.Float(c // res))


SLOTS_PER_CELL = 8         # equal-probability slots per cell of a learned pmf


def quantize(pmf: np.ndarray, slots: int) -> np.ndarray:
    """Slots per cell for each row of ``pmf``: ``slots`` per row, every
    cell at least one, the rest in proportion to ``pmf`` (largest
    remainders first)."""
    rows, n = pmf.shape
    share = pmf / pmf.sum(axis=1, keepdims=True) * (slots - n)
    counts = 1 + np.floor(share).astype(np.int64)
    left = slots - counts.sum(axis=1)                 # (in [0, n))
    order = np.argsort(np.floor(share) - share, axis=1, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.broadcast_to(np.arange(n), (rows, n)), axis=1)
    return counts + (rank < left[:, None])


def guide_tables(pmf: np.ndarray) -> dict:
    """The arrays :func:`sample_guide`, :func:`guide_pdf` and
    :func:`invert_guide` read, from pmfs (rows, res²): ``pmf`` quantized to
    multiples of 1/S (the density sampled, so the one weighed: the image
    stays unbiased; with 8 slots per cell a floor cell gets at least 1/8 of
    a uniform cell's share), ``slot`` the cell of each of a row's S slots,
    ``first`` each cell's first slot. Sampling then costs one gather where
    a bisection of the cdf cost log2(res²) (10 at 32²)."""
    rows, n = pmf.shape
    slots = SLOTS_PER_CELL * n
    counts = quantize(pmf, slots)
    first = np.cumsum(counts, axis=1) - counts
    cells = np.repeat(np.tile(np.arange(n, dtype=np.uint32), rows), counts.ravel())
    return {"pmf": (counts / slots).astype(np.float32).ravel(), "slot": cells,
            "first": first.astype(np.uint32).ravel()}


def _take(array, index):
    """``array[index]``: a gather in JIT variants, an element in scalar ones."""
    if dr.is_jit_v(mi.Float):
        return dr.gather(type(array), array, index)
    return array[int(index)].item()


# ----------------------------- Learning -----------------------------------
# Where: a voxel of a GRID³ grid over the scene's bounds. The learned tree
# splits voxels' blocks; flattened into a voxel → leaf table for sampling, a
# vertex finds its leaf with one lookup.

GRID = 32


def grid_of(bbox) -> tuple:
    """(lower corner, voxels per unit length) of the grid over ``bbox``."""
    lo, hi = np.array(bbox.min, float), np.array(bbox.max, float)
    pad = 1e-3 * max(float(np.max(hi - lo)), 1e-6)
    lo, hi = lo - pad, hi + pad
    return lo, GRID / np.maximum(hi - lo, 1e-9)


def voxel_of(p: mi.Point3f, grid) -> mi.UInt32:
    """Voxel index of ``p`` (x fastest)."""
    lo, scale = grid
    i = [dr.minimum(mi.UInt32(dr.maximum((p[k] - float(lo[k])) * float(scale[k]), 0)),
                    GRID - 1) for k in range(3)]
    return i[0] + GRID * (i[1] + GRID * i[2])


TRAIN_DEPTH = 8            # vertices of a training path that are recorded
PASSES = 2                 # training passes at most, by default (each traces the kernel)
MAX_RECORDS = 1 << 22      # records per training render (longer passes split)
FLOOR = 0.1                # uniform share of every learned pmf
MIN_TRAINED = 128          # records a node needs to learn its own pmf
MIN_SPLIT = 128            # records a directional cell needs to be refined
SHRINK = 64                # records' worth a refined cell's mean is pulled to its parent's
MAX_TREE_DEPTH = 3 * 5    # (a leaf of one voxel: GRID = 2^5)


def training_passes(spp: int, fraction: float, passes: int = PASSES) -> list[int]:
    """spp of the training passes: ``fraction`` of ``spp`` (leaving at least
    one sample for the image) in at most ``passes`` passes that double, the
    first at least 1 spp: every pass costs a trace of the whole kernel."""
    budget = max(int(min(fraction * spp, spp - 1)), 0)
    k = min(passes, (budget + 1).bit_length() - 1)   # 2^k - 1 ≤ budget
    if k == 0:
        return []
    unit = budget // (2 ** k - 1)
    out = [unit * 2 ** i for i in range(k)]
    out[-1] += budget - sum(out)
    return out


def pass_seed(seed: int, i: int) -> int:
    """Seed of training render ``i`` of the render with ``seed``: hashed, so
    that no other render's seed gives the same samples."""
    digest = hashlib.blake2s(f"guided_path {int(seed)} {i}".encode(), digest_size=4)
    return int.from_bytes(digest.digest(), "little")


class Guide:
    """A binary tree over the scene's bounds, each node split at the middle
    of its longest side while it holds more than ``threshold``·√R of the R
    records, with a learned pmf over the square's res² cells in every node;
    numpy arrays (children of a node consecutive), and the same on the
    device for sampling (:meth:`device`)."""

    def __init__(self, res: int):
        self.res = res
        self.axis = np.zeros(1, np.uint32)
        self.split = np.zeros(1, np.float32)
        self.child = np.zeros(1, np.uint32)      # first child; 0: a leaf
        self.pmf = np.full((1, res * res), 1.0 / (res * res))
        self.trained = np.zeros(1, bool)
        self.indirect = np.zeros(1)              # share of the light arriving indirectly

    @property
    def leaves(self) -> int:
        return int(np.sum(self.child == 0))

    @property
    def trained_leaves(self) -> int:
        return int(np.sum(self.trained & (self.child == 0)))

    @classmethod
    def learn(cls, res: int, voxel, cell, li, ld, threshold: float, refine: float) -> Guide:
        """The tree and pmfs of the records (:meth:`Records.learned`): per
        record its voxel, its direction's cell of the res² square, the
        radiance ``li`` it saw arrive indirectly and the emission ``ld`` its
        direction hit, MIS-weighted.

        The tree splits the grid breadth first (in voxel units) while a
        node holds more than ``threshold``·√R of the R records (so that, as
        in Müller et al., leaves and the records per leaf both grow as √R:
        more records buy spatial and directional resolution alike); a split
        never divides a voxel. A node with at least MIN_TRAINED records
        learns its pmf from them (:func:`refined_means`: per cell the mean
        L_i of a quadtree cell that is refined where light concentrates);
        one with fewer keeps its parent's (uniform at the root: cosine
        sampling, not trained).
        Every cell spans the same cosine-weighted solid angle, so a cell's
        mean L_i is its share of ∫ L_i cos θ, up to its within-cell
        variation, and far less noisy than splatting L_i/p, which one rare
        record of small p dominates. A node also keeps the share of its
        records' light that arrived indirectly, Σ li / Σ (li + ld): the
        part of the continuation's integrand the learned density models
        (the rest is the BSDF sample's share of the direct light, which it
        samples well).

        The image is unbiased whatever is learned."""
        g = cls(res)
        if not np.any(li > 0):          # (no light arrived: no node would learn)
            return g
        nb = res * res
        g._grow(np.bincount(voxel, minlength=GRID ** 3), threshold * np.sqrt(len(voxel)))
        nodes = len(g.child)
        node = g.locate(_voxel_centres(np.arange(GRID ** 3)))[voxel]
        key = node * nb + cell
        hits = np.bincount(key, minlength=nodes * nb).reshape(nodes, nb).astype(float)
        total = np.bincount(key, weights=li, minlength=nodes * nb).reshape(nodes, nb)
        direct = np.bincount(node, weights=ld, minlength=nodes)
        for k in reversed(range(nodes)):     # (an inner node's sums are its children's)
            first = int(g.child[k])
            if first:
                hits[k] = hits[first] + hits[first + 1]
                total[k] = total[first] + total[first + 1]
                direct[k] = direct[first] + direct[first + 1]
        own = (hits.sum(axis=1) >= MIN_TRAINED) & (total.sum(axis=1) > 0)
        means = refined_means(hits, total, res, refine)
        pmf = (1 - FLOOR) * means / np.maximum(means.sum(axis=1, keepdims=True), 1e-30) \
            + FLOOR / nb
        indirect = total.sum(axis=1) / np.maximum(total.sum(axis=1) + direct, 1e-30)
        g.pmf, g.trained, g.indirect = np.repeat(g.pmf, nodes, axis=0), np.zeros(nodes, bool), \
            np.zeros(nodes)
        parent = g.parents()
        for k in range(nodes):               # (breadth first: a parent before its children)
            if own[k]:
                g.pmf[k], g.trained[k], g.indirect[k] = pmf[k], True, indirect[k]
            elif k:
                g.pmf[k], g.trained[k], g.indirect[k] = (g.pmf[parent[k]], g.trained[parent[k]],
                                                         g.indirect[parent[k]])
        return g

    def _grow(self, counts, threshold: float):
        """Split the root breadth first by the records per voxel ``counts``."""
        occupied = np.flatnonzero(counts)
        p, c = _voxel_centres(occupied), counts[occupied]
        axis, split, child = [0], [0.0], [0]
        queue = deque([(0, np.arange(len(occupied)), np.zeros(3), np.full(3, float(GRID)), 0)])
        while queue:
            node, idx, lo, hi, depth = queue.popleft()
            if c[idx].sum() <= threshold or depth >= MAX_TREE_DEPTH or np.max(hi - lo) <= 1:
                continue
            a = int(np.argmax(hi - lo))
            mid = 0.5 * (lo[a] + hi[a])
            first = len(child)
            axis[node], split[node], child[node] = a, mid, first
            upper = p[idx, a] >= mid
            hi1, lo2 = hi.copy(), lo.copy()
            hi1[a] = lo2[a] = mid
            for k, (part, low, high) in enumerate(((idx[~upper], lo, hi1), (idx[upper], lo2, hi))):
                axis.append(0), split.append(0.0), child.append(0)
                queue.append((first + k, part, low, high, depth + 1))
        self.axis, self.split = np.array(axis, np.uint32), np.array(split, np.float32)
        self.child = np.array(child, np.uint32)

    def parents(self) -> np.ndarray:
        """Parent of every node (-1 for the root)."""
        parent = np.full(len(self.child), -1, np.int64)
        inner = np.flatnonzero(self.child)
        parent[self.child[inner]] = inner
        parent[self.child[inner] + 1] = inner
        return parent

    def bsdf_share(self, bsdf_fraction: float) -> float:
        """Mean BSDF share α over the trained leaves (1 if none learned)."""
        leaves = self.trained & (self.child == 0)
        if not leaves.any():
            return 1.0
        return float(np.mean(mixture_share(bsdf_fraction, self.indirect[leaves])))

    def locate(self, p: np.ndarray) -> np.ndarray:
        """Leaf of every point of ``p`` (n, 3; voxel units)."""
        node = np.zeros(len(p), np.int64)
        while True:
            inner = self.child[node] != 0
            if not inner.any():
                return node
            x = p[np.arange(len(p)), self.axis[node]]
            node = np.where(inner, self.child[node] + (x >= self.split[node]), node)

    def device(self, bsdf_fraction: float) -> dict:
        """The arrays :meth:`GuidedPathIntegrator.sample` reads, as the
        variant's types (numpy in scalar variants): the leaves' quantized
        pmfs and slot tables (:func:`guide_tables`), their BSDF shares, and
        the leaf of every voxel."""
        leaves = np.flatnonzero(self.child == 0)
        row = np.zeros(len(self.child), np.int64)
        row[leaves] = np.arange(len(leaves))
        alpha = np.where(self.trained[leaves], mixture_share(bsdf_fraction, self.indirect[leaves]),
                         1.0).astype(np.float32)
        leaf = row[self.locate(_voxel_centres(np.arange(GRID ** 3)))].astype(np.uint32)
        arrays = {"leaf": leaf, "alpha": alpha, **guide_tables(self.pmf[leaves])}
        if not dr.is_jit_v(mi.Float):
            return arrays
        return {k: (mi.UInt32 if v.dtype == np.uint32 else mi.Float)(v)
                for k, v in arrays.items()}


def mixture_share(bsdf_fraction: float, indirect):
    """The BSDF's share α of a node's one-sample mixture, from the share of
    its light that arrives indirectly: α = 1 − (1 − ``bsdf_fraction``)·share,
    ``bsdf_fraction`` where all light is indirect, 1 where none is.

    The continuation's integrand is f cos (L_ind + w L_dir): the learned
    density follows the first part only, the BSDF's sample suits the second
    (NEE takes the rest of L_dir). With ``bsdf_fraction`` everywhere, the
    variance at equal spp was 2.3× `mis`'s under sky_sphere's smooth sky
    (where light is mostly direct); with this share 1.13×, and on
    sunlit_room unchanged (docs/measurements.md, 2026-12-02)."""
    return 1.0 - (1.0 - bsdf_fraction) * np.asarray(indirect)


def _voxel_centres(voxel: np.ndarray) -> np.ndarray:
    """Centres of voxels (n, 3), in voxel units."""
    v = np.asarray(voxel, np.int64)
    return np.stack([v % GRID, (v // GRID) % GRID, v // (GRID * GRID)], axis=1) + 0.5


def refined_means(hits, total, res: int, refine: float) -> np.ndarray:
    """Per node (rows) and cell of the res² square, the mean L_i of the
    quadtree cell that holds it: from the whole square down, a quadtree
    cell is split in four while it carries more than ``refine`` of the
    node's ∫ L_i cos θ and holds at least MIN_SPLIT records (after Müller
    et al.'s directional quadtree). Where light concentrates (a sunlit
    patch seen from afar) its cells get the fine resolution; elsewhere a
    mean over many records replaces noisy small cells. A quadrant no record
    fell in keeps its parent's mean. ``hits`` and ``total`` (nodes, res²)
    are the records' counts and Σ L_i per cell."""
    n = len(hits)
    h, t = hits.reshape(n, res, res), total.reshape(n, res, res)

    def level(a, k):                         # sums over the k × k quadtree cells
        s = res // k
        return a.reshape(n, k, s, k, s).sum(axis=(2, 4))

    def children(a):                         # each cell's value on its 2 × 2 children
        return a.repeat(2, axis=1).repeat(2, axis=2)

    root = t.sum(axis=(1, 2)) / np.maximum(h.sum(axis=(1, 2)), 1)
    mean = root[:, None, None]
    refined = np.ones((n, 1, 1), bool)       # cells whose quadtree reaches this level
    k = 1
    while k < res:
        share = mean / (k * k) / np.maximum(root, 1e-30)[:, None, None]
        split = children(refined & (share > refine) & (level(h, k) >= MIN_SPLIT))
        hk, tk = level(h, 2 * k), level(t, 2 * k)
        prior = children(mean)
        own = (tk + SHRINK * prior) / (hk + SHRINK)
        mean = np.where(split, own, children(mean))
        refined, k = split, 2 * k
    return mean.reshape(n, res * res)


class Records:
    """What the training paths of one render leave: per vertex its voxel,
    its direction's cell of the guide's square, the throughput after it, the
    radiance gathered before its continuation and after the emission the
    continuation hit; per path its radiance (radiance and
    throughput as their mean over the channels: only learning reads them).
    Device buffers in JIT variants, lists in scalar ones."""

    def __init__(self, lanes: int, depth: int):
        self.lanes, self.depth = lanes, depth
        if dr.is_jit_v(mi.Float):
            n = lanes * depth
            self.voxel = dr.zeros(mi.UInt32, n)         # voxel + 1; 0: none
            self.cell = dr.zeros(mi.UInt32, n)
            self.beta, self.L = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
            self.hit = dr.zeros(mi.Float, n)
            self.path = dr.zeros(mi.Float, lanes)
        else:
            self.rows, self.path_L, self.lanes_taken = {}, {}, itertools.count()

    def learned(self):
        """(voxel, cell, L_i, L_d) as numpy, one row per vertex whose path
        went on (β > 0: where f = 0 the path died and L_i is unknown), each
        over the throughput after the vertex (which includes f cos/p). L_i is
        the radiance the path gathered after the emission its continuation
        hit: the light that arrives indirectly. L_d is that emission,
        MIS-weighted as the path added it: the continuation's share of the
        direct light."""
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
        if not dr.is_jit_v(mi.Float):
            if not self.rows:
                return none
            lane = np.array([k[0] for k in self.rows])
            voxel, cell, beta, L, hit = (np.array(c) for c in zip(*self.rows.values()))
            path = np.array([self.path_L[int(x)] for x in lane])
            with np.errstate(divide="ignore", invalid="ignore"):
                li, ld = np.maximum(path - hit, 0) / beta, np.maximum(hit - L, 0) / beta
            alive = (beta > 0) & np.isfinite(li) & np.isfinite(ld)
            return (voxel[alive].astype(np.int64), cell[alive].astype(np.int64),
                    li[alive], ld[alive])
        # (on the device: only the rows kept cross to the host)
        i = dr.compress(self.voxel > 0)
        if dr.width(i) == 0:                  # (e.g. only delta lobes were hit)
            return none
        beta, hit = dr.gather(mi.Float, self.beta, i), dr.gather(mi.Float, self.hit, i)
        li = dr.maximum(dr.gather(mi.Float, self.path, i // self.depth) - hit, 0) / beta
        ld = dr.maximum(hit - dr.gather(mi.Float, self.L, i), 0) / beta
        alive = dr.compress((beta > 0) & dr.isfinite(li) & dr.isfinite(ld))
        i = dr.gather(mi.UInt32, i, alive)
        li, ld = dr.gather(mi.Float, li, alive), dr.gather(mi.Float, ld, alive)
        voxel, cell = dr.gather(mi.UInt32, self.voxel, i), dr.gather(mi.UInt32, self.cell, i)
        dr.eval(voxel, cell, li, ld)           # (one launch for the four)
        return (np.array(voxel).astype(np.int64) - 1, np.array(cell).astype(np.int64),
                np.array(li), np.array(ld))


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
         of 1, 2, 4, … spp (in [0, 1)). (Default: 0.25)
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
    voxel (of a 32³ grid over the scene's bounds), its continuation's cell
    and L_i along it: the radiance the path gathered after it, less the
    emission the continuation hit (next-event estimation has that), over the
    throughput. From the pooled records a binary tree splits the grid while
    a node holds more than ``spatial_threshold``·√R of them; each leaf's pmf is
    its cells' mean L_i, so the density is ∝ indirect L_i cos θ, with the
    means taken over a quadtree that refines where light concentrates (cells
    above ``directional_threshold`` of the leaf's light) and stays coarse
    where records are few. Where
    nothing arrives indirectly the first pass learns nothing and training
    stops. The training passes' images are discarded: the image is the last
    render, with the remaining samples and the last density, so it is
    unbiased; its wall time includes the learning. Nested in another
    integrator (``moment``, which calls ``sample`` only) nothing is learned
    and it renders as ``mis``.

    .. tabs::

        .. code-tab:: xml

            <integrator type="guided_path">
                <integer name="max_depth" value="8"/>
                <float name="train_fraction" value="0.25"/>
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
    sample_emitter = staticmethod(sample_emitter_direction)
    emitter_pdf = staticmethod(emitter_direction_pdf)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.bsdf_fraction = float(props.get("bsdf_fraction", 0.5))
        self.train_fraction = float(props.get("train_fraction", 0.25))
        self.train_passes = props.get("train_passes", PASSES)
        self.spatial_threshold = float(props.get("spatial_threshold", 20.0))
        self.directional_res = int(props.get("directional_res", 32))
        self.directional_threshold = float(props.get("directional_threshold", 0.01))
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
        res = self.directional_res
        if res < 2 or res & (res - 1):
            raise ValueError(f"directional_res = {res} is invalid: use a power of 2 "
                             "(the cells are found by bisection), e.g. 8")
        self._guide = None                  # device arrays of the current guide
        self._records = None
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
        pixels = int(dr.prod(sensor_.film().crop_size()))
        depth = int(min(self.max_depth, TRAIN_DEPTH))
        records = []                        # (voxel, cell, L_i, L_d) of every pass so far
        try:
            for i, n in enumerate(training_passes(spp, self.train_fraction,
                                                  self.train_passes)):
                records.append(self._train(scene, sensor, pass_seed(seed, i), n, pixels, depth))
                pooled = [np.concatenate(c) for c in zip(*records)]
                guide = Guide.learn(self.directional_res, *pooled, self.spatial_threshold,
                                    self.directional_threshold)
                self.training.append({"spp": n, "records": len(pooled[0]),
                                      "leaves": guide.leaves,
                                      "trained_leaves": guide.trained_leaves,
                                      "bsdf_share": guide.bsdf_share(self.bsdf_fraction)})
                if not guide.trained_leaves:
                    break           # (nothing arrives indirectly: the rest renders as mis)
                self._guide = guide.device(self.bsdf_fraction)
            return super().render(scene, sensor, seed,
                                  spp - sum(t["spp"] for t in self.training), develop, evaluate)
        finally:
            # (a wrapper calling sample() alone later renders as mis, not
            # with this scene's guide)
            self._records, self.records_paths, self._guide = None, False, None

    def _train(self, scene, sensor, seed, spp, pixels, depth):
        """One training pass of ``spp`` (in pieces of at most MAX_RECORDS
        vertices), sampling with the guide learned so far: (voxel, cell,
        L_i, L_d) of its vertices (:meth:`Records.learned`). Every record estimates L_i
        whatever density drew it, so the passes' records are pooled."""
        pieces = max(1, -(-pixels * spp * depth // MAX_RECORDS))
        per = [spp // pieces + (k < spp % pieces) for k in range(pieces)]
        rows = []
        for k, n in enumerate(p for p in per if p):
            self._records, self.records_paths = Records(pixels * n, depth), True
            super().render(scene, sensor, pass_seed(seed, 1000 + k), n, True, True)
            rows.append(self._records.learned())
        self.records_paths = False
        return tuple(np.concatenate(c) for c in zip(*rows))

    # ------------------------- Training records ---------------------------

    def path_index(self, ray):
        if dr.is_jit_v(mi.Float):
            return dr.arange(mi.UInt32, dr.width(ray))
        return next(self._records.lanes_taken)   # (scalar: one path per call)

    def record_vertex(self, lane, depth, si, wo_world, pdf, delta, β, L, active):
        rec = self._records
        # the direction's cell in the guide frame; one to the other side is not learned
        w = to_guide(si, wo_world)
        cell = square_cell(mi.warp.cosine_hemisphere_to_square(w), self.directional_res)
        voxel = voxel_of(si.p, self._grid)
        # (no `~` on masks: in scalar variants they are Python bools)
        keep = dr.select(delta, False, active & (depth < rec.depth) & (pdf > 0) & (w.z > 0))
        if not dr.is_jit_v(mi.Float):
            if keep:
                rec.rows[(lane, depth)] = [voxel, cell, dr.mean(β), dr.mean(L), dr.mean(L)]
            return
        i = lane * rec.depth + depth
        dr.scatter(rec.voxel, voxel + 1, i, keep)
        dr.scatter(rec.cell, cell, i, keep)
        dr.scatter(rec.beta, dr.mean(β), i, keep)
        dr.scatter(rec.L, dr.mean(L), i, keep)
        dr.scatter(rec.hit, dr.mean(L), i, keep)       # (until an emission is hit)

    def record_emission(self, lane, depth, L, active):
        # Emission the continuation hit is direct light, which next-event
        # estimation samples too (exactly, under an importance-sampled map):
        # the density learns what arrives indirectly, so that q does not take
        # the emitter sample's MIS weight where it samples best; the direct
        # part sets the BSDF's share of the mixture (mixture_share).
        rec = self._records
        if not dr.is_jit_v(mi.Float):
            row = rec.rows.get((lane, depth - 1)) if depth >= 1 else None
            if active and row is not None:
                row[4] = dr.mean(L)
            return
        dr.scatter(rec.hit, dr.mean(L), lane * rec.depth + depth - 1,
                   active & (depth >= 1) & (depth <= rec.depth))

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
        node = _take(self._guide["leaf"], voxel_of(si.p, self._grid))
        alpha = _take(self._guide["alpha"], node)
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
        wo = dr.select(from_bsdf, wo_b, si.to_local(from_guide(si, wg)))

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

    def continuation_pdf(self, si, bsdf, wo_world, bsdf_pdf):
        if self._guide is None:
            return bsdf_pdf
        alpha, row = self.mixture(si, bsdf)
        return alpha * bsdf_pdf + (1 - alpha) * self.guide_density(si, row, wo_world)

    def guide_density(self, si, row, wo_world):
        """The learned density at world direction ``wo_world`` (0 on the side
        the path did not arrive from)."""
        return guide_pdf(self._guide["pmf"], row, self.directional_res,
                         to_guide(si, wo_world))

    def to_string(self) -> str:
        return (super().to_string()[:-1] + f", bsdf_fraction={self.bsdf_fraction}, "
                f"train_fraction={self.train_fraction}]")


registry.register(GuidedPathIntegrator)
