"""The report's image viewer: a scene's renders as the data they are.

Each render reaches the page as half floats (IEEE binary16, the nearest to
the float32 EXR: values beyond ±65504 are clamped there), stored by channel
planes, low bytes then high bytes, deflated (zlib) and base64-encoded: the
high bytes (sign, exponent, top of the mantissa) are what repeats, and
splitting them from the noisy low bytes is what lets deflate find it. The
browser inflates them with its own ``DecompressionStream``; no network, no
library.

The page's script (:data:`SCRIPT`, one for every viewer) shows one image of a
scene at a time on a canvas, at one zoom and pan for all of them, and lets a
reader flip between them (number keys or clicks), change the exposure of the
HDR data, switch to the relative-error or FLIP map, and read every image's
value under the pointer. Tone mapping is the page's: x · 2^EV, clipped, sRGB,
with a half-level dither before the 8-bit quantisation, so that a flat
render shows no contour that its data does not have.
"""

from __future__ import annotations

import base64
import html
import json
import zlib
from dataclasses import dataclass

import numpy as np

from ..stats import metrics
from .parts import ERROR_LEVELS, FLIP_LEVELS, map_colours

HALF_MAX = 65504.0              # the largest finite binary16
VIEW_SIDE = 512                 # the viewer's canvas on screen, CSS pixels


@dataclass(frozen=True)
class Shown:
    """One image of a viewer: its label (a button), a caption, its pixels
    (H, W, ≥3 linear RGB) and its FLIP map against the reference (H, W) in
    [0, 1], or None."""
    label: str
    caption: str
    pixels: np.ndarray
    flip: np.ndarray | None = None


def _planes(u16: np.ndarray) -> bytes:
    """uint16 values (C, H, W) as their low bytes, then their high bytes."""
    flat = u16.ravel()
    return (flat & 0xFF).astype(np.uint8).tobytes() + (flat >> 8).astype(np.uint8).tobytes()


def pack_half(image: np.ndarray) -> str:
    """The RGB of ``image`` (H, W, ≥3) as base64 of the deflated binary16
    planes (R, G, B; each row-major, top row first). NaN becomes 0 and ±∞
    or anything beyond ±HALF_MAX becomes ±HALF_MAX (a render has neither:
    the statistics count them)."""
    rgb = np.nan_to_num(np.asarray(image, np.float32)[..., :3], nan=0.0,
                        posinf=HALF_MAX, neginf=-HALF_MAX)
    half = np.clip(rgb, -HALF_MAX, HALF_MAX).astype(np.float16)
    planes = np.ascontiguousarray(half.transpose(2, 0, 1)).view(np.uint16)
    return base64.b64encode(zlib.compress(_planes(planes), 9)).decode()


def unpack_half(text: str, height: int, width: int) -> np.ndarray:
    """The inverse of :func:`pack_half`: (H, W, 3) float32. Raises
    ValueError if ``text`` does not hold H·W·3 half floats."""
    data = np.frombuffer(zlib.decompress(base64.b64decode(text)), np.uint8)
    n = height * width * 3
    if data.size != 2 * n:
        raise ValueError(f"expected {2 * n} bytes of half floats, got {data.size}")
    u16 = data[:n].astype(np.uint16) | (data[n:].astype(np.uint16) << 8)
    return u16.view(np.float16).astype(np.float32).reshape(3, height, width).transpose(1, 2, 0)


def pack_levels(level: np.ndarray) -> str:
    """A map in [0, 1] (H, W; NaN as 0) as base64 of deflated 8-bit levels
    (round(255·level)): finer than the FLIP_LEVELS steps it is shown in."""
    q = np.round(np.clip(np.nan_to_num(np.asarray(level, np.float64)), 0, 1) * 255)
    return base64.b64encode(zlib.compress(q.astype(np.uint8).tobytes(), 9)).decode()


def _palette(levels: int) -> list[str]:
    return ["#%02x%02x%02x" % tuple(c[:3]) for c in
            map_colours(levels)(np.arange(levels), bytes=True)]


