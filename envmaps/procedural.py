"""Deterministic procedural environment maps (float32 RGB, Mitsuba latlong).

Each generator returns an ``(height, width, 3)`` float32 array; :func:`write`
stores it as an OpenEXR file that Mitsuba's ``envmap`` emitter reads.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np


def directions(width: int, height: int) -> np.ndarray:
    """Unit direction at each pixel centre, shape (height, width, 3), y up."""
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi, theta = np.meshgrid(phi, theta)
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta),
                     -np.cos(phi) * np.sin(theta)], axis=-1)


def constant(radiance=1.0, width: int = 8, height: int = 4) -> np.ndarray:
    """Uniform radiance L everywhere (a furnace).

    Irradiance on any plane: E = π·L; a convex diffuse object of albedo ρ has
    exitant radiance ρ·L everywhere.
    """
    rgb = np.broadcast_to(np.asarray(radiance, np.float32), (3,))
    return np.broadcast_to(rgb, (height, width, 3)).astype(np.float32)


def gradient(zenith=(0.25, 0.45, 1.0), horizon=(1.0, 0.95, 0.85),
             ground=(0.2, 0.17, 0.15), width: int = 128, height: int = 64) -> np.ndarray:
    """Smooth sky: ``horizon`` at the horizon blending to ``zenith`` straight up
    as L(θ) = zenith·cosθ + horizon·(1 − cosθ) for y = cosθ > 0, and a uniform
    ``ground`` below the horizon. Low frequency everywhere (no sun).

    Irradiance on an upward-facing plane, ∫ L cosθ dω over the upper
    hemisphere: E = 2π (zenith/3 + horizon/6).
    """
    y = directions(width, height)[..., 1:2]
    z, h, g = (np.asarray(c, np.float64) for c in (zenith, horizon, ground))
    sky = z * y + h * (1 - y)
    return np.where(y > 0, sky, g).astype(np.float32)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write(path: str | os.PathLike, rgb: np.ndarray) -> str:
    """Write ``rgb`` (H, W, 3) as a float32 OpenEXR file, atomically."""
    import OpenEXR

    path = os.fspath(path)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) array, got shape {rgb.shape}")
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(suffix=".exr", dir=directory)
    os.close(fd)
    try:
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, {"RGB": rgb}).write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    return path
