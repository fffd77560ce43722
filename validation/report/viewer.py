"""The report's image viewer: a scene's renders as the data they are.

Each render reaches the page as half floats (IEEE binary16, the nearest to
the float32 EXR: values beyond ±65504 are clamped there), stored by channel
planes, low bytes then high bytes, and deflated (zlib). The planes are G, then R and B as their difference
from G in binary16's bit patterns (mod 2^16: exact, and for positive values
the ratio to G in steps of 2^-10): a path tracer's channels share their
paths, so their noise moves together and the differences are smaller. The
high bytes (sign, exponent, top of the mantissa) are what repeats, and
splitting them from the noisy low bytes is what lets deflate find it. A
noisy render's low bytes are close to incompressible: these steps bring it
near its entropy (about 10 bits a value). The deflated bytes are then
written 7 bits to a character (:func:`pack_text`) in an element of their own:
a character per 7 bits where base64 needs one per 6. The browser inflates
them with its own ``DecompressionStream``; no network, no library.

The page's script (:data:`SCRIPT`, one for every viewer) shows one image of a
scene at a time on a canvas, at one zoom and pan for all of them, and lets a
reader flip between them (number keys or clicks), change the exposure of the
HDR data, switch to the relative-error or FLIP map, and read every image's
value under the pointer. Tone mapping is the page's: x · 2^EV, clipped, sRGB,
with a half-level dither before the 8-bit quantisation, so that a flat
render shows no contour that its data does not have.
"""

from __future__ import annotations

import html
import importlib.resources
import json
import zlib
from dataclasses import dataclass

import numpy as np

from mcillum import images

from ..stats import metrics
from .parts import ERROR_LEVELS, FLIP_LEVELS, img, map_colours, render, steps

HALF_MAX = 65504.0              # the largest finite binary16
VIEW_SIDE = 512                 # the viewer's canvas on screen, CSS pixels


@dataclass(frozen=True)
class Test:
    """An estimator's per-pixel unbiasedness test on the statistics film (a
    coarser film of the same camera): the smallest p over channels per
    pixel (NaN: not tested) and the level a pixel is rejected below."""
    p: np.ndarray
    alpha_pixel: float


@dataclass(frozen=True)
class Shown:
    """One image of a viewer: its label (a button), a caption, its pixels
    (H, W, ≥3 linear RGB), its FLIP map against the reference (H, W) in
    [0, 1] or None, and its per-pixel :class:`Test` or None."""
    label: str
    caption: str
    pixels: np.ndarray
    flip: np.ndarray | None = None
    test: Test | None = None


#: −log10 p in steps of 0.1 as a byte; 255: not tested.
P_STEP, P_NONE = 0.1, 255


