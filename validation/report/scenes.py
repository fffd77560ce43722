"""The report's section of one scene comparison: the speed-and-images
stage (equal-time images, error and FLIP maps, the worst region, accuracy
against time), the budget axis (axis.py), the small-image statistics and
the quadrature stage."""

from __future__ import annotations

import dataclasses
import html
import os
from dataclasses import dataclass

import numpy as np

from mcillum import files, images

from ..results import SceneResult, kinds_shown, layout, ranking_text, ratio_text, relmse_text
from ..stats import metrics
from . import charts
from .axis import axis_section
from .parts import ERROR_LEVELS, FLIP_LEVELS, fmt, map_colours, outcome, swatch, worst_window
from .overview import evidence_anchor
from .viewer import Shown, Test, packed, text_bytes, viewer


def scene_section(scene: SceneResult, run_dir: str, colours: dict,
                  by_design=frozenset(), shots: Display | None = None,
                  max_bytes: int | None = None) -> str:
    """The section of ``scene``; ``shots`` its :func:`display` (read here
    when not given), its viewer's data within ``max_bytes``."""
    shots = shots if shots is not None else display(scene, run_dir, colours)
    speed = _speed_section(scene, shots, colours, max_bytes) if scene.speed else ""
    return f"""
<section id="{scene.name}">
<h2>{html.escape(scene.name)} <small>max_depth {scene.max_depth}</small></h2>
<p class=desc>{html.escape(scene.summary)}</p>
{_notes(scene)}
{speed}
{axis_section(scene, colours) if scene.budget_axis else ""}
{_statistics_section(scene, run_dir, colours, by_design)}
{_quadrature_section(scene, colours) if scene.quadrature else ""}
{_learning_section(scene, colours) if scene.learning else ""}
</section>"""


def _notes(scene: SceneResult) -> str:
    """A scene given by path: where its settings came from, its film, and
    which estimators do not render it."""
    if not scene.notes:
        return ""
    items = "".join(f"<li>{html.escape(n)}</li>" for n in scene.notes)
    return f"<ul class=notes>{items}</ul>"


def _quadrature_section(scene: SceneResult, colours: dict) -> str:
    """Estimators of N directions: equal rays against their baseline, bias
    against N, calibration of the posterior std (quadrature.py)."""
    rows, bias_rows = [], []
    for q in scene.quadrature:
        r, c = q.equal_rays, q.calibration
        rays = (f"{r.ratio:.3g} [{r.ratio_low:.3g}, {r.ratio_high:.3g}]"
                f" ({r.seconds / r.baseline_seconds:.2f}× the time)") if r else "—"
        against = (f"<code>{html.escape(r.baseline)}</code>" + (
            f" (its error at {r.baseline_read_at} spp, ÷ {q.directions})"
            if r.baseline_read_at and r.baseline_read_at != r.baseline_spp else "")) if r else "—"
        good = c is not None and (c.verdict == "calibrated" or c.verdict.startswith("exact"))
        cal = (f"<span class={'ok' if good else 'warn'}>{html.escape(c.verdict)}</span>: median "
               f"{fmt(c.median, '.2f')} ({fmt(c.q25, '.2f')}–{fmt(c.q75, '.2f')})"
               + (f" at {c.spp} spp" if c.spp else "")) if c else "—"
        rows.append(f"<tr><td>{swatch(q.name, colours)}</td><td>{q.directions}</td>"
                    f"<td>{against}</td><td>{rays}</td><td>{cal}</td></tr>")
        for b in q.bias or []:
            bias_rows.append(f"<tr><td>{swatch(q.name, colours)}</td><td>{b.directions}</td>"
                             f"<td>{b.renders or q.renders}</td>"
                             f"<td>{100 * b.rms_bias:.2f} % ± {100 * b.rms_bias_se:.2f} %</td>"
                             f"<td>{100 * b.mean_bias:+.2f} %</td></tr>")
    q0 = scene.quadrature[0]
    settings = "".join(_settings(q, colours) for q in scene.quadrature if q.settings)
    bias = ("<p>Bias against N (an estimator biased by design): rms over pixels of the "
            "mean of K renders less the reference, corrected for the noise of both, "
            "relative to the reference's rms; and the image mean's relative bias.</p>"
            "<table><tr><th>estimator</th><th>N</th><th>renders</th><th>rms bias ± se</th>"
            f"<th>image-mean bias</th></tr>{''.join(bias_rows)}</table>") if bias_rows else ""
    return f"""
<h3>Quadrature: N directions per shading point</h3>
<p>At {q0.spp} camera spp, {q0.renders} renders each. <b>Equal rays</b>: relMSE of N
directions × {q0.spp} spp over that of its baseline at N·{q0.spp} spp (<code>cosine_hemisphere</code>;
<code>emitter_sampling</code> for one that samples the light; below 1: the point set wins),
95 % interval; where the scene's sampler is independent the baseline's error is read off its
ladder renders at {q0.spp} spp and divided by N (N·spp independent samples have 1/N of the
variance), else rendered at N·spp. The time beside it: medians of timed renders of each. The N directions of a shading point share
one camera sample: where a pixel's own content varies (a texture, an edge), N·spp camera
samples of the baseline also antialias it, and the ratio says so. <b>Calibration</b>: per pixel, the measured
RMSE over the predicted posterior std (the reference's variance added), at the spp it names
(the rung below the top, whose error bars the reference resolves); calibrated when the
median lies in [0.5, 2] (above: over-confident); outside [0.1, 3] the check fails.</p>
<table><tr><th>estimator</th><th>N</th><th>baseline</th><th>relMSE ÷ baseline at equal rays</th>
<th>posterior std</th></tr>{''.join(rows)}</table>
{bias}{settings}"""


