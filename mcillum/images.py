"""Images for people: tone mapping and PNG previews (EXR files: mcillum.files)."""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from mcillum import files


#: The brightest a reference's median pixel is shown (linear; sRGB 0.74).
#: On a flat image (cap_plane's disk fills its frame) the 99th percentile
#: is the median, and mapping it to 1 showed every render white, its noise
#: above the mean clipped away.
MEDIAN_AT_MOST = 0.5


def exposure_for(reference: np.ndarray) -> float:
    """EV in half stops: the one that maps the reference's 99th percentile to
    1, or, where that shows its median brighter than MEDIAN_AT_MOST, the
    largest that does not (0 for a black reference)."""
    x = reference[..., :3]
    p, median = float(np.percentile(x, 99)), float(np.median(x))
    if p <= 0:
        return 0.0
    ev = float(np.round(-np.log2(p) * 2) / 2)
    if median > 0:
        ev = min(ev, float(np.floor(np.log2(MEDIAN_AT_MOST / median) * 2) / 2))
    return ev


def tonemap(image: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance → 8-bit sRGB: clip(2^exposure · x, 0, 1), sRGB curve.

    Non-finite values map to 0 (they must not occur; statistics count them).
    """
    x = np.nan_to_num(np.asarray(image, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.clip(x * 2.0 ** exposure, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    if srgb.ndim == 3 and srgb.shape[2] == 1:
        srgb = np.repeat(srgb, 3, axis=2)
    return np.round(srgb[..., :3] * 255).astype(np.uint8)


def write_png(path, image: np.ndarray, exposure: float = 0.0) -> None:
    """Write the :func:`tonemap` of ``image`` as PNG, atomically."""
    bitmap = mi.Bitmap(np.ascontiguousarray(tonemap(image, exposure)),
                       mi.Bitmap.PixelFormat.RGB)
    with files.atomic_path(path) as tmp:
        bitmap.write(tmp)
