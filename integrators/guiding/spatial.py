"""Where `guided_path` learns: a GRID³ voxel grid over the scene's bounds,
the anchors a vertex sees its leaf's light from (parallax), and the guide
frame at a vertex. The spatial tree (:class:`.guide.Guide`) splits blocks
of these voxels; flattened into a voxel → leaf table for sampling, a vertex
finds its leaf with one lookup. Nothing here depends on the variant:
Mitsuba's types are looked up when called."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

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


def voxel_centres(voxel: np.ndarray) -> np.ndarray:
    """Centres of voxels (n, 3), in voxel units."""
    v = np.asarray(voxel, np.int64)
    return np.stack([v % GRID, (v // GRID) % GRID, v // (GRID * GRID)], axis=1) + 0.5


# ------------------------------- Anchors -------------------------------------
# Parallax: a vertex sees its leaf's learned light from the centre of its
# anchor block (ANCHOR³ voxels, fixed, whatever the tree), as if that light
# lay on a sphere about the centre at the leaf's distance (to_anchor /
# from_anchor). Records learn the direction from the anchor to the point
# their continuation hit, so that a small source seen from all over a leaf
# falls into the same cells.
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


# ----------------------------- Guide frame -----------------------------------


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