def _learning_section(scene: SceneResult, colours: dict) -> str:
    """Estimators that learn their pdf: relMSE at a fixed spp against the
    training before it (learning.py)."""
    rows, charts_ = [], []
    for learned in scene.learning:
        first = learned.points[0]
        for p in learned.points:
            change = f"{p.relmse / first.relmse:.2f}" if first.relmse > 0 else "—"
            rows.append(f"<tr><td>{swatch(learned.name, colours)}</td><td>{p.passes}</td>"
                        f"<td>{p.training_spp}</td><td>{p.relmse:.3g} [{p.relmse_low:.3g}, "
                        f"{p.relmse_high:.3g}]</td><td>{change}</td>"
                        f"<td>{p.seconds * 1e3:.0f} ms</td></tr>")
        charts_.append(charts.learning_curve(learned, colours))
    l0 = scene.learning[0]
    return f"""
<h3>Learning: error against training</h3>
<p>An estimator that learns its pdf while it renders, at {l0.spp} spp in the image and
{l0.renders} renders per point: its relMSE (less the reference's share, 95 % interval)
after 0, 1, 2, … training passes of doubling spp. The image's own samples are the same
at every point; only what was learned before them changes, so a falling curve is the
learning paying off per sample, and where it flattens more training buys nothing.
Without training it renders as its fallback (<code>mis</code> for
<code>guided_path</code>). The time of a render includes its training.</p>
<table><tr><th>estimator</th><th>passes</th><th>training spp</th><th>relMSE [95 %]</th>
<th>÷ no training</th><th>time per render</th></tr>{''.join(rows)}</table>
{''.join(charts_)}"""


def _settings(q, colours: dict) -> str:
    """How an estimator chose its settings: the choice, and where the
    candidates were scored, their held-out error against ℓ."""
    st = q.settings
    text = (f"<p>{swatch(q.name, colours)} settings: {html.escape(st.mapping)} nodes, "
            f"σ_n²/σ² = {st.noise:g}, ℓ = {st.length_scale:.3g} "
            f"({html.escape(st.source)})"
            + (f"; posterior variance × {st.calibration:.3g}, the factor that makes it "
               "predict the held-out errors spp does not average away"
               if st.calibration != 1.0 else "") + ".")
    glossy = _glossy_settings(st.glossy, q.directions) if st.glossy else ""
    if not st.candidates:
        return text + glossy + "</p>"
    return (text + " Each candidate is scored by the relative squared error a pixel of "
            f"{st.spp} spp gets on known integrals (the environment map about the normals "
            "the camera sees, as the source says); the least error wins where it beats "
            "the safe candidate "
            "(largest σ_n²/σ² and ℓ: nearly equal weights) by more than two standard "
            "errors (the chart below)." + glossy + "</p>" + charts.settings_curve(q))


