"""The directional structure of a leaf of `guided_path`'s spatial tree:
per cell of the res² cosine-warped square, the mean L_i of a quadtree cell
that refines where the leaf's light concentrates (after Müller et al.'s
directional quadtree), rebuilt from the pooled records at every training
iteration. The pmf a leaf samples from is these means, with a uniform
floor (:data:`FLOOR`)."""

from __future__ import annotations

import numpy as np

FLOOR = 0.1                # uniform share of every learned pmf
MIN_SPLIT = 128            # records a directional cell needs to be refined
SHRINK = 64                # records' worth a refined cell's mean is pulled to its parent's


def leaf_pmfs(means: np.ndarray) -> np.ndarray:
    """Per row of cell ``means`` (rows, res²), the pmf ∝ them with a uniform
    floor of :data:`FLOOR`: every cell keeps a share, so what the records
    missed can still be drawn."""
    nb = means.shape[1]
    return (1 - FLOOR) * means / np.maximum(means.sum(axis=1, keepdims=True), 1e-30) + FLOOR / nb


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
