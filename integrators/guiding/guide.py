"""What `guided_path` learns, and the tables it samples from: a binary tree
over the scene's bounds with a learned pmf per node (over the res² cells of
the cosine-warped square, means taken over a refining quadtree, of the
directions from fixed anchors to where the records' light came from) and
the distance of that light, the training records its paths leave, and each
pmf quantized to equal-probability slots so that a sample costs one gather.

The sampling routine, its density and its inverse (``sample_guide``,
``guide_pdf``, ``invert_guide``) are in guided_path.py beside the plugin;
they read what :meth:`Guide.device` builds here. Nothing here depends on the
variant: Mitsuba's types are looked up when called.
"""

from __future__ import annotations

import hashlib
import itertools
from collections import deque

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy import sparse


def take(array, index):
    """``array[index]``: a gather in JIT variants, an element in scalar ones."""
    if dr.is_jit_v(mi.Float):
        return dr.gather(type(array), array, index)
    return array[int(index)].item()


# ------------------------------ Sampling tables ----------------------------------

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
    i = _voxel_coordinates(p, grid)
    return i[0] + GRID * (i[1] + GRID * i[2])


def _voxel_coordinates(p: mi.Point3f, grid) -> list:
    """The grid coordinates of the voxel that holds ``p`` (clamped to it)."""
    lo, scale = grid
    return [dr.minimum(mi.UInt32(dr.maximum((p[k] - float(lo[k])) * float(scale[k]), 0)),
                       GRID - 1) for k in range(3)]


# Parallax: a vertex sees its leaf's learned light from the centre of its
# anchor block (ANCHOR³ voxels, fixed, whatever the tree), as if that light
# lay on a sphere about the centre at the leaf's distance (guided_path's
# to_anchor/from_anchor). Records learn the direction from the anchor to
# the point their continuation hit, so that a small source seen from all
# over a leaf falls into the same cells.
ANCHOR = 8
FAR = 1e4                  # (× the scene's size: where an escaped record's light is)


def anchor_of(p: mi.Point3f, grid) -> mi.Point3f:
    """Centre of the anchor block that holds ``p``."""
    return _block_centre(_voxel_coordinates(p, grid), grid)


