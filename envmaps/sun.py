"""Split a map into its sun and the rest, to tell a missed sun from a bias.

A hemisphere estimator hits a sun of solid angle Ω with probability about
Ω · p(ω) per sample; over N samples of a pixel it expects N·Ω·p hits, and
below one hit its mean lacks the sun's share with high probability although
the estimator is unbiased. Rendering is linear in the map, so

    image(map) = image(map without sun) + image(sun alone),

and an estimator that agrees with the reference on the sunless map and
misses only a sun it is expected to hit only a few times is limited by its
sample count, not biased (``mcillum validate`` uses this in its failure cases and
scene comparisons: validation/stages/sun_split.py).

"Sun" texels: luminance above ``SUN_FACTOR`` × the map's solid-angle-weighted
mean luminance. They are set to zero in the sunless map.

A sun too small for the samples to hit often enough has a stand-in: the map
with its sun **widened** (:func:`widen`) to a disc of
:data:`WIDENED_SOLID_ANGLE` about it, the sun's texels kept and the disc
around them at the sun's own radiance (its power-weighted mean). An
estimator that does not sample the emitters weighs each hit the same
whatever the disc's size (L·f·cos/p: the same radiance, nearby directions),
so a bias it has on the sun (a clamp on bright samples, a pdf that is off
there) it has on the disc, which the samples do hit.
"""

from __future__ import annotations

import os

import numpy as np

from . import catalog, procedural, safety

SUN_FACTOR = 100.0
#: The widened sun's solid angle (sr): a disc of about 14.5° radius. At 8²
#: px a hemisphere estimator hits it some 10⁴ times over the image in 16 384
#: samples per pixel; at 0.06 sr four of the quick profile's fifteen sunlit
#: tests still ended at ±4-6 %
#: (docs/measurements.md#2026-12-03-widened-sun-decides-sun).
WIDENED_SOLID_ANGLE = 0.2
#: Rec. 709 luminance weights.
LUMA = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(…, C≥3) linear RGB → (…) luminance."""
    return np.asarray(rgb, np.float64)[..., :3] @ LUMA


def _texels(rgb: np.ndarray):
    """(luminance, cell solid angles, solid-angle-weighted mean luminance) of a map."""
    lum = luminance(rgb)
    solid = procedural.cell_solid_angles(*lum.shape)
    return lum, solid, float((lum * solid).sum() / solid.sum())


def sun_mask(rgb: np.ndarray, factor: float = SUN_FACTOR) -> np.ndarray:
    """(H, W) True at texels brighter than ``factor`` × the mean luminance."""
    lum, _, mean = _texels(rgb)
    return lum > factor * mean


def split(rgb: np.ndarray, factor: float = SUN_FACTOR) -> tuple[np.ndarray, dict]:
    """(map without its sun, facts): the sun's solid angle (sr), its share of
    the map's power (∫L dω, luminance) and texel count."""
    lum, solid, mean = _texels(rgb)
    mask = lum > factor * mean
    power = float((lum * solid).sum())
    sunless = np.where(mask[..., None], 0.0, rgb).astype(np.float32)
    return sunless, {"solid_angle": float(solid[mask].sum()), "texels": int(mask.sum()),
                     "power_share": float((lum * solid)[mask].sum() / power) if power else 0.0,
                     "factor": factor}


def without_sun(path: str | os.PathLike, factor: float = SUN_FACTOR) -> tuple[str, dict]:
    """Path of a cached copy of the (checked) map at ``path`` without its sun,
    and the facts of :func:`split`."""
    rgb, _ = safety.load(path)
    sunless, facts = split(rgb, factor)
    return _cached(path, "sunless", {"factor": factor}, sunless,
                   (split, procedural.cell_solid_angles, safety.sanitise)), facts


def _cached(path, name: str, params: dict, rgb: np.ndarray, code) -> str:
    """Path of the cached map ``rgb`` made from the map at ``path`` by
    ``code`` with ``params`` (catalog.cached, keyed by the source file too)."""
    st = os.stat(path)
    key = {"name": name, "source": os.path.abspath(path), "size": st.st_size,
           "mtime": st.st_mtime, **params}
    return catalog.cached(key, lambda: rgb, code)


def widen(rgb: np.ndarray, solid_angle: float = WIDENED_SOLID_ANGLE,
          factor: float = SUN_FACTOR) -> tuple[np.ndarray, dict]:
    """(map with its sun widened, facts): the texels within the angle about
    the sun's power-weighted centre that holds ``solid_angle`` take the sun's
    power-weighted mean radiance, except the sun's own texels, which keep
    theirs; the rest of the map is unchanged. Facts: the disc's solid angle
    (sr), its radiance (RGB) and texel count. Raises ValueError for a map
    without a sun."""
    lum, solid, mean = _texels(rgb)
    sun = lum > factor * mean
    if not sun.any():
        raise ValueError("the map has no sun to widen (no texel above "
                         f"{factor:g}× its mean luminance)")
    power = lum * solid * sun
    dirs = procedural.directions(lum.shape[1], lum.shape[0])[:, :, 0]   # texel centres
    centre = (dirs * power[..., None]).sum(axis=(0, 1))
    centre /= np.linalg.norm(centre)
    cos = dirs @ centre
    order = np.argsort(-cos, axis=None)                 # nearest first
    cut = np.searchsorted(np.cumsum(solid.ravel()[order]), solid_angle)
    disc = np.zeros(lum.size, bool)
    disc[order[:cut + 1]] = True
    disc = disc.reshape(lum.shape) | sun
    radiance = (np.asarray(rgb, np.float64)[..., :3] * power[..., None]).sum(axis=(0, 1)) \
        / power.sum()
    out = np.array(rgb, np.float32, copy=True)
    out[disc & ~sun, :3] = radiance
    return out, {"solid_angle": float(solid[disc].sum()), "texels": int(disc.sum()),
                 "radiance": [float(x) for x in radiance], "factor": factor}


def widened(path: str | os.PathLike, solid_angle: float = WIDENED_SOLID_ANGLE,
            factor: float = SUN_FACTOR) -> tuple[str, dict]:
    """Path of a cached copy of the (checked) map at ``path`` with its sun
    widened (:func:`widen`), and the facts."""
    rgb, _ = safety.load(path)
    out, facts = widen(rgb, solid_angle, factor)
    return _cached(path, "widened_sun", {"factor": factor, "solid_angle": solid_angle}, out,
                   (widen, procedural.directions, procedural.cell_solid_angles,
                    safety.sanitise)), facts