def pack_test(p: np.ndarray) -> bytes:
    """Per-pixel p-values (H, W) as deflated bytes of round(−log10 p / 0.1),
    at most 254 (p below 1e-25.4 reads as that); NaN as :data:`P_NONE`."""
    p = np.asarray(p, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.round(-np.log10(np.clip(p, 1e-300, 1.0)) / P_STEP)
    q = np.where(np.isfinite(p), np.minimum(q, P_NONE - 1), P_NONE)
    return zlib.compress(q.astype(np.uint8).tobytes(), 9)


def _planes(u16: np.ndarray) -> bytes:
    """uint16 values (C, H, W) as their low bytes, then their high bytes."""
    flat = u16.ravel()
    return (flat & 0xFF).astype(np.uint8).tobytes() + (flat >> 8).astype(np.uint8).tobytes()


# Seven-bit values a <script> element's text cannot carry as they are: NUL
# (the parser replaces it), CR (it becomes LF) and "<" (it could close the
# element). Each is written as one character of U+0100–U+017F (two bytes of
# UTF-8) together with the seven bits that follow it, so every byte of the
# page still carries seven bits.
UNSAFE = (0, 13, 60)
ESCAPE = 0x100


def pack_text(data: bytes) -> str:
    """``data`` as text for a <script type="application/octet-stream">: its
    bits, zero-padded to a multiple of 7, seven to a character (see
    :data:`UNSAFE`). :func:`unpack_text` needs ``len(data)`` back."""
    bits = np.unpackbits(np.frombuffer(data, np.uint8))
    bits = np.concatenate([bits, np.zeros(-bits.size % 7 + 7, np.uint8)])  # (+ 7: a spare)
    values = bits.reshape(-1, 7) @ (1 << np.arange(6, -1, -1))
    codes = values.copy()
    taken = np.zeros(values.size, bool)          # absorbed by the escape before it
    for k in np.flatnonzero(np.isin(values[:-1], UNSAFE)):   # (not the spare)
        if not taken[k]:
            codes[k] = ESCAPE + (UNSAFE.index(int(values[k])) << 7) + values[k + 1]
            taken[k + 1] = True
    return "".join(map(chr, codes[~taken][:-1] if not taken[-1] else codes[~taken]))


def unpack_text(text: str, size: int) -> bytes:
    """The inverse of :func:`pack_text`: the first ``size`` bytes. Raises
    ValueError where ``text`` holds fewer."""
    values = []
    for c in map(ord, text):
        if c < 128:
            values.append(c)
        else:
            values += [UNSAFE[(c - ESCAPE) >> 7], c & 127]
    bits = ((np.array(values, np.int64)[:, None] >> np.arange(6, -1, -1)) & 1).astype(np.uint8)
    data = np.packbits(bits.ravel())
    if data.size < size:
        raise ValueError(f"the text holds {data.size} bytes, not {size}")
    return data[:size].tobytes()


def _blob(data: bytes) -> str:
    return (f'<script type="application/octet-stream" class=vbin data-n={len(data)}>'
            f"{pack_text(data)}</script>")


def pack_half(image: np.ndarray) -> bytes:
    """The RGB of ``image`` (H, W, ≥3) as the deflated binary16
    planes (R − G, G, B − G as bit patterns mod 2^16; each row-major, top
    row first). NaN becomes 0 and ±∞ or anything beyond ±HALF_MAX becomes
    ±HALF_MAX (a render has neither: the statistics count them)."""
    rgb = np.nan_to_num(np.asarray(image, np.float32)[..., :3], nan=0.0,
                        posinf=HALF_MAX, neginf=-HALF_MAX)
    half = np.clip(rgb, -HALF_MAX, HALF_MAX).astype(np.float16)
    planes = np.ascontiguousarray(half.transpose(2, 0, 1)).view(np.uint16).copy()
    planes[[0, 2]] -= planes[1]                  # (uint16: wraps, mod 2^16)
    return zlib.compress(_planes(planes), 9)


def unpack_half(packed: bytes, height: int, width: int) -> np.ndarray:
    """The inverse of :func:`pack_half`: (H, W, 3) float32. Raises
    ValueError if ``packed`` does not hold H·W·3 half floats."""
    data = np.frombuffer(zlib.decompress(packed), np.uint8)
    n = height * width * 3
    if data.size != 2 * n:
        raise ValueError(f"expected {2 * n} bytes of half floats, got {data.size}")
    u16 = (data[:n].astype(np.uint16) | (data[n:].astype(np.uint16) << 8)).reshape(3, -1)
    u16[[0, 2]] += u16[1]
    return u16.view(np.float16).astype(np.float32).reshape(3, height, width).transpose(1, 2, 0)


def pack_levels(level: np.ndarray, levels: int = FLIP_LEVELS) -> bytes:
    """A map in [0, 1] (H, W; NaN as 0) as its deflated step indices
    (:func:`.parts.steps`): the colour step each pixel is shown in. Half the
    bytes of 8-bit levels, and a reader reads a step, not a value, off a map."""
    return zlib.compress(steps(level, levels).tobytes(), 9)


def _palette(levels: int) -> list[str]:
    return ["#%02x%02x%02x" % tuple(c[:3]) for c in
            map_colours(levels)(np.arange(levels), bytes=True)]


def packed(shown: list[Shown]) -> list[bytes]:
    """Each image's data, then its FLIP map and its test where it has them,
    in that order: what :func:`viewer` writes for ``shown``."""
    return [b for s in shown for b in
            [pack_half(s.pixels)] + ([] if s.flip is None else [pack_levels(s.flip)])
            + ([] if s.test is None else [pack_test(s.test.p)])]


def text_bytes(blobs: list[bytes]) -> int:
    """The bytes (UTF-8) that ``blobs`` take on the page (:func:`pack_text`)."""
    return sum(-(-8 * len(b) // 7) for b in blobs)


def window(height: int, width: int, worst: tuple[int, int, int] | None,
           share: float) -> tuple[int, int, int]:
    """(y, x, side) of the square about ``share`` of the film's pixels,
    centred on the worst region (else the film's centre), inside the film."""
    side = max(1, min(height, width, int(np.sqrt(share * height * width))))
    cy, cx = ((worst[0] + worst[2] / 2, worst[1] + worst[2] / 2) if worst
              else (height / 2, width / 2))
    y = int(np.clip(round(cy - side / 2), 0, height - side))
    x = int(np.clip(round(cx - side / 2), 0, width - side))
    return y, x, side


def viewer(anchor: str, shown: list[Shown], exposure: float,
           error_scale: tuple[float, float], worst: tuple[int, int, int] | None = None,
           max_bytes: int | None = None, blobs: list[bytes] | None = None) -> str:
    """The HTML of one viewer: ``shown[0]`` is the reference; ``exposure``
    the starting EV; ``error_scale`` (vmin, vmax) the relative-error map's
    logarithmic scale, shared with the page's colour bar; ``worst`` (y, x,
    size) a region the key w zooms to. Where the data of the whole film
    would exceed ``max_bytes``, the viewer holds the square window about
    the worst region that fits, every pixel of it exact, and the page shows
    the whole film beside it as a picture. ``blobs``: :func:`packed` of
    ``shown`` where the caller has it. Raises ValueError if the images
    differ in size."""
    h, w = shown[0].pixels.shape[:2]
    if any(s.pixels.shape[:2] != (h, w) for s in shown):
        raise ValueError("a viewer's images must share one size")
    blobs = packed(shown) if blobs is None else blobs
    whole, origin, full = shown, (0, 0), text_bytes(blobs)
    if max_bytes is not None and full > max_bytes:
        # bytes go with pixels; 0.95: room for what the window's content adds
        y0, x0, side = window(h, w, worst, 0.95 * max_bytes / full)
        cut = lambda a: None if a is None else a[y0:y0 + side, x0:x0 + side]  # noqa: E731
        shown = [Shown(s.label, s.caption, cut(s.pixels), cut(s.flip), s.test) for s in shown]
        blobs = packed(shown)
        origin, h, w = (x0, y0), side, side
        if worst:
            worst = (worst[0] - y0, worst[1] - x0, worst[2])
    spec = {"w": w, "h": h, "ev": exposure, "eps": metrics.EPSILON, "worst": worst,
            "origin": origin, "film": [whole[0].pixels.shape[1], whole[0].pixels.shape[0]],
            "errorScale": list(error_scale), "errorPalette": _palette(ERROR_LEVELS),
            "flipPalette": _palette(FLIP_LEVELS),
            "images": [{"label": s.label, "caption": s.caption} for s in shown]}
    data_elements = "".join(map(_blob, blobs))
    for im, s in zip(spec["images"], shown):
        im["flip"] = s.flip is not None
        im["test"] = None if s.test is None else {
            "w": s.test.p.shape[1], "h": s.test.p.shape[0], "alpha": s.test.alpha_pixel}
    buttons = "".join(
        f'<button type=button data-i="{i}" title="key {(i + 1) % 10 if i < 10 else ""}">'
        f'<kbd>{(i + 1) % 10 if i < 10 else ""}</kbd> {html.escape(s.label)}</button>'
        for i, s in enumerate(shown))
    # JSON inside <script type=application/json>: "</" must not close the element
    data = json.dumps(spec, separators=(",", ":")).replace("</", "<\\/")
    return f"""<div class=viewer id="{html.escape(anchor)}" tabindex=0>
<div class=vbar>{buttons}</div>
<div class=vbar><label><input type=radio name="{html.escape(anchor)}-mode" value=image checked>
image <kbd>i</kbd></label><label><input type=radio name="{html.escape(anchor)}-mode"
value=error> relative error <kbd>e</kbd></label><label><input type=radio
name="{html.escape(anchor)}-mode" value=flip> FLIP <kbd>f</kbd></label>
<label>EV <input type=range class=ev min=-12 max=12 step=0.5 value="{exposure:g}">
<output class=evtext>{exposure:+.1f}</output></label> <kbd>−</kbd><kbd>+</kbd>
<button type=button class=reset title="or double-click">fit</button>
{'<button type=button class=worst title="key w">worst region <kbd>w</kbd></button>' if worst else ''}</div>
<div class=vmain><div class=vport style="width:{VIEW_SIDE}px;height:{VIEW_SIDE}px">
<canvas width={w} height={h}></canvas></div>
<div class=vside><p class=vcap></p><table class=vpix></table></div></div>
<script type="application/json" class=vdata>{data}</script>{data_elements}
<noscript><p>The viewer needs JavaScript.</p></noscript>
</div>{_whole(whole[0], exposure, origin, h) if shown is not whole else ""}"""


def _whole(reference: Shown, exposure: float, origin: tuple[int, int], side: int) -> str:
    """The whole film of a viewer that holds a window of it: the reference
    as a picture, and where the window lies."""
    fh, fw = reference.pixels.shape[:2]
    x0, y0 = origin
    return (f"<div class=row>{img(render(images.tonemap(reference.pixels, exposure)), 'reference: the whole film', 128)}"
            f"<p class=desc>The viewer holds the {side}×{side} px about the worst region "
            f"(x {x0}–{x0 + side - 1}, y {y0}–{y0 + side - 1}) of the {fw}×{fh} film, every "
            "pixel exact: the whole film of every estimator would pass the page's budget "
            "for image data (report.page.VIEWER_BYTES).</p></div>")


CSS = """
.viewer{border:1px solid #ccc;padding:8px;margin:8px 0;outline:none}
.viewer:focus{border-color:#1f77b4}
.vbar{display:flex;flex-wrap:wrap;gap:6px;align-items:center;margin-bottom:6px;font-size:13px}
.vbar button{font:inherit;padding:2px 6px;border:1px solid #bbb;background:#f7f7f7;border-radius:3px;cursor:pointer}
.vbar button.on{background:#1f77b4;color:#fff;border-color:#1f77b4}
kbd{font:11px monospace;border:1px solid #bbb;border-radius:2px;padding:0 3px;background:#fff;color:#333}
.vmain{display:flex;gap:12px;align-items:flex-start}
.vport{position:relative;overflow:hidden;background:#333;cursor:crosshair;flex:none}
.vport canvas{position:absolute;left:0;top:0;transform-origin:0 0;image-rendering:pixelated}
.vside{font-size:12px;min-width:300px} .vside table{font-size:12px;margin:4px 0}
.vside td{padding:1px 6px;font-variant-numeric:tabular-nums;white-space:nowrap} .vside tr.on{background:#e8f1fa;font-weight:bold}
.vcap{margin:0 0 4px}
"""

# The viewers' script (viewer.js beside this file, package data): plain
# ES2018, no library; one for every viewer of a page.
SCRIPT = importlib.resources.files(__package__).joinpath("viewer.js").read_text("utf-8")
