"""Image files: float32 OpenEXR with metadata, and tone-mapped PNG previews.

Every write goes to a temporary file in the target directory and is renamed
into place, so a reader never sees a partial file.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager

import numpy as np

#: Prefix of the custom EXR header attributes mcillum writes.
META_PREFIX = "mcillum."

#: EXR channel group used for an image with this many channels.
_CHANNELS = {1: "Y", 3: "RGB", 4: "RGBA"}


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it there on success."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path)) or "."
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"output directory does not exist: {directory}")
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=".partial-", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp creates 0600
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_exr(path, image: np.ndarray, metadata: dict | None = None) -> None:
    """Write an (H, W, C) image, C in {1, 3, 4}, as float32 EXR.

    ``metadata`` values (str, int or float) are stored as header attributes
    named ``mcillum.<key>``.
    """
    import OpenEXR

    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in _CHANNELS:
        raise ValueError(f"cannot store an image of shape {image.shape} as EXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            value = str(value)
        header[META_PREFIX + key] = value
    channels = {_CHANNELS[image.shape[2]]: np.ascontiguousarray(image)}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(tmp)


def read_exr(path) -> tuple[np.ndarray, dict]:
    """Read an image written by :func:`write_exr`: (H, W, C) float32, metadata."""
    import OpenEXR

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such EXR file: {path}")
    f = OpenEXR.File(path)
    channels = f.channels()
    for name in ("RGBA", "RGB", "Y"):
        if name in channels:
            pixels = np.asarray(channels[name].pixels, dtype=np.float32)
            break
    else:
        raise ValueError(f"{path}: no RGB, RGBA or Y channels (has {sorted(channels)})")
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    meta = {k[len(META_PREFIX):]: v for k, v in f.header().items()
            if k.startswith(META_PREFIX)}
    return pixels, meta


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
    """Write the :func:`tonemap` of ``image`` as PNG (needs a Mitsuba variant)."""
    import mitsuba as mi

    bitmap = mi.Bitmap(np.ascontiguousarray(tonemap(image, exposure)),
                       mi.Bitmap.PixelFormat.RGB)
    with atomic_path(path) as tmp:
        bitmap.write(tmp)
