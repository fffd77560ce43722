"""Images for people: tone mapping and PNG previews (EXR files: mcillum.files)."""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from mcillum import files


def exposure_for(reference: np.ndarray) -> float:
    """EV (in half stops) that maps the reference's 99th percentile to 1."""
    p = float(np.percentile(reference[..., :3], 99))
    return 0.0 if p <= 0 else float(np.round(-np.log2(p) * 2) / 2)


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
