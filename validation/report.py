"""The reference-comparison report: one self-contained HTML page.

Reads ``DIR/results.json`` and the EXR images beside it, renders nothing, and
writes ``DIR/report/index.html`` (images as PNG data URIs, charts as inline
SVG, inline CSS, no script, a Content-Security-Policy that forbids every
external request) and ``DIR/report/summary.md``.

Tone mapping, the same for every image of a scene: x · 2^EV, clipped to
[0, 1], sRGB curve; EV puts the reference's 99th-percentile channel value at 1.
Error maps: |x − r| / (|r| + 0.01) per pixel (channel mean), on one shared
logarithmic colour scale per scene.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import time

import numpy as np

from . import charts, images, results

ERROR_EPS = 0.01
ERROR_CMAP = "magma"
MIN_SIDE = 160          # small renders are enlarged (nearest) to at least this


def _png_uri(rgb8: np.ndarray) -> str:
    import matplotlib.image

    buf = io.BytesIO()
    matplotlib.image.imsave(buf, rgb8, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _enlarge(a: np.ndarray, side: int = MIN_SIDE) -> np.ndarray:
    k = max(1, int(np.ceil(side / max(a.shape[:2]))))
    return np.repeat(np.repeat(a, k, axis=0), k, axis=1)


def exposure_for(reference: np.ndarray) -> float:
    """EV (in half stops) that maps the reference's 99th percentile to 1."""
    p = float(np.percentile(reference[..., :3], 99))
    return 0.0 if p <= 0 else float(np.round(-np.log2(p) * 2) / 2)


