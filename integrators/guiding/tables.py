"""The tables `guided_path` samples its learned density from, and the
sampling routine, its density and its inverse (:func:`sample_guide`,
:func:`guide_pdf`, :func:`invert_guide`): each leaf's pmf over the res²
cells of the cosine-warped square, quantized to equal-probability slots so
that a sample costs one gather. Nothing here depends on the variant:
Mitsuba's types are looked up when called."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

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



# ------------------------------ Strategy ------------------------------------
# The learned part is a piecewise-constant density on the unit square, warped
# to the hemisphere by the cosine warp (Shirley-Chiu's concentric map, as
# mi.warp.square_to_cosine_hemisphere) in a frame built from the shading
# normal alone, turned to the side the path arrived from: a uniform pmf is
# cosine sampling, and a pmf ∝ the mean L_i over each of the res² cells makes
# p ∝ L_i cos θ (the product a diffuse vertex wants). Directions on the
# other side get density 0: the BSDF's share covers them.
#     p(ω) = pmf[cell(ω)] · res² · cos θ / π
# It is the density seen from the vertex's anchor c (spatial.anchor_of), as
# if the light lay on a sphere about c of radius r (the leaf's learned
# distance, at least 2|x − c|): a vertex x draws ω_c, then ω towards
# y = c + r ω_c (parallax), and
#     p_x(ω) = p(ω_c) · t² / (r² cos θ_y),   y = x + t ω on the sphere,
# cos θ_y the angle between ω and the sphere's normal ω_c at y.


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
