// The report's image viewers (validation/report/viewer.py): plain ES2018, no
// library. Each .viewer holds its data (a JSON spec, then one element per
// blob); this script decodes them once, then draws on demand.
(() => {
  // binary16 → float32 for every bit pattern, once.
  const HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const e = (h >> 10) & 31, m = h & 1023;
    const v = e === 0 ? m * 2 ** -24 : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * 2 ** (e - 15);
    HALF[h] = h & 0x8000 ? -v : v;
  }
  // Seven bits a character; an escape (U+0100–U+017F) carries an unsafe
  // value and the seven bits after it (viewer.pack_text).
  const UNSAFE = [0, 13, 60];
  function bytesOf(el) {
    const text = el.textContent, out = new Uint8Array(+el.dataset.n);
    let acc = 0, held = 0, o = 0;
    const put = v => { acc = (acc << 7) | v; held += 7; if (held >= 8) { held -= 8; if (o < out.length) out[o++] = (acc >> held) & 255; acc &= (1 << held) - 1; } };
    for (let i = 0; i < text.length; i++) {
      const c = text.charCodeAt(i);
      if (c < 128) put(c); else { put(UNSAFE[(c - 256) >> 7]); put(c & 127); }
    }
    return out;
  }
  async function inflate(el) {
    const stream = new Blob([bytesOf(el)]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }
  // Planes R − G, G, B − G of low bytes then high bytes → interleaved RGB float32.
  async function halves(el, n) {
    const b = await inflate(el), out = new Float32Array(3 * n), all = 3 * n;
    for (let i = 0; i < n; i++) {
      const g = b[n + i] | (b[all + n + i] << 8);
      out[3 * i] = HALF[(b[i] | (b[all + i] << 8)) + g & 0xffff];
      out[3 * i + 1] = HALF[g];
      out[3 * i + 2] = HALF[(b[2 * n + i] | (b[all + 2 * n + i] << 8)) + g & 0xffff];
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
    const blobs = [...root.querySelectorAll(".vbin")];
    let b = 0;
    const parts = spec.images.map(im => [blobs[b++], im.flip ? blobs[b++] : null, im.test ? blobs[b++] : null]);
    const images = await Promise.all(parts.map(([d]) => halves(d, n)));
    const flips = await Promise.all(parts.map(([, f]) => f ? inflate(f) : null));
    const tests = await Promise.all(parts.map(([, , t]) => t ? inflate(t) : null));
    // The test of the statistics pixel under a film pixel: "✓ p=…" or "✗ p=…".
    const testAt = (k, x, y) => {
      const t = spec.images[k].test;
      if (!t) return "—";
      const sx = Math.floor((x + spec.origin[0]) * t.w / spec.film[0]), sy = Math.floor((y + spec.origin[1]) * t.h / spec.film[1]);
      const q = tests[k][sy * t.w + sx];
      if (q === 255) return "not tested";
      const p = 10 ** (-q / 10);
      return `${p < t.alpha ? "✗ rejected" : "✓"} p≈${p.toExponential(1)} at (${sx}, ${sy})`;
    };
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
            rgb = fl ? flipPal[fl[p]] : [40, 40, 40];
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
      let rows = `<tr><th colspan=6>pixel x=${h.x + spec.origin[0]}, y=${h.y + spec.origin[1]}</th></tr><tr><th></th><th>R</th><th>G</th><th>B</th><th>rel. error · FLIP</th><th>unbiased? (statistics pixel)</th></tr>`;
      images.forEach((im, k) => {
        const f = flips[k] ? `${(flips[k][p] / flipPal.length).toFixed(2)}–${((flips[k][p] + 1) / flipPal.length).toFixed(2)}` : "—";
        rows += `<tr class="${k === state.i ? "on" : ""}" data-k="${k}"><td>${spec.images[k].label}</td>` +
          [0, 1, 2].map(c => `<td class=v>${fmt(im[3 * p + c])}</td>`).join("") +
          `<td>${k ? rel(im, p).toPrecision(3) : "—"} · ${f}</td><td>${testAt(k, h.x, h.y)}</td></tr>`;
      });
      t.innerHTML = rows;
    }
    const show = i => { if (i >= 0 && i < images.length) { state.i = i; draw(); } };
    root.querySelectorAll(".vbar button[data-i]").forEach(b => b.addEventListener("click", () => show(+b.dataset.i)));
    root.querySelectorAll("input[type=radio]").forEach(r => r.addEventListener("change", () => { state.mode = r.value; draw(); }));
    root.querySelector(".ev").addEventListener("input", e => { state.ev = +e.target.value; draw(); });
    root.querySelector(".reset").addEventListener("click", fit);
    // The worst region: zoomed to fill the view, so its pixels can be read.
    function worst() {
      if (!spec.worst) return;
      const [y, x, size] = spec.worst, side = Math.min(port.clientWidth, port.clientHeight);
      state.zoom = Math.max(1, Math.floor(side / size));
      state.x = (port.clientWidth - size * state.zoom) / 2 - x * state.zoom;
      state.y = (port.clientHeight - size * state.zoom) / 2 - y * state.zoom;
      place();
    }
    const worstButton = root.querySelector(".worst");
    if (worstButton) worstButton.addEventListener("click", worst);
    root.addEventListener("keydown", e => {
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      const k = e.key;
      if (/^[0-9]$/.test(k)) show((+k + 9) % 10);
      else if (k === "w") worst();
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
    root.viewer = { images, flips, tests, testAt, state, show, draw, spec };
    fit(); draw();
    root.dataset.ready = "1";
  }
  // (when every viewer is ready, in ms since navigation: how long a reader waits)
  Promise.all([...document.querySelectorAll(".viewer")].map(v => setUp(v).catch(err => {
    v.insertAdjacentHTML("beforeend", `<p class=bad>The viewer could not decode its data: ${err}</p>`);
  }))).then(() => { document.documentElement.dataset.viewersReady = performance.now().toFixed(0); });
})();
