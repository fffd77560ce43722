"""Split a map into its sun and the rest, to tell a missed sun from a bias.

A hemisphere estimator hits a sun of solid angle Ω with probability about
Ω · p(ω) per sample; over N samples of a pixel it expects N·Ω·p hits, and
below one hit its mean lacks the sun's share with high probability although
the estimator is unbiased. Rendering is linear in the map, so

    image(map) = image(map without sun) + image(sun alone),

and an estimator that agrees with the reference on the sunless map and
misses only a sun it is expected to hit only a few times is limited by its
sample count, not biased (the failures group of ``mcillum validate`` uses this:
validation/stages/cases.py, ``split_sun``).

"Sun" texels: luminance above ``SUN_FACTOR`` × the map's solid-angle-weighted
mean luminance. They are set to zero in the sunless map.
"""

from __future__ import annotations

import os

import numpy as np

from . import catalog, procedural, safety

SUN_FACTOR = 100.0
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
    st = os.stat(path)
    key = {"name": "sunless", "source": os.path.abspath(path), "size": st.st_size,
           "mtime": st.st_mtime, "factor": factor}
    return catalog.cached(key, lambda: sunless,
                          (split, procedural.cell_solid_angles, safety.sanitise)), facts

