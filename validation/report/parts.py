"""The pieces of the report's HTML: images as PNG data URIs, error and FLIP
maps on one colour scale, the worst region, numbers, swatches, outcomes."""

from __future__ import annotations

import base64
import html
import io
import re

import matplotlib
import matplotlib.image
import numpy as np

ERROR_CMAP = "magma"
MIN_SIDE = 160          # small renders are enlarged (nearest) to at least this


def png_uri(rgb8: np.ndarray) -> str:
    buf = io.BytesIO()
    matplotlib.image.imsave(buf, rgb8, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def enlarge(a: np.ndarray, side: int = MIN_SIDE) -> np.ndarray:
    k = max(1, int(np.ceil(side / max(a.shape[:2]))))
    return np.repeat(np.repeat(a, k, axis=0), k, axis=1)


def error_rgb(err: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    norm = matplotlib.colors.LogNorm(vmin=vmin, vmax=vmax, clip=True)
    rgba = matplotlib.colormaps[ERROR_CMAP](norm(np.maximum(err, vmin)))
    return (rgba[..., :3] * 255).astype(np.uint8)


def flip_rgb(flip: np.ndarray) -> np.ndarray:
    """A FLIP map in [0, 1] on the linear magma scale (FLIP's own)."""
    rgba = matplotlib.colormaps[ERROR_CMAP](np.clip(flip, 0.0, 1.0))
    return (rgba[..., :3] * 255).astype(np.uint8)


def worst_window(errors: list[np.ndarray]) -> tuple[int, int, int]:
    """(y, x, size) of the square window, a quarter of the image wide, with the
    highest summed relative error over all estimators."""
    total = np.sum(errors, axis=0)
    h, w = total.shape
    size = max(2, min(h, w) // 4)
    c = np.pad(total, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    sums = c[size:, size:] - c[:-size, size:] - c[size:, :-size] + c[:-size, :-size]
    y, x = np.unravel_index(np.argmax(sums), sums.shape)
    return int(y), int(x), size


def fmt(x, spec=".3g"):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def swatch(name: str, colours: dict) -> str:
    return (f"<span class=sw style='background:{colours.get(name, '#777')}'></span>"
            f"{html.escape(name)}")


def img(rgb8: np.ndarray, caption: str, side: int = MIN_SIDE) -> str:
    """A figure of an 8-bit image at least ``side`` pixels wide on screen:
    large images as they are (zoomed by CSS), small ones enlarged first."""
    h, w = rgb8.shape[:2]
    if max(h, w) < 64:                      # thumbnails: enlarge the pixels themselves
        rgb8 = enlarge(rgb8, side)
        h, w = rgb8.shape[:2]
    zoom = max(1, int(np.ceil(side / max(h, w))))
    alt = html.escape(re.sub(r"<[^>]+>", " ", caption))
    return (f'<figure><img src="{png_uri(rgb8)}" alt="{alt}" '
            f'width="{w * zoom}" height="{h * zoom}"><figcaption>{caption}</figcaption></figure>')


OUTCOME_CLASS = {"pass": "ok", "inconclusive": "warn", "fail": "bad"}


def outcome(outcome: str, why: str = "") -> str:
    """A check's outcome as a coloured word, its reason on hover."""
    title = f' title="{html.escape(why, quote=True)}"' if why else ""
    word = "FAIL" if outcome == "fail" else outcome
    return f"<span class={OUTCOME_CLASS.get(outcome, '')}{title}>{word}</span>"