def viewer(anchor: str, shown: list[Shown], exposure: float,
           error_scale: tuple[float, float]) -> str:
    """The HTML of one viewer: ``shown[0]`` is the reference; ``exposure``
    the starting EV; ``error_scale`` (vmin, vmax) the relative-error map's
    logarithmic scale, shared with the page's colour bar. Raises ValueError
    if the images differ in size."""
    h, w = shown[0].pixels.shape[:2]
    if any(s.pixels.shape[:2] != (h, w) for s in shown):
        raise ValueError("a viewer's images must share one size")
    spec = {"w": w, "h": h, "ev": exposure, "eps": metrics.EPSILON,
            "errorScale": list(error_scale), "errorPalette": _palette(ERROR_LEVELS),
            "flipPalette": _palette(FLIP_LEVELS),
            "images": [{"label": s.label, "caption": s.caption, "data": pack_half(s.pixels),
                        "flip": None if s.flip is None else pack_levels(s.flip)}
                       for s in shown]}
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
<button type=button class=reset title="key 0 on the keypad or double-click">fit</button></div>
<div class=vmain><div class=vport style="width:{VIEW_SIDE}px;height:{VIEW_SIDE}px">
<canvas width={w} height={h}></canvas></div>
<div class=vside><p class=vcap></p><table class=vpix></table></div></div>
<script type="application/json" class=vdata>{data}</script>
<noscript><p>The viewer needs JavaScript; the worst region below is a static picture.</p></noscript>
</div>"""


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
.vside td{padding:1px 6px;font-variant-numeric:tabular-nums} .vside tr.on{background:#e8f1fa;font-weight:bold}
.vcap{margin:0 0 4px}
"""