def _glossy_settings(g, n: int) -> str:
    """The two sets of a glossy shading point, in a sentence."""
    scored = (f"chosen the same way on the lobes about the mirror directions the camera "
              f"sees, scored at exponent {g.lobe_exponent:.3g}"
              if g.lobe_exponent is not None else "defaults: no map to score them on")
    return (f" On glossy surfaces its directions form two sets: {n - g.lobe_directions} "
            f"about the normal ({html.escape(g.diffuse_mapping)} nodes, "
            f"σ_n²/σ² = {g.diffuse_noise:g}, ℓ = {g.diffuse_length_scale:.3g}, chosen for "
            f"that many) and {g.lobe_directions} about the mirror direction in the lobe "
            f"(σ_n²/σ² = {g.lobe_noise:g}, ℓ = {g.lobe_length_scale:.3g} lobe widths; "
            f"{scored}; posterior variance × {g.lobe_calibration:.3g}).")



def _scaling(ev: float) -> str:
    """The tone mapping's scale factor as the page writes it: ``x`` when the
    exposure rounds to 0 (not ``x·2^-0.0``), else ``x·2^ev``."""
    return "x" if abs(ev) < 0.05 else f"x·2<sup>{ev:+.1f}</sup>"


def _timed_on(sp) -> str:
    if not sp.timed_on:
        return ""
    return (f" Every render of this stage was timed alone on "
            f"{html.escape(', '.join(sp.timed_on))}.")


def _load(sp) -> str:
    """A warning where other processes loaded the machine while this stage's
    renders were timed (results before minor version 9 say nothing)."""
    if not getattr(sp, "loaded", False):
        return ""
    return (f"<p class=loaded>The machine was loaded: other processes used "
            f"{sp.others_cores:.2f} of its {sp.cores} cores on average while these renders "
            "were timed. The times below are a loaded machine's; the estimators were "
            "interleaved, so their ratios hold while the load was steady. Run again on a "
            "quiet machine to compare with other runs.</p>")


@dataclass(frozen=True)
class Display:
    """A scene's equal-time renders as the report shows them: the viewer's
    images (the reference first) and their data as the viewer writes them
    (viewer.packed: encoded once, for the page's budget and the page), the
    exposure, each estimator's relative error map against the reference,
    and their estimators."""
    shown: list
    blobs: list
    exposure: float
    errors: list
    names: list

    def viewer_bytes(self) -> int:
        """What the viewer's data of every image take on the page."""
        return text_bytes(self.blobs)


def display(scene: SceneResult, run_dir: str, colours: dict) -> Display | None:
    """The speed stage's images of ``scene`` (None without the stage)."""
    sp = scene.speed
    if sp is None:
        return None
    d = layout.display_dir(run_dir, scene.name)
    ref, _ = files.read_exr(os.path.join(d, "reference.exr"))
    names = list(sp.budgets[-1].estimators)
    shown = [Shown("reference", f"reference (path), {sp.reference.spp} spp", ref)]
    for n in names:
        x, meta = files.read_exr(os.path.join(d, f"{n}.exr"))
        flip = sp.mean_flip.get(n, np.nan)
        shown.append(Shown(n, f"{swatch(n, colours)}: {meta['spp']} spp, "
                              f"{meta['render_seconds'] * 1e3:.0f} ms"
                              + ("" if np.isnan(flip) else f", mean FLIP {flip:.3f}"), x,
                           None if np.isnan(flip) else
                           files.read_exr(os.path.join(d, f"{n}.exr"), "flip")[0][..., 0]))
    shown[1:] = [dataclasses.replace(s, test=_test(run_dir, scene, s.label)) for s in shown[1:]]
    errors = [metrics.relative_error_map(s.pixels, ref) for s in shown[1:]]
    return Display(shown, packed(shown), images.exposure_for(ref), errors, names)