def anchor_of_voxel(voxel: mi.UInt32, grid) -> mi.Point3f:
    """Centre of the anchor block of voxel index ``voxel`` (as :func:`voxel_of`)."""
    return _block_centre([voxel % GRID, (voxel // GRID) % GRID, voxel // (GRID * GRID)], grid)


def on_plane(c: mi.Point3f, x: mi.Point3f, n: mi.Vector3f) -> mi.Point3f:
    """The anchor ``c`` moved onto the tangent plane of ``x`` (normal ``n``):
    seen from there, a surface's horizon is its own, so light near the
    plane of a wall stays on the side it lies."""
    return c - n * dr.dot(c - x, n)


def _block_centre(i, grid) -> mi.Point3f:
    lo, scale = grid
    return mi.Point3f(*[float(lo[k]) + (mi.Float(i[k] // ANCHOR * ANCHOR) + 0.5 * ANCHOR)
                        / float(scale[k]) for k in range(3)])


TRAIN_DEPTH = 8            # vertices of a training path that are recorded
PASSES = 2                 # training passes at most, by default (each traces the kernel)
#: Share of a render's samples that train, by default. With the training
#: images kept, ⅛ against ¼ at 128² × 256 spp: the same error for 15-25 %
#: less time (a training sample records its path, at about 2× a sample's
#: cost); ¹⁄₁₆ was within the intervals of ⅛ but for the scene made for
#: guiding, 1.23× against 1.36× `path` (docs/measurements.md, 2026-12-03).
TRAIN_FRACTION = 0.125
#: Guiding goes on while the learned mixture is predicted to leave at most
#: this share of BSDF sampling's variance of the indirect light
#: (Guide.variance_ratio), and while a pass it drew measured at most this
#: share of the unguided pass's relative variance per sample
#: (measured_ratios): the guided kernel costs 1.2-1.5x mis's per sample,
#: and the indirect light is only part of a pixel's variance.
PAYS_BELOW = 0.8
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
        self.distance = np.zeros(1)              # of its light from the anchors (0: far)
        # per node and cell the records' count, Σ L_i and Σ L_i² (None: not learned)
        self.counts = self.sums = self.squares = None
        self.voxel_node = np.zeros(GRID ** 3, np.int64)   # leaf of every voxel: the root

    @property
    def leaves(self) -> int:
        return int(np.sum(self.child == 0))

    @property
    def trained_leaves(self) -> int:
        return int(np.sum(self.trained & (self.child == 0)))

    @classmethod
    def learn(cls, tally: Tally, threshold: float, refine: float) -> Guide:
        """The tree and pmfs of the training records summed in ``tally``
        (:class:`Tally`): per voxel and cell of the res² square, the
        records' count, the radiance L_i they saw arrive indirectly (its sum
        and sum of squares) and the emission L_d their directions hit,
        MIS-weighted.

        The tree splits the grid breadth first (in voxel units) while a
        node holds more than ``threshold``·√R of the R records (so that, as
        in Müller et al., leaves and the records per leaf both grow as √R:
        more records buy spatial and directional resolution alike); a split
        never divides a voxel, so the voxels' sums are all it reads. A node
        with at least MIN_TRAINED records learns its pmf from them
        (:func:`refined_means`: per cell the mean L_i of a quadtree cell
        that is refined where light concentrates); one with fewer keeps its
        parent's (uniform at the root: cosine sampling, not trained).
        Every cell spans the same cosine-weighted solid angle, so a cell's
        mean L_i is its share of ∫ L_i cos θ, up to its within-cell
        variation, and far less noisy than splatting L_i/p, which one rare
        record of small p dominates. A node also keeps the share of its
        records' light that arrived indirectly, Σ li / Σ (li + ld): the
        part of the continuation's integrand the learned density models
        (the rest is the BSDF sample's share of the direct light, which it
        samples well).

        The image is unbiased whatever is learned."""
        res = tally.res
        g = cls(res)
        if not tally.records:
            return g
        nb = res * res
        g._grow(tally.voxel_counts, threshold * np.sqrt(tally.records))
        nodes = len(g.child)
        hits, total, squares, direct = tally.node_sums(g.voxel_node, nodes)
        if not np.any(total > 0):       # (no light arrived: no node would learn)
            return cls(res)
        near = np.bincount(g.voxel_node, weights=tally.voxel_near, minlength=nodes)
        for k in reversed(range(nodes)):     # (an inner node's sums are its children's)
            first = int(g.child[k])
            if first:
                for a in (hits, total, squares, direct, near):
                    a[k] = a[first] + a[first + 1]
        g.counts, g.sums, g.squares = hits, total, squares
        light = total.sum(axis=1)
        own = (hits.sum(axis=1) >= MIN_TRAINED) & (light > 0)
        means = refined_means(hits, total, res, refine)
        pmf = (1 - FLOOR) * means / np.maximum(means.sum(axis=1, keepdims=True), 1e-30) \
            + FLOOR / nb
        indirect = light / np.maximum(light + direct, 1e-30)
        # the distance of a node's light from its anchors: Σ L_i / Σ (L_i /
        # distance), a harmonic mean that the near light sets (0 where all
        # came from afar: no parallax)
        distance = np.where(near > 0, light / np.maximum(near, 1e-30), 0.0)
        g.pmf, g.trained, g.indirect = np.repeat(g.pmf, nodes, axis=0), np.zeros(nodes, bool), \
            np.zeros(nodes)
        g.distance = np.zeros(nodes)
        parent = g.parents()
        for k in range(nodes):               # (breadth first: a parent before its children)
            if own[k]:
                g.pmf[k], g.trained[k], g.indirect[k] = pmf[k], True, indirect[k]
                g.distance[k] = distance[k]
            elif k:
                p = parent[k]
                g.pmf[k], g.trained[k], g.indirect[k] = g.pmf[p], g.trained[p], g.indirect[p]
                g.distance[k] = g.distance[p]
        return g

    def _grow(self, counts, threshold: float):
        """Split the root breadth first by the records per voxel ``counts``."""
        occupied = np.flatnonzero(counts)
        p, c = _voxel_centres(occupied), counts[occupied]
        axis, split, child = [0], [0.0], [0]
        leaf_of = np.zeros((GRID,) * 3, np.int64)      # (z, y, x): voxel v's leaf at v
        queue = deque([(0, np.arange(len(occupied)), np.zeros(3), np.full(3, float(GRID)), 0)])
        while queue:
            node, idx, lo, hi, depth = queue.popleft()
            if c[idx].sum() <= threshold or depth >= MAX_TREE_DEPTH or np.max(hi - lo) <= 1:
                # (splits halve sides of 2^k voxels: a leaf's box is whole voxels)
                x0, y0, z0 = lo.astype(int)
                x1, y1, z1 = hi.astype(int)
                leaf_of[z0:z1, y0:y1, x0:x1] = node
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
        self.voxel_node = leaf_of.reshape(-1)

    def parents(self) -> np.ndarray:
        """Parent of every node (-1 for the root)."""
        parent = np.full(len(self.child), -1, np.int64)
        inner = np.flatnonzero(self.child)
        parent[self.child[inner]] = inner
        parent[self.child[inner] + 1] = inner
        return parent

    def variance_ratio(self, bsdf_fraction: float) -> float:
        """The variance of the indirect light's one-sample estimate with this
        guide's mixture, over its variance with the BSDF's (cosine) sampling
        alone, predicted from the records it learned from: per leaf and
        cell the records' mean L_i and L_i², with q_c the mixture's
        probability of cell c (α/n + (1 − α)·pmf_c of the n cells, each
        of equal cosine-weighted solid angle),

            V_q = Σ_c m2_c / (n² q_c) − I²,   V_cos = Σ_c m2_c / n − I²,

        I the leaf's mean L_i, summed over leaves weighted by their records
        (the vertices they stand for). NaN where no leaf learned."""
        if self.counts is None or not self.trained_leaves:
            return float("nan")
        nb = self.res * self.res
        count, first, second = self.counts, self.sums, self.squares
        n = count.sum(axis=1)
        # (a cell no record fell in: its leaf's mean, as the learned pmf does)
        m1 = np.where(count > 0, first / np.maximum(count, 1),
                      (first.sum(axis=1) / np.maximum(n, 1))[:, None])
        m2 = np.where(count > 0, second / np.maximum(count, 1),
                      (second.sum(axis=1) / np.maximum(n, 1))[:, None])
        alpha = np.where(self.trained, mixture_share(bsdf_fraction, self.indirect), 1.0)
        q = alpha[:, None] / nb + (1 - alpha[:, None]) * self.pmf
        mean_sq = m1.mean(axis=1) ** 2
        v_cos = m2.mean(axis=1) - mean_sq
        v_mix = (m2 / q).sum(axis=1) / nb ** 2 - mean_sq
        leaves = (self.child == 0) & (n > 0)
        below = float(np.sum(n[leaves] * v_cos[leaves]))
        return float(np.sum(n[leaves] * v_mix[leaves])) / below if below > 0 else float("nan")

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
        pmfs and slot tables (:func:`guide_tables`), their BSDF shares and
        light's distances, and the leaf of every voxel."""
        leaves = np.flatnonzero(self.child == 0)
        row = np.zeros(len(self.child), np.int64)
        row[leaves] = np.arange(len(leaves))
        alpha = np.where(self.trained[leaves], mixture_share(bsdf_fraction, self.indirect[leaves]),
                         1.0).astype(np.float32)
        leaf = row[self.voxel_node].astype(np.uint32)
        arrays = {"leaf": leaf, "alpha": alpha, **guide_tables(self.pmf[leaves]),
                  "distance": self.distance[leaves].astype(np.float32)}
        if not dr.is_jit_v(mi.Float):
            return arrays
        out = {k: owned(v) for k, v in arrays.items()}
        dr.eval(out)
        return out


def owned(array: np.ndarray):
    """``array`` as the variant's UInt32 or Float, in memory Dr.Jit owns:
    made from numpy alone it maps numpy's memory (LLVM variants), and a
    frozen pass (validation/run/replays.py) is recorded again whenever that
    memory's alignment changes, 5-14 recordings for the same 12 renders
    where it needs 5. (The opaque 0 keeps the sum from folding away.) The
    copy reads from a 64-byte aligned buffer: Dr.Jit compiles the reading
    kernel for the source's alignment, and numpy's varied, so a copy could
    compile in any render, and a timed render that compiles is rendered
    again (validation/run/renders.timed_render)."""
    kind = mi.UInt32 if array.dtype == np.uint32 else mi.Float
    return kind(_aligned(array)) + dr.opaque(kind, 0)


def _aligned(array: np.ndarray, to: int = 64) -> np.ndarray:
    """A copy of ``array`` (1-D) whose data starts on a ``to``-byte boundary."""
    raw = np.empty(array.nbytes + to, np.uint8)
    start = -raw.ctypes.data % to
    out = raw[start:start + array.nbytes].view(array.dtype)
    out[:] = array
    return out


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
    h, t = _pyramid(hits.reshape(n, res, res)), _pyramid(total.reshape(n, res, res))

    def children(a):                         # each cell's value on its 2 × 2 children
        return a.repeat(2, axis=1).repeat(2, axis=2)

    root = t[1][:, 0, 0] / np.maximum(h[1][:, 0, 0], 1)
    mean = root[:, None, None]
    refined = np.ones((n, 1, 1), bool)       # cells whose quadtree reaches this level
    k = 1
    while k < res:
        share = mean / (k * k) / np.maximum(root, 1e-30)[:, None, None]
        split = children(refined & (share > refine) & (h[k] >= MIN_SPLIT))
        hk, tk = h[2 * k], t[2 * k]
        prior = children(mean)
        own = (tk + SHRINK * prior) / (hk + SHRINK)
        mean = np.where(split, own, children(mean))
        refined, k = split, 2 * k
    return mean.reshape(n, res * res)


def _pyramid(a: np.ndarray) -> dict[int, np.ndarray]:
    """Sums of ``a`` (n, res, res) over the k × k quadtree cells, by k (1,
    2, 4 … res), each level from the one below it."""
    out = {a.shape[1]: a}
    k = a.shape[1]
    while k > 1:
        k //= 2
        out[k] = out[2 * k].reshape(len(a), k, 2, k, 2).sum(axis=(2, 4))
    return out


class Tally:
    """A render's training records, as :meth:`Guide.learn` reads them: per
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
    every voxel made small renders 5× slower (docs/measurements.md,
    2026-12-06)."""

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


class PixelMoments:
    """Σ L and Σ L² per pixel of the paths' radiance in the training passes
    drawn with one density (Records.pixel_moments), in two halves (a
    pixel's even and odd samples, so that one half can weigh the other
    without bias), and each half's samples per pixel."""

    def __init__(self):
        self.halves = [[None, None, 0], [None, None, 0]]

    def add(self, moments) -> None:
        """Add ``moments`` (as Records.pixel_moments gives them; None: nothing)."""
        if moments is None:
            return
        for half, (first, second, n) in zip(self.halves, moments):
            if n:
                half[0] = first if half[0] is None else half[0] + first
                half[1] = second if half[1] is None else half[1] + second
                half[2] += n

    def mean_square(self, half=None) -> tuple:
        """(mean, mean of squares) per pixel of one half (0, 1) or of both;
        (None, None) where it holds no samples."""
        parts = [h for i, h in enumerate(self.halves) if h[2] and half in (None, i)]
        if not parts:
            return None, None
        n = sum(h[2] for h in parts)
        return sum(h[0] for h in parts) / n, sum(h[1] for h in parts) / n


#: Relative variance as relMSE weighs it: over (μ² + this) per pixel (tev's
#: convention, as validation/stats/metrics.py).
RELATIVE_EPSILON = 0.01


#: A guided pass whose pixels' mean (weighted as relMSE weighs them) is this
#: much above the unguided pass's found light the unguided paths missed:
#: their variance reads low, and the measured share is not trusted.
#: sunlit_room under its hole (sun 500), where guiding cut relMSE to 0.29×
#: at 64² × 1 024 spp, read 1.11 with a variance share of 1.16 in one of
#: three renders at 32² × 512 spp; the Cornell box, the sunrise and city
#: probes, phong_spheres and sun_sky, where guiding did not pay, read
#: 0.98-1.02 (docs/measurements.md, 2026-12-06).
UNSEEN_ABOVE = 1.05


def measured_ratios(unguided: PixelMoments, guided: PixelMoments) -> tuple[float, float]:
    """(variance, mean): the relative variance of one sample of the pixels'
    estimate drawn with a learned density (``guided``) over that of BSDF
    sampling's (``unguided``), measured on the training passes' own paths,
    and the ratio of their means. Per pixel the variance is E[L²] − μ², μ²
    estimated without bias by the product of the two passes' means
    (independent samples of one pixel), weighted by 1/(μ̂² + ε) as relMSE
    weighs pixels, μ̂ the mean of the guided pass's other half (a weight
    drawn from the samples it weighs biased the variances by more than
    they are); both ways round, summed. What the whole path's estimate
    gains, direct light and path weights included, where
    Guide.variance_ratio predicts the indirect light's alone. A mean ratio
    above :data:`UNSEEN_ABOVE` says the unguided paths missed light (their
    variance reads low). (NaN, NaN) where either was not measured or the
    guided pass has one sample per pixel; inf where the unguided paths show
    no variance."""
    m_u, s_u = unguided.mean_square()
    if m_u is None or not all(h[2] for h in guided.halves):
        return float("nan"), float("nan")
    v_u = v_g = mean_u = mean_g = 0.0
    for weighs, weighed in ((0, 1), (1, 0)):
        m_w, _ = guided.mean_square(weighs)
        m_g, s_g = guided.mean_square(weighed)
        weight = 1.0 / (np.square(m_w) + RELATIVE_EPSILON)
        v_u += float(np.sum(weight * (s_u - m_u * m_g)))
        v_g += float(np.sum(weight * (s_g - m_u * m_g)))
        mean_u += float(np.sum(weight * m_u))
        mean_g += float(np.sum(weight * m_g))
    return (v_g / v_u if v_u > 0 else float("inf")), \
        (mean_g / mean_u if mean_u > 0 else float("inf"))


class Records:
    """What the training paths of one render leave: per vertex its voxel,
    the point its continuation hit (far along it where it escaped), the
    normal of its guide frame, the throughput after it, the radiance
    gathered before its continuation and after the emission the
    continuation hit; per path its radiance (radiance and throughput as
    their mean over the channels: only learning reads them). Device buffers
    in JIT variants, lists in scalar ones."""

    def __init__(self, lanes: int, depth: int):
        self.lanes, self.depth = lanes, depth
        if dr.is_jit_v(mi.Float):
            n = lanes * depth
            self.voxel = dr.zeros(mi.UInt32, n)         # voxel + 1; 0: none
            self.beta, self.L = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
            self.hit = dr.zeros(mi.Float, n)
            self.path = dr.zeros(mi.Float, lanes)
            self.x = [dr.zeros(mi.Float, n) for _ in range(3)]    # the vertex
            self.y = [dr.zeros(mi.Float, n) for _ in range(3)]    # the point hit
            self.g = [dr.zeros(mi.Float, n) for _ in range(3)]    # the frame's normal
        else:
            self.rows, self.path_L, self.lanes_taken = {}, {}, itertools.count()

    #: The device arrays a training pass scatters into, in order.
    FIELDS = ("voxel", "beta", "L", "hit", "path", "x", "y", "g")

    def arrays(self) -> tuple:
        """The device arrays of :attr:`FIELDS` (JIT variants), flat."""
        out = []
        for f in self.FIELDS:
            a = getattr(self, f)
            out += a if isinstance(a, list) else [a]
        return tuple(out)

    def hold(self, arrays) -> None:
        """Make ``arrays`` (as :meth:`arrays` returns them) these records'."""
        arrays = list(arrays)
        for f in self.FIELDS:
            if isinstance(getattr(self, f), list):
                setattr(self, f, arrays[:3])
                del arrays[:3]
            else:
                setattr(self, f, arrays.pop(0))

    def pixel_moments(self, pixels: int):
        """[(Σ L, Σ L², samples)] per pixel of the ``pixels`` (numpy) from the
        paths' radiance, of its even and of its odd samples, as
        :class:`PixelMoments` adds them; None in scalar
        variants, which trace a pixel's samples in no fixed order. A JIT
        wavefront holds each pixel's samples side by side (Mitsuba's
        sampling integrator: lane // spp is the pixel)."""
        if not dr.is_jit_v(mi.Float) or self.lanes % pixels:
            return None
        n = self.lanes // pixels
        # (summed on the device: numpy's sums along rows of a few samples
        # took 30 ms a pass at 256² beside Dr.Jit's threads; n opaque, so
        # that every spp shares one kernel)
        lane = dr.arange(mi.UInt32, self.lanes)
        per = dr.opaque(mi.UInt32, n)
        slot = lane // per * 2 + lane % per % 2
        sums = [dr.zeros(mi.Float, 2 * pixels) for _ in range(2)]
        dr.scatter_reduce(dr.ReduceOp.Add, sums[0], self.path, slot)
        dr.scatter_reduce(dr.ReduceOp.Add, sums[1], dr.square(self.path), slot)
        dr.eval(sums)
        first, second = (np.array(a, np.float64).reshape(pixels, 2) for a in sums)
        return [(first[:, h], second[:, h], (n + 1 - h) // 2) for h in (0, 1)]

    def learned(self, grid, res: int, parallax: bool = True):
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
        if not dr.is_jit_v(mi.Float):
            return self._learned_scalar(grid, res, parallax, none)
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
        cell, dist, above = anchored_cell(voxel, x, y, g, grid, res, parallax)
        alive = dr.compress((beta > 0) & dr.isfinite(li) & dr.isfinite(ld) & above)
        out = [dr.gather(type(a), a, alive) for a in (voxel, cell, li, ld, dist)]
        dr.eval(out)                           # (one launch for the five)
        voxel, cell, li, ld, dist = (np.array(a) for a in out)
        return voxel.astype(np.int64), cell.astype(np.int64), li, ld, dist

    def _learned_scalar(self, grid, res, parallax, none):
        if not self.rows:
            return none
        lane = np.array([k[0] for k in self.rows])
        voxel, beta, L, hit, x, y, g = zip(*self.rows.values())
        voxel, beta, L, hit = (np.array(c) for c in (voxel, beta, L, hit))
        path = np.array([self.path_L[int(x)] for x in lane])
        found = [anchored_cell(v, a, b, n, grid, res, parallax)
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


def square_cell(u: mi.Point2f, res: int) -> mi.UInt32:
    """Cell of square point ``u`` (row-major)."""
    ix = dr.minimum(mi.UInt32(dr.maximum(u.x * res, 0)), res - 1)
    iy = dr.minimum(mi.UInt32(dr.maximum(u.y * res, 0)), res - 1)
    return iy * res + ix