# The viewers' script: plain ES2018, no library. Each .viewer holds its data
# (the JSON above); the script decodes it once, then draws on demand.
SCRIPT = r"""
(() => {
  // binary16 → float32 for every bit pattern, once.
  const HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const e = (h >> 10) & 31, m = h & 1023;
    const v = e === 0 ? m * 2 ** -24 : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * 2 ** (e - 15);
    HALF[h] = h & 0x8000 ? -v : v;
  }
  async function inflate(b64) {
    const bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }
  // Planes R, G, B of low bytes then high bytes → interleaved RGB float32.
  async function halves(b64, n) {
    const b = await inflate(b64), out = new Float32Array(3 * n), all = 3 * n;
    for (let c = 0; c < 3; c++)
      for (let i = 0; i < n; i++) {
        const k = c * n + i;
        out[3 * i + c] = HALF[b[k] | (b[all + k] << 8)];
      }
    return out;
  }
  const srgb = x => x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055;
  // A fixed dither in [0, 1) per pixel: breaks 8-bit contours, same on every redraw.
  const dither = (x, y) => { let h = Math.imul(x * 73856093 ^ y * 19349663, 0x5bd1e995); h ^= h >>> 15; return (h >>> 8) / 16777216; };
  const hex = s => [1, 3, 5].map(i => parseInt(s.slice(i, i + 2), 16));
  const fmt = v => !isFinite(v) ? String(v) : Math.abs(v) >= 1e5 || (v !== 0 && Math.abs(v) < 1e-4) ? v.toExponential(4) : v.toPrecision(5);

  async function setUp(root) {
    const spec = JSON.parse(root.querySelector(".vdata").textContent);
    const n = spec.w * spec.h, canvas = root.querySelector("canvas"), port = root.querySelector(".vport");
    const ctx = canvas.getContext("2d"), pixels = ctx.createImageData(spec.w, spec.h);
    const images = await Promise.all(spec.images.map(im => halves(im.data, n)));
    const flips = await Promise.all(spec.images.map(im => im.flip ? inflate(im.flip) : null));
    const errPal = spec.errorPalette.map(hex), flipPal = spec.flipPalette.map(hex);
    const [vmin, vmax] = spec.errorScale, ref = images[0];
    const state = { i: 0, mode: "image", ev: spec.ev, zoom: 1, x: 0, y: 0, hover: null };
    const rel = (im, p) => { let s = 0; for (let c = 0; c < 3; c++) s += Math.abs(im[3 * p + c] - ref[3 * p + c]) / (Math.abs(ref[3 * p + c]) + spec.eps); return s / 3; };

    function draw() {
      const im = images[state.i], out = pixels.data, gain = 2 ** state.ev, fl = flips[state.i];
      for (let y = 0, p = 0; y < spec.h; y++)
        for (let x = 0; x < spec.w; x++, p++) {
          let rgb;
          if (state.mode === "error") {
            const e = rel(im, p), t = e <= vmin ? 0 : Math.min(1, Math.log(e / vmin) / Math.log(vmax / vmin));
            rgb = errPal[Math.min(errPal.length - 1, Math.floor(t * errPal.length))];
          } else if (state.mode === "flip") {
            rgb = fl ? flipPal[Math.min(flipPal.length - 1, Math.floor(fl[p] / 255 * flipPal.length))] : [40, 40, 40];
          } else {
            const d = dither(x, y);
            rgb = [0, 1, 2].map(c => { const v = im[3 * p + c] * gain; return Math.floor(255 * srgb(v > 0 ? Math.min(v, 1) : 0) + d); });
          }
          out[4 * p] = rgb[0]; out[4 * p + 1] = rgb[1]; out[4 * p + 2] = rgb[2]; out[4 * p + 3] = 255;
        }
      ctx.putImageData(pixels, 0, 0);
      root.querySelectorAll(".vbar button[data-i]").forEach(b => b.classList.toggle("on", +b.dataset.i === state.i));
      root.querySelector(".vcap").innerHTML = spec.images[state.i].caption;
      root.querySelector(`input[value=${state.mode}]`).checked = true;
      root.querySelector(".ev").value = state.ev;
      root.querySelector(".evtext").value = (state.ev >= 0 ? "+" : "") + state.ev.toFixed(1);
      place(); readout();
    }
    function place() {
      canvas.style.transform = `translate(${state.x}px,${state.y}px) scale(${state.zoom})`;
    }
    function fit() {
      state.zoom = Math.max(1, Math.floor(port.clientWidth / Math.max(spec.w, spec.h)));
      state.x = (port.clientWidth - spec.w * state.zoom) / 2; state.y = (port.clientHeight - spec.h * state.zoom) / 2;
      place();
    }
    function readout() {
      const t = root.querySelector(".vpix"), h = state.hover;
      if (!h) { t.innerHTML = "<tr><td>point at a pixel to read every image's value there</td></tr>"; return; }
      const p = h.y * spec.w + h.x;
      let rows = `<tr><th colspan=5>pixel x=${h.x}, y=${h.y}</th></tr><tr><th></th><th>R</th><th>G</th><th>B</th><th>rel. error · FLIP</th></tr>`;
      images.forEach((im, k) => {
        const f = flips[k] ? (flips[k][p] / 255).toFixed(3) : "—";
        rows += `<tr class="${k === state.i ? "on" : ""}" data-k="${k}"><td>${spec.images[k].label}</td>` +
          [0, 1, 2].map(c => `<td class=v>${fmt(im[3 * p + c])}</td>`).join("") +
          `<td>${k ? rel(im, p).toPrecision(3) : "—"} · ${f}</td></tr>`;
      });
      t.innerHTML = rows;
    }
    const show = i => { if (i >= 0 && i < images.length) { state.i = i; draw(); } };
    root.querySelectorAll(".vbar button[data-i]").forEach(b => b.addEventListener("click", () => show(+b.dataset.i)));
    root.querySelectorAll("input[type=radio]").forEach(r => r.addEventListener("change", () => { state.mode = r.value; draw(); }));
    root.querySelector(".ev").addEventListener("input", e => { state.ev = +e.target.value; draw(); });
    root.querySelector(".reset").addEventListener("click", fit);
    root.addEventListener("keydown", e => {
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      const k = e.key;
      if (/^[0-9]$/.test(k)) show((+k + 9) % 10);
      else if (k === "i" || k === "e" || k === "f") { state.mode = { i: "image", e: "error", f: "flip" }[k]; draw(); }
      else if (k === "+" || k === "=") { state.ev = Math.min(12, state.ev + 0.5); draw(); }
      else if (k === "-") { state.ev = Math.max(-12, state.ev - 0.5); draw(); }
      else if (k === "ArrowRight" || k === "ArrowDown") show((state.i + 1) % images.length);
      else if (k === "ArrowLeft" || k === "ArrowUp") show((state.i + images.length - 1) % images.length);
      else return;
      e.preventDefault();
    });
    root.addEventListener("mouseenter", () => root.focus({ preventScroll: true }));
    port.addEventListener("mousemove", e => {
      const r = port.getBoundingClientRect();
      const x = Math.floor((e.clientX - r.left - state.x) / state.zoom), y = Math.floor((e.clientY - r.top - state.y) / state.zoom);
      if (drag) { state.x = drag.x + e.clientX - drag.cx; state.y = drag.y + e.clientY - drag.cy; place(); }
      state.hover = x >= 0 && y >= 0 && x < spec.w && y < spec.h ? { x, y } : null; readout();
    });
    let drag = null;
    port.addEventListener("mousedown", e => { drag = { x: state.x, y: state.y, cx: e.clientX, cy: e.clientY }; e.preventDefault(); });
    window.addEventListener("mouseup", () => { drag = null; });
    port.addEventListener("dblclick", fit);
    port.addEventListener("wheel", e => {
      const r = port.getBoundingClientRect(), mx = e.clientX - r.left, my = e.clientY - r.top;
      const z = Math.max(0.25, Math.min(64, state.zoom * (e.deltaY < 0 ? 2 : 0.5)));
      state.x = mx - (mx - state.x) * z / state.zoom; state.y = my - (my - state.y) * z / state.zoom; state.zoom = z;
      place(); e.preventDefault();
    }, { passive: false });
    // For tests and the curious: this viewer's decoded data and state.
    root.viewer = { images, flips, state, show, draw, spec };
    fit(); draw();
    root.dataset.ready = "1";
  }
  document.querySelectorAll(".viewer").forEach(v => setUp(v).catch(err => {
    v.insertAdjacentHTML("beforeend", `<p class=bad>The viewer could not decode its data: ${err}</p>`);
  }));
})();
"""