def _test(run_dir: str, scene: SceneResult, name: str) -> Test | None:
    """``name``'s per-pixel unbiasedness test on the statistics film (the p
    layer of its K-render mean, stages/scene.py); None where the run has
    none (not tested, or a run before the layer was written)."""
    path = os.path.join(layout.images_dir(run_dir, scene.name),
                        f"{name}_spp{scene.ladder[-1]}_mean.exr")
    if not os.path.isfile(path):
        return None
    try:
        p, meta = files.read_exr(path, "p")
    except ValueError:                  # (no p layer)
        return None
    return Test(p[..., 0], float(meta["alpha_pixel"]))


def _speed_section(scene: SceneResult, shots: Display, colours: dict,
                   max_bytes: int | None = None) -> str:
    """The speed-and-images stage: equal-time images at the display
    resolution in a viewer (its data within ``max_bytes``), error and FLIP
    maps, the worst region, accuracy against time."""
    sp = scene.speed
    top = sp.budgets[-1]
    names, errors, ev = shots.names, shots.errors, shots.exposure
    positive = np.concatenate([e[e > 0].ravel() for e in errors] + [np.array([1e-3])])
    vmax = max(float(np.percentile(positive, 99)), 1e-2)
    vmin = vmax / 1e3
    means = ", ".join(f"{n} {e.mean():.3g}" for n, e in zip(names, errors))
    flip_means = ", ".join(f"{s.label} {sp.mean_flip[s.label]:.3f}"
                           for s in shots.shown[1:] if s.flip is not None)
    y, x0, size = worst_window(errors)
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in sp.notes)
    ref_info = sp.reference
    capped = f" — capped ({html.escape(ref_info.capped)})" if ref_info.capped else ""
    return f"""
<h3>Equal time at {sp.res}²: {top.seconds * 1e3:.0f} ms per render</h3>
<p>Every estimator got the time Mitsuba's <code>path</code> takes for {top.path_spp} spp;
its spp come from its own cost model t = a + b·spp (a pilot at 1 and 16 spp, in the table
below), corrected where its measured times missed the budget. Reference: <code>path</code>,
{ref_info.spp} spp in {ref_info.passes} passes{capped}.{_timed_on(sp)} Tone mapping: the
viewer starts at {_scaling(ev)}, clipped to [0, 1], sRGB, dithered by half an 8-bit level.
Captions: spp and the measured time of the render shown.</p>
{viewer(f"{scene.name}-viewer", shots.shown, ev, (vmin, vmax), (y, x0, size), max_bytes,
        shots.blobs)}
<p class=desc>Keys 1–9 and 0 (or the buttons, or the arrows) flip between the images at one
zoom and pan; the wheel zooms, a drag pans, a double-click fits. <b>i</b>, <b>e</b>, <b>f</b>:
the image, its relative error |x−r|/(|r|+{metrics.EPSILON}) (mean over channels, the shared
logarithmic scale below), its FLIP map (HDR mode: flip-evaluator tone-maps both images, ACES,
exposures from the reference; 0 = no visible difference). <b>+</b>/<b>−</b>: exposure.
<b>w</b>: the worst region ({size}×{size} px at x={x0}, y={y}, by the relative error summed over
estimators). The data are the renders' own, as half floats. Mean relative error: {means}. Mean FLIP:
{flip_means or 'undefined here (the reference is black)'}.</p>
<div class=row><div class=bar>{charts.colour_bar(vmin, vmax, map_colours(ERROR_LEVELS),
                                  "relative error (shared scale)")}</div>
<div class=bar>{charts.colour_bar(0.0, 1.0, map_colours(FLIP_LEVELS), "FLIP", log=False)}</div></div>
<h4>Accuracy against time</h4>
<div class=row>{charts.error_vs_time(scene, colours)}</div>
{_load(sp)}
{_speed_table(sp, colours)}
{'<ul class=notes>' + notes + '</ul>' if notes else ''}"""


