"""The pieces of the report's HTML: images as data URIs (renders as AVIF where
that keeps their noise, error maps exact on a stepped colour scale),
the worst region, numbers, swatches, outcomes."""

from __future__ import annotations

import base64
import html
import io
import re
from dataclasses import dataclass

import matplotlib
import numpy as np
from PIL import Image

ERROR_CMAP = "magma"
# Steps of a map's colour scale: its pixels are exactly these colours, and its
# colour bar shows them. A relative-error map is noise from pixel to pixel,
# which hides the steps: 16 (5 a decade) look as 256 do, in 0.4× the bytes.
# A FLIP map is smooth: 48 keep its faint features (FLIP below 0.03).
ERROR_LEVELS = 16
FLIP_LEVELS = 48
# A tone-mapped render as AVIF: 4:4:4 (one bright pixel keeps its colour),
# tuned for SSIM (the default tuning smooths noise away: 3–8 % of its RMS on
# 256² renders at quality 80), at the lowest of these qualities that keeps the
# render's pixel-scale detail (its noise) within DETAIL_TOLERANCE; faint noise
# (a few 8-bit levels) needs 90 or 95. Else, or where smaller, exact.
RENDER_AVIF = {"format": "avif", "subsampling": "4:4:4", "speed": 6, "codec": "aom",
               "advanced": {"tune": "ssim"}}
RENDER_QUALITIES = (60, 70, 80, 90, 95)
DETAIL_TOLERANCE = 0.05
MIN_SIDE = 160          # small images are shown (pixelated) at least this wide


@dataclass(frozen=True)
class Picture:
    """An encoded image: its data URI and its size in pixels."""
    uri: str
    height: int
    width: int


def _encoded(image: Image.Image, **options) -> bytes:
    buf = io.BytesIO()
    image.save(buf, **options)
    return buf.getvalue()


def _picture(image: Image.Image, candidates: list[dict]) -> Picture:
    """The smallest of ``candidates`` (Pillow save options) as a Picture."""
    data, fmt = min(((_encoded(image, **c), c["format"]) for c in candidates),
                    key=lambda e: len(e[0]))
    return Picture(f"data:image/{fmt};base64,{base64.b64encode(data).decode()}",
                   image.height, image.width)


def _usable(options: dict) -> bool:
    """Whether this Pillow encodes with ``options`` (WebP and AVIF are
    optional in Pillow; AVIF's codec options need libaom)."""
    try:
        _encoded(Image.new("RGB", (8, 8)), **options)
        return True
    except (KeyError, OSError, ValueError):   # no such format, codec or option
        return False


_LOSSLESS = [o for o in ({"format": "png", "optimize": True},
                         {"format": "webp", "lossless": True}) if _usable(o)]
_AVIF = _usable(dict(RENDER_AVIF, quality=RENDER_QUALITIES[0]))


def detail(rgb8: np.ndarray) -> float:
    """RMS of the image's Laplacian: its pixel-scale detail, noise included."""
    a = np.asarray(rgb8, np.float64)
    lap = 4 * a[1:-1, 1:-1] - a[:-2, 1:-1] - a[2:, 1:-1] - a[1:-1, :-2] - a[1:-1, 2:]
    return float(np.sqrt(np.mean(lap ** 2))) if lap.size else 0.0


def render(rgb8: np.ndarray) -> Picture:
    """A tone-mapped 8-bit RGB image: AVIF at the lowest quality of
    RENDER_QUALITIES that keeps its :func:`detail`, or exact (PNG or lossless
    WebP) where that is smaller or no quality keeps it."""
    rgb8 = np.ascontiguousarray(rgb8[..., :3])
    image = Image.fromarray(rgb8, "RGB")
    exact = _picture(image, _LOSSLESS)
    wanted = detail(rgb8)
    for quality in RENDER_QUALITIES if _AVIF else ():
        lossy = _picture(image, [dict(RENDER_AVIF, quality=quality)])
        if len(lossy.uri) >= len(exact.uri):
            break
        if abs(detail(decoded(lossy)) - wanted) <= DETAIL_TOLERANCE * wanted:
            return lossy
    return exact


def decoded(picture: Picture) -> np.ndarray:
    """The RGB pixels of ``picture`` (8-bit), as a browser would show them."""
    data = base64.b64decode(picture.uri.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def map_colours(levels: int) -> matplotlib.colors.Colormap:
    """The colour scale of a map in ``levels`` steps (ERROR_LEVELS, FLIP_LEVELS)."""
    return matplotlib.colormaps[ERROR_CMAP].resampled(levels)


def steps(level: np.ndarray, levels: int) -> np.ndarray:
    """Values in [0, 1] (NaN as 0) as the index of their step on
    :func:`map_colours` (uint8): the step matplotlib would pick for them."""
    level = np.nan_to_num(np.asarray(level, np.float64), nan=0.0)
    return np.clip((level * levels).astype(np.int64), 0, levels - 1).astype(np.uint8)


def _level_map(level: np.ndarray, levels: int) -> Picture:
    """Values in [0, 1] (NaN as 0) on :func:`map_colours` as an exact palette
    image (PNG or lossless WebP): each pixel the colour matplotlib would pick."""
    image = Image.fromarray(steps(level, levels), "P")
    image.putpalette(map_colours(levels)(np.arange(levels), bytes=True)[:, :3].ravel())
    return _picture(image, _LOSSLESS)


def error_map(err: np.ndarray, vmin: float, vmax: float) -> Picture:
    """A relative-error map on the logarithmic scale [vmin, vmax] (clipped)."""
    norm = matplotlib.colors.LogNorm(vmin=vmin, vmax=vmax, clip=True)
    return _level_map(np.ma.filled(norm(np.maximum(err, vmin)), 0.0), ERROR_LEVELS)


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


def img(picture: Picture, caption: str, side: int = MIN_SIDE) -> str:
    """A figure of ``picture`` at least ``side`` pixels wide on screen: each
    pixel shown as a whole number of screen pixels (CSS: pixelated)."""
    zoom = max(1, int(np.ceil(side / max(picture.height, picture.width))))
    alt = html.escape(re.sub(r"<[^>]+>", " ", caption))
    return (f'<figure><img src="{picture.uri}" alt="{alt}" width="{picture.width * zoom}" '
            f'height="{picture.height * zoom}"><figcaption>{caption}</figcaption></figure>')


OUTCOME_CLASS = {"pass": "ok", "inconclusive": "warn", "fail": "bad"}


def outcome(outcome: str, why: str = "") -> str:
    """A check's outcome as a coloured word, its reason on hover."""
    title = f' title="{html.escape(why, quote=True)}"' if why else ""
    word = "FAIL" if outcome == "fail" else outcome
    return f"<span class={OUTCOME_CLASS.get(outcome, '')}{title}>{word}</span>"