def relative_error(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    return (np.abs(x[..., :3] - r[..., :3]) / (np.abs(r[..., :3]) + ERROR_EPS)).mean(axis=-1)


def error_rgb(err: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    import matplotlib

    norm = matplotlib.colors.LogNorm(vmin=vmin, vmax=vmax, clip=True)
    rgba = matplotlib.colormaps[ERROR_CMAP](norm(np.maximum(err, vmin)))
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


def _figure(uri: str, caption: str) -> str:
    return (f'<figure><img src="{uri}" alt="{html.escape(caption)}">'
            f"<figcaption>{caption}</figcaption></figure>")


def _fmt(x, spec=".3g"):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def _scene_section(scene: dict, run_dir: str, palette: dict) -> str:
    img_dir = os.path.join(run_dir, "images", scene["name"])
    ref, _ = images.read_exr(os.path.join(img_dir, "reference.exr"))
    ev = exposure_for(ref)
    et = scene.get("equal_time") or {}
    ref_caption = (f"reference (path)<br>{scene['reference']['spp']} spp, "
                   f"{scene['reference']['seconds']:.1f} s")
    row_et, row_spp, errors, err_names, renders_ = [], [], [], [], []
    for est in scene["estimators"]:
        name, top = est["name"], est["runs"][-1]
        f_et = os.path.join(img_dir, f"{name}_equal_time.exr")
        if os.path.isfile(f_et):
            x, meta = images.read_exr(f_et)
            row_et.append(_figure(_png_uri(_enlarge(images.tonemap(x, ev))),
                                  f"{name}<br>equal time: {meta['spp']} spp, "
                                  f"{meta['render_seconds'] * 1e3:.1f} ms"))
        x, _ = images.read_exr(os.path.join(img_dir, f"{name}_spp{top['spp']}.exr"))
        row_spp.append(_figure(_png_uri(_enlarge(images.tonemap(x, ev))),
                               f"{name}<br>equal spp: {top['spp']} spp, "
                               f"{top['median_seconds'] * 1e3:.1f} ms"))
        errors.append(relative_error(x, ref))
        err_names.append(name)
        renders_.append(x)

    positive = np.concatenate([e[e > 0].ravel() for e in errors] + [np.array([1e-3])])
    vmax = max(float(np.percentile(positive, 99)), 1e-2)
    vmin = vmax / 1e3
    err_row = [_figure(_png_uri(_enlarge(error_rgb(e, vmin, vmax))),
                       f"{n}: |x−r|/(|r|+{ERROR_EPS}), mean {e.mean():.3g}")
               for n, e in zip(err_names, errors)]
    bar = charts.colour_bar(vmin, vmax, ERROR_CMAP, "relative error (shared scale)")

    y, x0, size = worst_window(errors)
    crop = lambda a: a[y:y + size, x0:x0 + size]  # noqa: E731
    crops = [_figure(_png_uri(_enlarge(images.tonemap(crop(ref), ev))), "reference")]
    for name, x in zip(err_names, renders_):
        crops.append(_figure(_png_uri(_enlarge(images.tonemap(crop(x), ev))), name))

    rows = []
    best_rel = min(e["runs"][-1]["relmse"] for e in scene["estimators"])
    best_eff = max(e["runs"][-1]["efficiency"] for e in scene["estimators"])
    best_sps = max(e["runs"][-1]["samples_per_second"] for e in scene["estimators"])
    for est in scene["estimators"]:
        top, u, c = est["runs"][-1], est["unbiasedness"], est["convergence"]
        verdict = "pass" if u["passed"] else "FAIL"
        slope = "exact" if c.get("exact") else f"{c['slope']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}]"
        rows.append(
            f"<tr><td><span class=sw style='background:{palette[est['name']]}'></span>"
            f"{html.escape(est['name'])}</td>"
            f"<td>{_fmt(top['relmse'])} ({_fmt(top['relmse'] / best_rel if best_rel else None, '.2f')}×)</td>"
            f"<td>{top['bias']:+.2e} ± {top['bias_se']:.1e}</td>"
            f"<td class={'ok' if u['passed'] else 'bad'}>{verdict} ({100 * u['pass_fraction']:.1f} %)</td>"
            f"<td>{slope}</td>"
            f"<td>{top['samples_per_second'] / 1e6:.2f} M ({top['samples_per_second'] / best_sps:.2f}×)</td>"
            f"<td>{_fmt(top['efficiency'])} ({top['efficiency'] / best_eff:.2g}×)</td></tr>")
    et_line = ""
    if et:
        measured = ", ".join(et["measured_ranking"] or [])
        et_line = (f"<p>At equal time ({et['budget_seconds'] * 1e3:.1f} ms per render) the "
                   f"fitted curves predict, most accurate first: "
                   f"<b>{', '.join(et['predicted_ranking'])}</b>; renders at that budget "
                   f"measured: <b>{measured}</b>"
                   f"{'' if et['agrees'] else ' (the winner differs from the prediction)'}.</p>")
    ref_info = scene["reference"]
    capped = f" — capped ({ref_info['capped']})" if ref_info["capped"] else ""
    return f"""
<section id="{scene['name']}">
<h2>{html.escape(scene['name'])} <small>{scene['res']}², max_depth {scene['max_depth']}</small></h2>
<p class=desc>{html.escape(scene.get('summary', ''))}</p>
<p>Reference: Mitsuba's <code>path</code>, {ref_info['spp']} spp in {ref_info['passes']} passes{capped}.
Tone mapping for every image below: x·2<sup>{ev:+.1f}</sup>, clipped to [0, 1], sRGB.</p>
<h3>Images: equal time, then equal spp</h3>
<div class=row>{_figure(_png_uri(_enlarge(images.tonemap(ref, ev))), ref_caption)}{''.join(row_et)}</div>
<div class=row>{''.join(row_spp)}</div>
<h3>Relative error at equal spp</h3>
<div class=row>{''.join(err_row)}</div>
<div class=bar>{bar}</div>
<h3>Accuracy against speed</h3>
<div class=row>{charts.error_vs_time(scene, palette)}{charts.error_vs_spp(scene, palette)}</div>
{et_line}
<table><tr><th>estimator</th><th>relMSE (÷ best)</th><th>bias ± se</th><th>unbiased (pixels passing)</th>
<th>slope [95 % CI]</th><th>samples/s (÷ best)</th><th>efficiency (÷ best)</th></tr>
{''.join(rows)}</table>
<h3>Worst region ({size}×{size} px at x={x0}, y={y}), equal spp</h3>
<div class=row>{''.join(crops)}</div>
</section>"""


def _failures(res: dict, run_dir: str, palette: dict) -> str:
    failed = [c for c in res["checks"] if not c["passed"]]
    items = "".join(f"<li><code>{html.escape(c['id'])}</code>: {html.escape(c['message'])}</li>"
                    for c in failed) or "<li>No check failed in this run.</li>"
    capped = [f"<li><code>{html.escape(s['name'])}</code>: reference capped "
              f"({html.escape(s['reference']['capped'])})</li>"
              for s in res["scenes"] if s["reference"]["capped"]]
    tails = []
    for s in res["scenes"]:
        for e in s["estimators"]:
            per = np.asarray(e["runs"][-1]["relmse_per_render"], float)
            if len(per) and np.median(per) > 0 and per.max() / np.median(per) > 5:
                tails.append(f"<li><code>{s['name']}/{e['name']}</code>: the worst render's "
                             f"relMSE is {per.max() / np.median(per):.0f}× the median "
                             f"(heavy tail)</li>")
    spreads = "".join(charts.error_spread(s, palette) for s in res["scenes"])
    cases = "".join(_failure_case(c, run_dir, palette) for c in res.get("failures", []))
    return f"""
<section id="failures">
<h2>Where methods fail</h2>
<p>Every failed check of this run, every reference that hit its cap, and the spread
of per-render error over seeds (a long upper tail means rare, large contributions:
fireflies).</p>
<ul>{items}{''.join(capped)}{''.join(tails)}</ul>
<div class=row>{spreads}</div>
{cases}
</section>"""


VERDICT_CLASS = {"fine": "ok", "heavy-tailed": "warn", "K too small to tell": "warn",
                 "refused": "ok", "biased (opt-in)": "warn", "biased": "bad",
                 "non-finite/negative": "bad"}


def _failure_case(case: dict, run_dir: str, palette: dict) -> str:
    """One case of the failures group: verdicts, numbers, evidence images."""
    case_dir = os.path.join(run_dir, "failures", case["id"])
    ref_file = os.path.join(case_dir, "reference.exr")
    ref = images.read_exr(ref_file)[0] if os.path.isfile(ref_file) else None
    ev = exposure_for(ref) if ref is not None else 0.0
    figs = [] if ref is None else [_figure(_png_uri(_enlarge(images.tonemap(ref, ev), 96)),
                                           "reference (path)")]
    rows = []
    for est in case["estimators"]:
        for label, f in est.get("images", {}).items():
            x = images.read_exr(os.path.join(case_dir, f))[0]
            figs.append(_figure(_png_uri(_enlarge(images.tonemap(x, ev), 96)),
                                f"{est['name']}<br>{label} seed"))
        rows.append(_failure_row(case, est, palette))
    if case.get("sweep"):
        sw = case["sweep"]
        head = ("<tr><th>estimator</th>" + "".join(
            f"<th>relMSE at {sw['param']} = {v}</th>" for v in sw["values"]) +
            "<th>growth</th><th>verdict</th></tr>")
        chart = charts.failure_sweep(case, palette)
        note = (f"<p>Evidence images at {sw['param']} = {sw['values'][-1]} (median- and "
                "worst-error seeds).</p>")
    else:
        head = ("<tr><th>estimator</th><th>verdict</th><th>relMSE median / p90 / p99 / max"
                "</th><th>fireflies</th><th>spp to match path at "
                f"{case['spp']} spp [90 % bootstrap]</th><th>evidence</th></tr>")
        chart, note = "", ""
    capped = f", capped ({case['reference']['capped']})" if case.get("reference", {}).get(
        "capped") else ""
    ref_line = (f" Reference: path, {case['reference']['spp']} spp{capped}."
                if case.get("reference") else "")
    defines = ", ".join(f"{k}={v}" for k, v in case.get("defines", {}).items())
    return f"""
<h3 id="{html.escape(case['id'])}">{html.escape(case['group'])}: {html.escape(case['label'])}
<small>{html.escape(case['scene'])}{' (' + html.escape(defines) + ')' if defines else ''},
{case['res']}², {case['spp']} spp × {case['seeds']} seeds</small></h3>
<p class=desc>{html.escape(case.get('summary', ''))}{html.escape(ref_line)}</p>
{chart}{note}
<table>{head}{''.join(rows)}</table>
<div class=row>{''.join(figs)}</div>"""


def _failure_row(case: dict, est: dict, palette: dict) -> str:
    name = (f"<td><span class=sw style='background:{palette.get(est['name'], '#777')}'></span>"
            f"{html.escape(est['name'])}</td>")
    v = est["verdict"]
    cls = VERDICT_CLASS.get(v, "")
    if case.get("sweep"):
        cells = "".join(f"<td>{_fmt(r)}</td>" for r in est["relmse"])
        return (f"<tr>{name}{cells}<td>×{_fmt(est['growth'])}</td>"
                f"<td class={cls}>{html.escape(v)}</td></tr>")
    n = est.get("numbers", {})
    if v == "refused" or not n:
        return (f"<tr>{name}<td class={cls}>{html.escape(v)}</td>"
                f"<td colspan=4>{html.escape(est.get('message', ''))}</td></tr>")
    rel = n["relmse"]
    match = n["spp_to_match_path"]
    evidence = []
    if "missing_fraction" in n:
        evidence.append(f"BIASED by allow_unreachable=true: {100 * n['missing_fraction']:.1f} % "
                        "of path's image mean missing")
    if "sun" in n:
        hits = n.get("expected_sun_hits_per_pixel")
        evidence.append(
            f"without the sun ({n['sun']['solid_angle']:.2g} sr, "
            f"{100 * n['sun_share_of_image']:.0f} % of the image): "
            + ("passes" if n["sunless_passed"] else "FAILS")
            + (f"; expected sun hits/pixel {hits:.2g}" if hits is not None else ""))
    if "rejected_pixels" in n:
        again = ("" if n["replicated"] is None else
                 f", {n['replicated_pixels']} replicated in fresh renders"
                 + (" (with the image mean)" if n["replicated"] and not n["replicated_pixels"]
                    else ""))
        evidence.append(f"per-pixel test: {100 * n['pass_fraction']:.1f} % pass, "
                        f"pooled p {min(n['pooled_p']):.2g}; {n['rejected_pixels']} px "
                        f"rejected{again}")
    spp = (f"{_fmt(match['spp'])} [{_fmt(match['low'])}, {_fmt(match['high'])}]"
           if match else "never (biased)")
    return (f"<tr>{name}<td class={cls}>{html.escape(v)}</td>"
            f"<td>{_fmt(rel['median'])} / {_fmt(rel['p90'])} / {_fmt(rel['p99'])} / "
            f"{_fmt(rel['max'])}</td><td>{100 * n['firefly_fraction']:.3f} %</td>"
            f"<td>{spp}</td><td>{html.escape('; '.join(evidence))}</td></tr>")


CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1200px;color:#222;padding:0 12px}
h1{margin-bottom:4px} h2{border-top:2px solid #ddd;padding-top:12px} h2 small{color:#777;font-weight:normal}
.row{display:flex;flex-wrap:wrap;gap:10px;align-items:flex-start}
figure{margin:0;text-align:center;font-size:12px} figure img{image-rendering:pixelated;display:block}
table{border-collapse:collapse;margin:10px 0;font-size:13px} td,th{border:1px solid #ccc;padding:4px 8px}
.ok{color:#1a7f37} .warn{color:#a15c00} .bad{color:#c62828;font-weight:bold} .sw{display:inline-block;width:10px;height:10px;margin-right:6px}
.verdict{font-size:18px;padding:8px 12px;display:inline-block;border-radius:4px}
.pass{background:#e6f4ea} .fail{background:#fdecea} .desc{color:#555} svg{max-width:100%;height:auto}
.bar svg{width:420px}
"""


def build(run_dir: str) -> str:
    """Write ``run_dir/report/index.html`` and ``summary.md``; return the HTML path."""
    path = os.path.join(run_dir, "results.json")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no results.json in {run_dir}: run `mcillum validate --out "
                                f"{run_dir}` first")
    with open(path, encoding="utf-8") as f:
        res = json.load(f)
    names = list(dict.fromkeys([e["name"] for s in res["scenes"] for e in s["estimators"]]
                               + [e["name"] for c in res.get("failures", [])
                                  for e in c["estimators"]]))
    palette = charts.colours(names)
    checks = res["checks"]
    failed = sum(not c["passed"] for c in checks)
    m = res["machine"]
    verdict = ("pass" if failed == 0 else "fail",
               f"{len(checks) - failed} of {len(checks)} checks passed")
    toc = " · ".join(f"<a href='#{s['name']}'>{s['name']}</a>" for s in res["scenes"])
    body = "".join(_scene_section(s, run_dir, palette) for s in res["scenes"])
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; style-src 'unsafe-inline'">
<title>mcillum validation report</title><style>{CSS}</style></head><body>
<h1>mcillum: estimators against Mitsuba's path tracer</h1>
<p>{html.escape(res['created'])} · {html.escape(m['platform'])}, {m['cpus']} CPUs ·
variant <code>{html.escape(res['variant'])}</code> · mitsuba {html.escape(res['mitsuba_version'])},
drjit {html.escape(res['drjit_version'])} · profile <b>{html.escape(res['profile'])}</b> ·
{res['wall_seconds']:.0f} s · report written {time.strftime('%Y-%m-%d %H:%M')}</p>
<p class="verdict {verdict[0]}">{verdict[1]}</p>
<p>Scenes: {toc} · <a href="#failures">where methods fail</a> · <a href="#summary">summary</a></p>
<p>Each estimator renders every scene K times per spp; Mitsuba's <code>path</code> at the same
max_depth is the reference. Unbiasedness: per-pixel Welch tests with each side's own variance
(Šidák-corrected) and an image-mean test, family-wise α = {res['alpha']}.
relMSE = mean (x−r)²/(r²+0.01); efficiency = 1/(relMSE·time).</p>
{body}
{_failures(res, run_dir, palette)}
<section id="summary"><h2>Summary across scenes</h2>{charts.efficiency_summary(res, palette)}</section>
</body></html>
"""
    out_dir = os.path.join(run_dir, "report")
    os.makedirs(out_dir, exist_ok=True)
    target = os.path.join(out_dir, "index.html")
    results.write_text(target, page)
    results.write_text(os.path.join(out_dir, "summary.md"), results.summary(res))
    return target
