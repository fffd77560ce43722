"""The reference-comparison report: one self-contained HTML page.

Reads the run's :class:`~.results.Results` (``DIR/results.json``) and the EXR
images beside it, renders nothing, and writes ``DIR/report/index.html`` (images as PNG data URIs, charts as inline
SVG, inline CSS, no script, a Content-Security-Policy that forbids every
external request) and ``DIR/report/summary.md``.

Tone mapping, the same for every image of a scene: x · 2^EV, clipped to
[0, 1], sRGB curve; EV puts the reference's 99th-percentile channel value at 1.
Error maps: :func:`metrics.relative_error_map`, |x − r| / (|r| + 0.01) per
pixel (channel mean), on one shared logarithmic colour scale per scene.
"""

from __future__ import annotations

import base64
import html
import io
import os
import re
import time

import matplotlib
import matplotlib.image
import numpy as np

from mcillum import files
from mcillum.errors import UserError
from mcillum.integrators.scene_checks import KIND_NAMES

from . import charts, checks, images, metrics, results, tails
from .results import CaseResult, Results, SceneResult

ERROR_CMAP = "magma"
MIN_SIDE = 160          # small renders are enlarged (nearest) to at least this


def _png_uri(rgb8: np.ndarray) -> str:
    buf = io.BytesIO()
    matplotlib.image.imsave(buf, rgb8, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _enlarge(a: np.ndarray, side: int = MIN_SIDE) -> np.ndarray:
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


def _fmt(x, spec=".3g"):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def _swatch(name: str, colours: dict) -> str:
    return (f"<span class=sw style='background:{colours.get(name, '#777')}'></span>"
            f"{html.escape(name)}")


def _img(rgb8: np.ndarray, caption: str, side: int = MIN_SIDE) -> str:
    """A figure of an 8-bit image at least ``side`` pixels wide on screen:
    large images as they are (zoomed by CSS), small ones enlarged first."""
    h, w = rgb8.shape[:2]
    if max(h, w) < 64:                      # thumbnails: enlarge the pixels themselves
        rgb8 = _enlarge(rgb8, side)
        h, w = rgb8.shape[:2]
    zoom = max(1, int(np.ceil(side / max(h, w))))
    alt = html.escape(re.sub(r"<[^>]+>", " ", caption))
    return (f'<figure><img src="{_png_uri(rgb8)}" alt="{alt}" '
            f'width="{w * zoom}" height="{h * zoom}"><figcaption>{caption}</figcaption></figure>')


def _scene_section(scene: SceneResult, run_dir: str, colours: dict,
                   by_design=frozenset()) -> str:
    speed = _speed_section(scene, run_dir, colours) if scene.speed else ""
    return f"""
<section id="{scene.name}">
<h2>{html.escape(scene.name)} <small>max_depth {scene.max_depth}</small></h2>
<p class=desc>{html.escape(scene.summary)}</p>
{speed}
{_statistics_section(scene, run_dir, colours, by_design)}
{_quadrature_section(scene, colours) if scene.quadrature else ""}
</section>"""


def _quadrature_section(scene: SceneResult, colours: dict) -> str:
    """Estimators of N directions: equal rays against cosine_hemisphere, bias
    against N, calibration of the posterior std (quadrature.py)."""
    rows, bias_rows = [], []
    for q in scene.quadrature:
        r, c = q.equal_rays, q.calibration
        rays = (f"{r.ratio:.3g} [{r.ratio_low:.3g}, {r.ratio_high:.3g}]"
                f" ({r.seconds / r.baseline_seconds:.2f}× the time)") if r else "—"
        good = c is not None and (c.verdict == "calibrated" or c.verdict.startswith("exact"))
        cal = (f"<span class={'ok' if good else 'warn'}>{html.escape(c.verdict)}</span>: median "
               f"{_fmt(c.median, '.2f')} ({_fmt(c.q25, '.2f')}–{_fmt(c.q75, '.2f')})"
               ) if c else "—"
        rows.append(f"<tr><td>{_swatch(q.name, colours)}</td><td>{q.directions}</td>"
                    f"<td>{rays}</td><td>{cal}</td></tr>")
        for b in q.bias or []:
            bias_rows.append(f"<tr><td>{_swatch(q.name, colours)}</td><td>{b.directions}</td>"
                             f"<td>{100 * b.rms_bias:.2f} % ± {100 * b.rms_bias_se:.2f} %</td>"
                             f"<td>{100 * b.mean_bias:+.2f} %</td></tr>")
    q0 = scene.quadrature[0]
    bias = ("<p>Bias against N (an estimator biased by design): rms over pixels of the "
            "mean of K renders less the reference, corrected for the noise of both, "
            "relative to the reference's rms; and the image mean's relative bias.</p>"
            "<table><tr><th>estimator</th><th>N</th><th>rms bias ± se</th>"
            f"<th>image-mean bias</th></tr>{''.join(bias_rows)}</table>") if bias_rows else ""
    return f"""
<h3>Quadrature: N directions per shading point</h3>
<p>At {q0.spp} camera spp, {q0.renders} renders each. <b>Equal rays</b>: relMSE of N
directions × {q0.spp} spp over that of <code>cosine_hemisphere</code> at N·{q0.spp} spp
(below 1: the point set wins), 95 % interval. <b>Calibration</b>: per pixel, the measured
RMSE over the predicted posterior std (the reference's variance added); calibrated when the
median lies in [0.67, 1.5]
(above: over-confident).</p>
<table><tr><th>estimator</th><th>N</th><th>relMSE ÷ cosine at equal rays</th>
<th>posterior std</th></tr>{''.join(rows)}</table>
{bias}"""


def _executor(where: dict) -> str:
    """Where the renders ran (results ``executor``), in a few words."""
    if where.get("kind") != "ray":
        return "rendered in one process"
    nodes = len(where.get("nodes", []))
    return (f"rendered on Ray ({where.get('workers', '?')} workers on {nodes} "
            f"node{'s' if nodes != 1 else ''})")


def _scaling(ev: float) -> str:
    """The tone mapping's scale factor as the page writes it: ``x`` when the
    exposure rounds to 0 (not ``x·2^-0.0``), else ``x·2^ev``."""
    return "x" if abs(ev) < 0.05 else f"x·2<sup>{ev:+.1f}</sup>"


def _timed_on(sp) -> str:
    if not sp.timed_on:
        return ""
    return (f" Every render of this stage was timed alone on "
            f"{html.escape(', '.join(sp.timed_on))}.")


def _speed_section(scene: SceneResult, run_dir: str, colours: dict) -> str:
    """The speed-and-images stage: equal-time images at the display
    resolution, error and FLIP maps, the worst region, accuracy against time."""
    sp = scene.speed
    d = os.path.join(run_dir, "images", scene.name, "display")
    ref, _ = files.read_exr(os.path.join(d, "reference.exr"))
    ev = images.exposure_for(ref)
    top = sp.budgets[-1]
    names = list(top.estimators)
    shots, flips = {}, {}
    for n in names:
        shots[n] = files.read_exr(os.path.join(d, f"{n}.exr"))
        if not np.isnan(sp.mean_flip.get(n, np.nan)):
            flips[n] = files.read_exr(os.path.join(d, f"{n}.exr"), "flip")[0][..., 0]
    side = 256                              # 128² at 2×, 256² as it is
    row = [_img(images.tonemap(ref, ev), f"reference (path)<br>{sp.reference.spp} spp", side)]
    for n in names:
        x, meta = shots[n]
        flip = sp.mean_flip.get(n, np.nan)
        row.append(_img(images.tonemap(x, ev), f"{_swatch(n, colours)}<br>{meta['spp']} spp, "
                        f"{meta['render_seconds'] * 1e3:.0f} ms"
                        + ("" if np.isnan(flip) else f", FLIP {flip:.3f}"), side))
    errors = [metrics.relative_error_map(shots[n][0], ref) for n in names]
    positive = np.concatenate([e[e > 0].ravel() for e in errors] + [np.array([1e-3])])
    vmax = max(float(np.percentile(positive, 99)), 1e-2)
    vmin = vmax / 1e3
    err_row = [_img(error_rgb(e, vmin, vmax), f"{n}: mean {e.mean():.3g}", side)
               for n, e in zip(names, errors)]
    flip_row = [_img(flip_rgb(flips[n]), f"{n}: mean FLIP {sp.mean_flip[n]:.3f}", side)
                for n in names if n in flips]
    y, x0, size = worst_window(errors)
    crop = lambda a: a[y:y + size, x0:x0 + size]  # noqa: E731
    crops = [_img(images.tonemap(crop(ref), ev), "reference", side // 2)]
    crops += [_img(images.tonemap(crop(shots[n][0]), ev), n, side // 2) for n in names]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in sp.notes)
    ref_info = sp.reference
    capped = f" — capped ({html.escape(ref_info.capped)})" if ref_info.capped else ""
    return f"""
<h3>Equal time at {sp.res}²: {top.seconds * 1e3:.0f} ms per render</h3>
<p>Every estimator got the time Mitsuba's <code>path</code> needs for {top.path_spp} spp;
its spp come from its own cost model t = a + b·spp. Reference: <code>path</code>,
{ref_info.spp} spp in {ref_info.passes} passes{capped}.{_timed_on(sp)} Tone mapping for every image:
{_scaling(ev)}, clipped to [0, 1], sRGB. Captions: spp and the measured time of the
render shown.</p>
<div class=row>{''.join(row)}</div>
<h4>Relative error |x−r|/(|r|+{metrics.EPSILON}) of these renders</h4>
<div class=row>{''.join(err_row)}</div>
<div class=bar>{charts.colour_bar(vmin, vmax, ERROR_CMAP, "relative error (shared scale)")}</div>
<h4>FLIP (HDR mode: flip-evaluator tone-maps both images, ACES, exposures from the
reference; 0 = no visible difference, 1 = the largest)</h4>
<div class=row>{''.join(flip_row) or '<p>FLIP is undefined here: the reference is black.</p>'}</div>
<div class=bar>{charts.colour_bar(0.0, 1.0, ERROR_CMAP, "FLIP", log=False)}</div>
<h4>Worst region ({size}×{size} px at x={x0}, y={y}, by summed relative error)</h4>
<div class=row>{''.join(crops)}</div>
<h4>Accuracy against time</h4>
<div class=row>{charts.error_vs_time(scene, colours)}</div>
{_speed_table(sp, colours)}
{'<ul class=notes>' + notes + '</ul>' if notes else ''}"""


def _speed_table(sp, colours: dict) -> str:
    top = sp.budgets[-1]
    rank = {p.estimator: p for p in sp.ranking}
    rows = []
    for n, run in top.estimators.items():
        c, r, p = sp.cost_model[n], sp.efficiency_vs_path[n], rank[n]
        tied = f" (tie: {', '.join(p.tied_with)})" if p.tied_with else ""
        wall = float(np.median(run.wall_seconds)) * 1e3
        rows.append(
            f"<tr><td>{_swatch(n, colours)}</td><td>{p.rank}{html.escape(tied)}</td>"
            f"<td>{_fmt(r.ratio)} [{_fmt(r.ci.low)}, {_fmt(r.ci.high)}]</td>"
            f"<td>{_fmt(run.relmse)} [{_fmt(run.relmse_ci.low)}, {_fmt(run.relmse_ci.high)}]</td>"
            f"<td>{run.spp}</td><td class={'ok' if run.on_budget else 'warn'}>{wall:.0f}</td>"
            f"<td>{c.fixed_s * 1e3:.1f} [{c.fixed_s_ci.low * 1e3:.1f}, "
            f"{c.fixed_s_ci.high * 1e3:.1f}]</td>"
            f"<td>{c.per_spp_s * 1e3:.2f} [{c.per_spp_s_ci.low * 1e3:.2f}, "
            f"{c.per_spp_s_ci.high * 1e3:.2f}]</td></tr>")
    return f"""<p>At {top.seconds * 1e3:.0f} ms, most efficient first ("=": the 95 % intervals
overlap, a tie): <b>{html.escape(results.ranking_text(sp.ranking))}</b>.</p>
<table><tr><th>estimator</th><th>rank</th><th>efficiency ÷ path [95 % CI]</th>
<th>relMSE [95 % CI]</th><th>spp</th><th>median ms (K = {sp.renders})</th>
<th>fixed cost a, ms [95 % CI]</th><th>per spp b, ms [95 % CI]</th></tr>
{''.join(rows)}</table>"""


def _statistics_section(scene: SceneResult, run_dir: str, colours: dict,
                        by_design=frozenset()) -> str:
    """The small-image statistics: unbiasedness, convergence, the ladder
    (an estimator biased by design shows its slope, not tested)."""
    rows = []
    best_rel = min(e.top.relmse for e in scene.estimators)
    for est in scene.estimators:
        top, u, c = est.top, est.unbiasedness, est.convergence
        slope = "exact" if c.exact else f"{c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]"
        if est.name in by_design:
            tested = (f"biased by design ({100 * u.pass_fraction:.1f} % of pixels pass)",
                      f"not tested: {slope}")
        else:
            tested = (f"{_outcome(u.outcome, u.reason)} ({100 * u.pass_fraction:.1f} %)",
                      f"{_outcome(c.outcome, c.message)} {slope}")
        rows.append(
            f"<tr><td>{_swatch(est.name, colours)}</td>"
            f"<td>{_fmt(top.relmse)} ({_fmt(top.relmse / best_rel if best_rel else None, '.2f')}×)</td>"
            f"<td>{top.bias:+.2e} ± {top.bias_se:.1e}</td>"
            f"<td>{tested[0]}</td><td>{tested[1]}</td></tr>")
    ref_info = scene.reference
    capped = f" — capped ({ref_info.capped})" if ref_info.capped else ""
    spp = ", ".join(str(s) for s in scene.ladder)
    return f"""
<h3>Statistics at {scene.res}² ({scene.renders} renders per estimator at {spp} spp)</h3>
<p>Small images, many renders: enough samples per pixel for per-pixel tests. Reference:
<code>path</code>, {ref_info.spp} spp in {ref_info.passes} passes{capped}.</p>
<table><tr><th>estimator</th><th>relMSE at {scene.ladder[-1]} spp (÷ best)</th><th>bias ± se</th>
<th>unbiased (pixels passing)</th><th>slope [95 % CI]</th></tr>
{''.join(rows)}</table>
<div class=row>{charts.error_vs_spp(scene, colours)}</div>"""


OUTCOME_CLASS = {"pass": "ok", "inconclusive": "warn", "fail": "bad"}


def _outcome(outcome: str, why: str = "") -> str:
    """A check's outcome as a coloured word, its reason on hover."""
    title = f' title="{html.escape(why, quote=True)}"' if why else ""
    word = "FAIL" if outcome == "fail" else outcome
    return f"<span class={OUTCOME_CLASS.get(outcome, '')}{title}>{word}</span>"


def _failures(res: Results, run_dir: str, colours: dict) -> str:
    items = "".join(f"<li><code>{html.escape(c.id)}</code>: {html.escape(c.message)}</li>"
                    for c in res.failed) or "<li>No check failed in this run.</li>"
    unsure = "".join(f"<li><code>{html.escape(c.id)}</code>: {html.escape(c.message)}</li>"
                     for c in res.inconclusive)
    unsure = (f"<h3>Inconclusive at this budget</h3><p>The test saw a difference that a heavy "
              f"tail explains (an estimator darker where its renders caught fireflies, or a "
              f"sun too small to be hit), or a rejection that did not replicate: neither "
              f"biased nor shown unbiased. Each line says about how many samples per pixel "
              f"would decide.</p><ul>{unsure}</ul>") if unsure else ""
    capped = [f"<li><code>{html.escape(s.name)}</code>: reference capped "
              f"({html.escape(s.reference.capped)})</li>"
              for s in res.scenes if s.reference.capped]
    heavy = []
    for s in res.scenes:
        for e in s.estimators:
            per = np.asarray(e.top.relmse_per_render, float)
            fireflies = e.top.firefly_fraction
            if len(per) and tails.is_heavy(float(per.max()), float(np.median(per)),
                                           fireflies or 0.0):
                shown = ("" if fireflies is None else
                         f", fireflies {100 * fireflies:.3f} % of pixels")
                heavy.append(f"<li><code>{s.name}/{e.name}</code>: heavy-tailed at "
                             f"{e.top.spp} spp: the worst render's relMSE is "
                             f"{tails.tail_ratio(per):.0f}× the median{shown}</li>")
    spreads = "".join(charts.error_spread(s, colours) for s in res.scenes)
    cases = "".join(_failure_case(c, run_dir, colours) for c in res.failures)
    return f"""
<section id="failures">
<h2>Where methods fail</h2>
<h3>Failed: biased or broken</h3>
<p>Every failed check of this run, with its evidence.</p>
<ul>{items}</ul>
{unsure}
<h3>Heavy tails and capped references</h3>
<p>Every reference that hit its cap, every heavy-tailed estimator (worst render over
{tails.TAIL_RATIO:g}× the median error, or over {100 * tails.TAIL_FIREFLIES:g} % fireflies),
and the spread of per-render error over seeds (a long upper tail means rare, large
contributions: fireflies).</p>
<ul>{''.join(capped) + ''.join(heavy) or '<li>None in this run.</li>'}</ul>
<div class=row>{spreads}</div>
{cases}
</section>"""


VERDICT_CLASS = {"fine": "ok", "heavy-tailed": "warn", checks.HEAVY: "warn",
                 checks.NOT_REPLICATED: "warn", "K too small to tell": "warn",
                 "refused": "ok", "biased (opt-in)": "warn", "biased": "bad",
                 checks.BY_DESIGN: "warn",
                 "non-finite/negative": "bad"}


def _failure_case(case: CaseResult, run_dir: str, colours: dict) -> str:
    """One case of the failures group: verdicts, numbers, evidence images."""
    case_dir = os.path.join(run_dir, "failures", case.id)
    ref_file = os.path.join(case_dir, "reference.exr")
    ref = files.read_exr(ref_file)[0] if os.path.isfile(ref_file) else None
    ev = images.exposure_for(ref) if ref is not None else 0.0
    figs = [] if ref is None else [_img(images.tonemap(ref, ev), "reference (path)", 96)]
    rows = []
    for est in case.estimators:
        for label, f in est.images.items():
            x = files.read_exr(os.path.join(case_dir, f))[0]
            figs.append(_img(images.tonemap(x, ev), f"{est.name}<br>{label} seed", 96))
        rows.append(_failure_row(case, est, colours))
    if case.sweep is not None:
        sw = case.sweep
        head = ("<tr><th>estimator</th>" + "".join(
            f"<th>relMSE at {sw.param} = {v}</th>" for v in sw.values) +
            "<th>growth</th><th>verdict</th></tr>")
        chart = charts.failure_sweep(case, colours)
        note = (f"<p>Evidence images at {sw.param} = {sw.values[-1]} (median- and "
                "worst-error seeds).</p>")
    else:
        head = ("<tr><th>estimator</th><th>verdict</th><th>relMSE median / p90 / p99 / max"
                "</th><th>fireflies</th><th>spp to match path at "
                f"{case.spp} spp [90 % bootstrap]</th><th>evidence</th></tr>")
        chart, note = "", ""
    ref_line = ""
    if case.reference is not None:
        capped = f", capped ({case.reference.capped})" if case.reference.capped else ""
        ref_line = f" Reference: path, {case.reference.spp} spp{capped}."
    defines = ", ".join(f"{k}={v}" for k, v in case.defines.items())
    return f"""
<h3 id="{html.escape(case.id)}">{html.escape(case.group)}: {html.escape(case.label)}
<small>{html.escape(case.scene)}{' (' + html.escape(defines) + ')' if defines else ''},
{case.res}², {case.spp} spp × {case.seeds} seeds</small></h3>
<p class=desc>{html.escape(case.summary)}{html.escape(ref_line)}</p>
{chart}{note}
<table>{head}{''.join(rows)}</table>
<div class=row>{''.join(figs)}</div>"""


def _failure_row(case: CaseResult, est, colours: dict) -> str:
    name = f"<td>{_swatch(est.name, colours)}</td>"
    v = est.verdict
    cls = VERDICT_CLASS.get(v, "")
    if case.sweep is not None:
        cells = "".join(f"<td>{_fmt(r)}</td>" for r in est.relmse)
        return (f"<tr>{name}{cells}<td>×{_fmt(est.growth)}</td>"
                f"<td class={cls}>{html.escape(v)}</td></tr>")
    n = est.numbers
    if n is None:
        return (f"<tr>{name}<td class={cls}>{html.escape(v)}</td>"
                f"<td colspan=4>{html.escape(est.message or '')}</td></tr>")
    rel, match, t = n.relmse, n.spp_to_match_path, n.test
    evidence = []
    if n.missing_fraction is not None:
        evidence.append(f"BIASED by allow_unreachable=true: {100 * n.missing_fraction:.1f} % "
                        "of path's image mean missing")
    if n.sun is not None:
        hits = n.sun.expected_sun_hits_per_pixel
        evidence.append(
            f"without the sun ({n.sun.sun['solid_angle']:.2g} sr, "
            f"{100 * n.sun.sun_share_of_image:.0f} % of the image): "
            + ("not biased" if n.sun.sunless_passed else "BIASED")
            + (f"; expected sun hits/pixel {hits:.2g}" if hits is not None else ""))
    if t is not None and t.reason and t.outcome != "pass":
        evidence.append(t.reason)
    if n.sun is not None and n.sun.sunless_reason and not n.sun.sunless_passed:
        evidence.append(f"without the sun: {n.sun.sunless_reason}")
    if t is not None and not t.passed:
        again = ("" if t.replicated is None else
                 f", {t.replicated_pixels} replicated in fresh renders"
                 + (" (with the image mean)" if t.replicated and not t.replicated_pixels
                    else ""))
        evidence.append(f"per-pixel test: {100 * t.pass_fraction:.1f} % pass, "
                        f"pooled p {min(t.pooled_p):.2g}; {t.rejected_pixels} px "
                        f"rejected{again}")
    elif t is not None:
        evidence.append(f"per-pixel test: {100 * t.pass_fraction:.1f} % pass, "
                        f"pooled p {min(t.pooled_p):.2g}")
    spp = (f"{_fmt(match.spp)} [{_fmt(match.low)}, {_fmt(match.high)}]"
           if match else "never (biased)")
    return (f"<tr>{name}<td class={cls}>{html.escape(v)}</td>"
            f"<td>{_fmt(rel.median)} / {_fmt(rel.p90)} / {_fmt(rel.p99)} / "
            f"{_fmt(rel.max)}</td><td>{100 * n.firefly_fraction:.3f} %</td>"
            f"<td>{spp}</td><td>{html.escape('; '.join(evidence))}</td></tr>")


def _estimators(res: Results, colours: dict) -> str:
    """The estimators of the run: name, what they are, what they cannot reach."""
    rows = "".join(
        f"<tr><td>{_swatch(name, colours)}</td><td>{html.escape(f.display_name)}</td>"
        f"<td>{html.escape(', '.join(KIND_NAMES.get(k, k) for k in f.unreachable))}</td></tr>"
        for name, f in res.estimator_facts.items())
    return ("<table><tr><th>estimator</th><th>what it is</th><th>refuses scenes with</th>"
            f"</tr>{rows}</table>") if rows else ""


CSS = """
body{font:14px/1.45 system-ui,sans-serif;margin:24px auto;max-width:1200px;color:#222;padding:0 12px}
h1{margin-bottom:4px} h2{border-top:2px solid #ddd;padding-top:12px} h2 small{color:#777;font-weight:normal}
.row{display:flex;flex-wrap:wrap;gap:10px;align-items:flex-start}
figure{margin:0;text-align:center;font-size:12px} figure img{image-rendering:pixelated;display:block}
table{border-collapse:collapse;margin:10px 0;font-size:13px} td,th{border:1px solid #ccc;padding:4px 8px}
.ok{color:#1a7f37} .warn{color:#a15c00} .bad{color:#c62828;font-weight:bold} .sw{display:inline-block;width:10px;height:10px;margin-right:6px}
.verdict{font-size:18px;padding:8px 12px;display:inline-block;border-radius:4px}
.pass{background:#e6f4ea} .fail{background:#fdecea} .inconclusive{background:#fff4e0} .desc{color:#555} svg{max-width:100%;height:auto}
.bar svg{width:420px}
"""


def build(run_dir: str, res: Results | None = None) -> str:
    """Write ``run_dir/report/index.html`` and ``summary.md`` from ``res`` (read
    from ``run_dir/results.json`` when not given); return the HTML path."""
    res = res if res is not None else results.load(run_dir)
    try:
        return _write(run_dir, res)
    except FileNotFoundError as err:
        raise UserError(f"{err.filename or err} is missing (the report needs every image "
                        f"of the run): run `mcillum validate --out {run_dir}` again") from None


def _write(run_dir: str, res: Results) -> str:
    colours = charts.palette(res)
    checks, n = res.checks, res.counts()
    m = res.machine
    verdict = ("fail" if n["fail"] else "inconclusive" if n["inconclusive"] else "pass",
               f"{n['pass']} of {len(checks)} checks pass, {n['inconclusive']} inconclusive, "
               f"{n['fail']} fail")
    toc = " · ".join(f"<a href='#{s.name}'>{s.name}</a>" for s in res.scenes)
    by_design = {n for n, f in res.estimator_facts.items() if not f.unbiased}
    body = "".join(_scene_section(s, run_dir, colours, by_design) for s in res.scenes)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; style-src 'unsafe-inline'">
<title>mcillum validation report</title><style>{CSS}</style></head><body>
<h1>mcillum: estimators against Mitsuba's path tracer</h1>
<p>{html.escape(res.created)} · {html.escape(m['platform'])}, {m['cpus']} CPUs ·
variant <code>{html.escape(res.variant)}</code> · mitsuba {html.escape(res.mitsuba_version)},
drjit {html.escape(res.drjit_version)} · profile <b>{html.escape(res.profile)}</b> ·
{_executor(res.executor)} · {res.wall_seconds:.0f} s · report written {time.strftime('%Y-%m-%d %H:%M')}</p>
<p class="verdict {verdict[0]}">{verdict[1]}</p>
<p>Scenes: {toc} · <a href="#failures">where methods fail</a> · <a href="#summary">summary</a></p>
<p>Each estimator renders every scene K times per spp; Mitsuba's <code>path</code> at the same
max_depth is the reference. Unbiasedness: per-pixel Welch tests with each side's own variance
(Šidák-corrected) and an image-mean test, family-wise α = {res.alpha}.
relMSE = mean (x−r)²/(r²+{metrics.EPSILON}); efficiency = 1/(relMSE·time).</p>
{_estimators(res, colours)}
{body}
{_failures(res, run_dir, colours)}
<section id="summary"><h2>Summary across scenes</h2>{charts.efficiency_summary(res, colours)}</section>
</body></html>
"""
    out_dir = os.path.join(run_dir, "report")
    os.makedirs(out_dir, exist_ok=True)
    target = os.path.join(out_dir, "index.html")
    files.write_text(target, page)
    files.write_text(os.path.join(out_dir, "summary.md"), results.summary(res))
    return target
