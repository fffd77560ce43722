"""The report's section "Where methods fail": failed and inconclusive
checks, heavy tails and capped references, and each failure case with its
verdicts, numbers and evidence images."""

from __future__ import annotations

import html
import os

import numpy as np

from mcillum import files, images

from ..checks import cases as case_checks
from ..checks import evidence
from ..results import CaseResult, Results, layout
from ..stats import tails
from . import charts
from .parts import fmt, img, render, swatch


def failures_section(res: Results, run_dir: str, colours: dict) -> str:
    items = "".join(f"<li><code>{html.escape(c.id)}</code>: {html.escape(c.message)}</li>"
                    for c in res.failed) or "<li>No check failed in this run.</li>"
    unsure = "".join(f"<li><code>{html.escape(c.id)}</code>: {html.escape(c.message)}</li>"
                     for c in res.inconclusive)
    unsure = (f"<h3>Inconclusive at this budget</h3><p>The sequential test rendered on to "
              f"its budget and could not decide: a difference that a heavy tail can still "
              f"explain (an estimator darker where its renders have not yet seen the tail, or "
              f"a sun not yet hit), an interval on the bias wider than ±ε, or a rejection "
              f"that did not come back on fresh renders: neither biased nor shown unbiased. "
              f"Each line says the samples per pixel reached and about how many would "
              f"decide (<code>--budget</code>).</p><ul>{unsure}</ul>") if unsure else ""
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


VERDICT_CLASS = {"fine": "ok", "heavy-tailed": "warn", evidence.HEAVY: "warn",
                 evidence.NOT_REPLICATED: "warn", "K too small to tell": "warn",
                 "refused": "ok", "biased (opt-in)": "warn", "biased": "bad",
                 evidence.BY_DESIGN: "warn",
                 "non-finite/negative": "bad"}


def _failure_case(case: CaseResult, run_dir: str, colours: dict) -> str:
    """One case of the failures group: verdicts, numbers, evidence images."""
    case_dir = layout.case_dir(run_dir, case.id)
    ref_file = os.path.join(case_dir, "reference.exr")
    ref = files.read_exr(ref_file)[0] if os.path.isfile(ref_file) else None
    ev = images.exposure_for(ref) if ref is not None else 0.0
    figs = [] if ref is None else [img(render(images.tonemap(ref, ev)), "reference (path)", 96)]
    rows = []
    for est in case.estimators:
        for label, f in est.images.items():
            x = files.read_exr(os.path.join(case_dir, f))[0]
            figs.append(img(render(images.tonemap(x, ev)), f"{est.name}<br>{label} seed", 96))
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
    name = f"<td>{swatch(est.name, colours)}</td>"
    v = est.verdict
    cls = VERDICT_CLASS.get(v, "")
    if case.sweep is not None:
        cells = "".join(f"<td>{fmt(r)}</td>" for r in est.relmse)
        return (f"<tr>{name}{cells}<td>×{fmt(est.growth)}</td>"
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
    decided = case_checks.widened_decided(n.sun)
    if decided:                     # the widened sun decided: say so first
        evidence.append(f"decided {case_checks.widened_words(n.sun)}")
    if n.sun is not None:
        hits = n.sun.expected_sun_hits_per_pixel
        evidence.append(
            f"without the sun ({n.sun.sun['solid_angle']:.2g} sr, "
            f"{100 * n.sun.sun_share_of_image:.0f} % of the image): "
            + ("not biased" if n.sun.sunless_passed else "BIASED")
            + (f"; at most {hits:.2g} sun hits/pixel" if hits is not None else ""))
    if t is not None and t.reason and t.outcome != "pass":
        evidence.append(("the real sun: " if decided else "") + t.reason)
    if n.sun is not None and n.sun.sunless_reason and not n.sun.sunless_passed:
        evidence.append(f"without the sun: {n.sun.sunless_reason}")
    if n.sun is not None and n.sun.widened_outcome and not decided:
        evidence.append(case_checks.widened_words(n.sun))
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
    if t is not None and t.looks > 1:
        evidence.append(f"sequential: {t.looks} looks, {fmt(t.samples_per_pixel)} samples "
                        "per pixel")
    spp = (f"{fmt(match.spp)} [{fmt(match.low)}, {fmt(match.high)}]"
           if match else "never (biased)")
    return (f"<tr>{name}<td class={cls}>{html.escape(v)}</td>"
            f"<td>{fmt(rel.median)} / {fmt(rel.p90)} / {fmt(rel.p99)} / "
            f"{fmt(rel.max)}</td><td>{100 * n.firefly_fraction:.3f} %</td>"
            f"<td>{spp}</td><td>{html.escape('; '.join(evidence))}</td></tr>")
