"""Mitsuba's ``sunsky`` emitter (Hosek–Wilkie sky + solar disk) baked to a map.

The sun's disk is 0.5358° wide, smaller than a pixel of a 1024×512 latlong
map (0.35° × 0.35° at the equator, wider near the poles); sampling pixel centres
would catch or miss it by chance. Each pixel is therefore the mean of
``supersample``² stratified directions, and the pixels around the sun are
refined with ``sun_supersample``² directions, so the disk's energy lands in the
map. :func:`energy_error` measures what is left: the irradiance of the baked map
on a plane against Mitsuba's own importance-sampled estimate from the live
emitter.

Units are Mitsuba's (physical radiance, sun up to ~10⁷); ``scale`` multiplies
the whole map. Mitsuba's sunsky is z-up; the map is y-up like every envmap.
"""

from __future__ import annotations

from contextlib import contextmanager

import mitsuba as mi
import numpy as np

from . import procedural


@contextmanager
def _variant(variant: str):
    """Run in ``variant`` (a vectorized one: millions of directions), then
    restore the caller's variant."""
    before = mi.variant()
    if before != variant:
        mi.set_variant(variant)
    try:
        yield mi
    finally:
        if before is not None and before != variant:
            mi.set_variant(before)


def sun_direction(sun_elevation_deg: float, sun_azimuth_deg: float) -> np.ndarray:
    """Unit direction towards the sun in the map's y-up world frame."""
    el, az = np.radians(sun_elevation_deg), np.radians(sun_azimuth_deg)
    return np.array([np.cos(el) * np.cos(az), np.sin(el), -np.cos(el) * np.sin(az)])


def emitter(mi, sun_elevation_deg: float, sun_azimuth_deg: float, turbidity: float):
    """A y-up ``sunsky`` emitter with the sun at the given elevation/azimuth.

    ``to_world`` turns sunsky's z-up sky into y-up; ``sun_direction`` is
    taken in *world* space by Mitsuba 3.9 (measured: the baked peak lands there).
    """
    return mi.load_dict({
        "type": "sunsky", "turbidity": float(turbidity),
        "sun_direction": [float(c) for c in sun_direction(sun_elevation_deg, sun_azimuth_deg)],
        "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),
    })


def _radiance(mi, em, d: np.ndarray) -> np.ndarray:
    """Radiance arriving from directions ``d`` (N, 3), as (N, 3) RGB."""
    si = mi.SurfaceInteraction3f()
    si.wi = -mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])  # looking along d
    return np.array(em.eval(si), dtype=np.float64).reshape(3, -1).T


def bake(sun_elevation_deg: float = 30.0, sun_azimuth_deg: float = 40.0,
         turbidity: float = 3.0, scale: float = 1.0, width: int = 1024, height: int = 512,
         supersample: int = 2, sun_supersample: int = 64,
         variant: str = "llvm_ad_rgb") -> np.ndarray:
    """Bake the sun and sky to a latlong map (H, W, 3) float32.

    No closed form; the energy kept is measured by :func:`energy_error`.
    """
    with _variant(variant) as mi:
        em = emitter(mi, sun_elevation_deg, sun_azimuth_deg, turbidity)
        flat = lambda d: _radiance(mi, em, d.reshape(-1, 3)).reshape(d.shape)  # noqa: E731
        rgb = procedural.bake(flat, width, height, supersample).astype(np.float64)

        # Refine every pixel within 2° of the sun (the disk's radius is 0.27°).
        sun = sun_direction(sun_elevation_deg, sun_azimuth_deg)
        centres = procedural.directions(width, height, 1)[:, :, 0]
        near = np.argwhere(centres @ sun > np.cos(np.radians(2.0)))
        if len(near):
            d = np.stack([procedural.cell_directions(width, height, y, x, sun_supersample)
                          for y, x in near])                       # (n, s², 3)
            rgb[near[:, 0], near[:, 1]] = flat(d).mean(axis=1)
    return (rgb * scale).astype(np.float32)


def energy_error(rgb: np.ndarray, sun_elevation_deg: float = 30.0,
                 sun_azimuth_deg: float = 40.0, turbidity: float = 3.0,
                 scale: float = 1.0, samples: int = 1 << 22, variant: str = "llvm_ad_rgb"):
    """Relative error of the baked map's irradiance on an upward plane against
    an importance-sampled estimate from the live emitter (``samples`` draws).

    Returns (relative error per channel, standard error of the reference, relative).
    """
    with _variant(variant) as mi:
        em = emitter(mi, sun_elevation_deg, sun_azimuth_deg, turbidity)
        import drjit as dr

        it = dr.zeros(mi.Interaction3f)  # any reference point: the sky is infinite
        u = np.random.default_rng(0).random((2, samples))
        ds, weight = em.sample_direction(it, mi.Point2f(u[0], u[1]))
        cos = np.clip(np.array(ds.d.y), 0, None)
        terms = np.array(weight, np.float64).reshape(3, -1) * cos * scale  # L cos / pdf
    reference = terms.mean(axis=1)
    stderr = terms.std(axis=1) / np.sqrt(samples) / reference
    baked = procedural.irradiance(rgb, (0, 1, 0))
    return baked / reference - 1, stderr
