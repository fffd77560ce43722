"""What `guided_path` learns: a binary tree over the scene's voxel grid
(:mod:`.spatial`) with, in every node, a pmf over the res² cells of the
cosine-warped square (:mod:`.directional`: means over a refining quadtree
of the directions from fixed anchors to where the records' light came
from), the share of its light that arrives indirectly and the distance of
that light; rebuilt from the pooled records (:class:`.records.Tally`) at
every training iteration, and made into the tables the kernel samples from
(:meth:`Guide.device`, :mod:`.tables`). Nothing here depends on the
variant: Mitsuba's types are looked up when called."""

from __future__ import annotations

from collections import deque

import drjit as dr
import mitsuba as mi
import numpy as np

from .directional import leaf_pmfs, refined_means
from .spatial import GRID, voxel_centres
from .tables import guide_tables, owned

MIN_TRAINED = 128          # records a node needs to learn its own pmf
MAX_TREE_DEPTH = 3 * 5     # (a leaf of one voxel: GRID = 2^5)


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
    def learn(cls, tally, threshold: float, refine: float) -> Guide:
        """The tree and pmfs of the training records summed in ``tally``
        (:class:`.records.Tally`): per voxel and cell of the res² square, the
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
        pmf = leaf_pmfs(means)
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
        p, c = voxel_centres(occupied), counts[occupied]
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


def mixture_share(bsdf_fraction: float, indirect):
    """The BSDF's share α of a node's one-sample mixture, from the share of
    its light that arrives indirectly: α = 1 − (1 − ``bsdf_fraction``)·share,
    ``bsdf_fraction`` where all light is indirect, 1 where none is.

    The continuation's integrand is f cos (L_ind + w L_dir): the learned
    density follows the first part only, the BSDF's sample suits the second
    (NEE takes the rest of L_dir). With ``bsdf_fraction`` everywhere, the
    variance at equal spp was 2.3× `mis`'s under sky_sphere's smooth sky
    (where light is mostly direct); with this share 1.13×, and on
    sunlit_room unchanged
    (docs/measurements.md#2026-12-02-guided-path-bsdf-share-learning)."""
    return 1.0 - (1.0 - bsdf_fraction) * np.asarray(indirect)