def _speed_table(sp, colours: dict) -> str:
    top = sp.budgets[-1]
    rank = {p.estimator: p for p in sp.ranking}
    rows = []
    for n, run in top.estimators.items():
        c, r, p = sp.cost_model[n], sp.efficiency_vs_path[n], rank.get(n)
        # (issue 66: a figure withheld off its budget is not ranked)
        tied = f" (tie: {', '.join(p.tied_with)})" if p and p.tied_with else ""
        wall = float(np.median(run.wall_seconds)) * 1e3
        tries = (f" <span class=desc>({len(run.tries)} tries)</span>"
                 if len(run.tries) > 1 else "")
        rows.append(
            f"<tr><td>{swatch(n, colours)}</td><td>{p.rank if p else '—'}{html.escape(tied)}</td>"
            f"<td>{html.escape(ratio_text(r))}</td>"
            f"<td>{relmse_text(run, fmt)}</td>"
            f"<td>{run.spp}</td><td class={'ok' if run.on_budget else 'warn'}>{wall:.0f}{tries}</td>"
            f"<td>{c.fixed_s * 1e3:.1f} [{c.fixed_s_ci.low * 1e3:.1f}, "
            f"{c.fixed_s_ci.high * 1e3:.1f}]</td>"
            f"<td>{c.per_spp_s * 1e3:.2f} [{c.per_spp_s_ci.low * 1e3:.2f}, "
            f"{c.per_spp_s_ci.high * 1e3:.2f}]</td></tr>")
    kinds = [f"<li><b>{k}</b>: {html.escape(v)}</li>" for k, v in kinds_shown(sp).items()]
    share = (f"{fmt(top.reference_relmse)} ± {fmt(top.reference_relmse_se)}"
             if top.reference_relmse_se else fmt(top.reference_relmse))
    return f"""<p>At {top.seconds * 1e3:.0f} ms, most efficient first ("=": the 95 % intervals
overlap, a tie): <b>{html.escape(ranking_text(sp.ranking))}</b>. Efficiency is
1/((relMSE − the reference's share)·time): the reference's own noise adds {share} to every
relMSE here, and is taken out. A render whose median missed its budget by more than 10 % was
rendered again at corrected spp ("tries"); the one nearest the budget is shown.</p>
{'<ul class=notes>' + ''.join(kinds) + '</ul>' if kinds else ''}
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
            tested = (_unbiased_cell(u), f"{outcome(c.outcome, c.message)} {slope}")
        rows.append(
            f"<tr id='{evidence_anchor(scene.name, est.name)}'><td>{swatch(est.name, colours)}</td>"
            f"<td>{fmt(top.relmse)} ({fmt(top.relmse / best_rel if best_rel else None, '.2f')}×)</td>"
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
<th>unbiased (pixels passing; image-mean bias ± interval, looks)</th><th>slope [95 % CI]</th></tr>
{''.join(rows)}</table>
<div class=row>{charts.error_vs_spp(scene, colours)}</div>"""


def _unbiased_cell(u) -> str:
    """The unbiasedness verdict, the pixels passing and the image mean's
    bias; where the sun split was tested (results from minor version 14), the
    real map's numbers follow its outcomes: without the sun, and widened."""
    real = f"{100 * u.pass_fraction:.1f} %{_image_bias(u)}"
    s = u.sun
    if s is None:
        return f"{outcome(u.outcome, u.reason)} ({real})"
    widened = (f", with it widened {outcome(s.widened_outcome, s.widened_reason)}"
               if s.widened_outcome else "")
    return (f"{outcome(u.outcome, u.reason)} — sun split: without the sun "
            f"{outcome(s.sunless_outcome, s.sunless_reason)}{widened}; the real map: {real}")


def _image_bias(u) -> str:
    """The sequential test's image-mean bias, its interval and its looks
    (results before minor version 8 have none)."""
    if not u.relative_bias or u.half_width is None:
        return ""
    worst = max(u.relative_bias, key=abs)
    looks = f", {u.looks} looks" if u.looks > 1 else ""
    return f"; {100 * worst:+.2g} ± {100 * u.half_width:.2g} %{looks}"
