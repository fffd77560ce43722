"""The top of the report: what needs a reader's eye, then the whole run in
one table.

*Needs attention* lists every failed and inconclusive check with its reason
in a line, a link to its evidence and, where the check is a scene's, the
pixels that decided it: the statistics film's mean of K renders against the
reference, as relative error. *Estimators × scenes* gives each pair its
verdict (the worst of its checks) and, where the speed stage ran, its
efficiency ÷ path with the 95 % interval, coloured by which side of 1 the
interval lies.
"""

from __future__ import annotations

import html
import os
import re

from mcillum import files, images

from ..results import Check, Results, layout, ratio_text
from ..stats import metrics
from .parts import error_map, img, render, swatch

# A verdict as a glyph and its class (page.CSS): worst first.
GLYPHS = {"fail": ("✗", "bad"), "inconclusive": ("?", "warn"), "pass": ("✓", "ok")}
REFUSED = ("—", "desc")        # the estimator refuses the scene (its facts say why)
BY_DESIGN = ("≈", "warn")      # biased by design: not tested for unbiasedness
ORDER = ("fail", "inconclusive", "pass")
REASON_CHARS = 220             # a reason in one line; the whole one on hover


def evidence_anchor(scene: str, estimator: str) -> str:
    """The id of a scene's statistics row of ``estimator`` (scenes.py)."""
    return f"{scene}--{estimator}"


def _split(check: Check) -> tuple[str, str, str]:
    """(scene or case, estimator, what) of a check id; '' where absent."""
    parts = check.id.split("/")
    return (parts[0], parts[1] if len(parts) > 2 else "", parts[-1])


def _one_line(message: str) -> str:
    text = " ".join(message.split())
    return text if len(text) <= REASON_CHARS else text[:REASON_CHARS - 1] + "…"


def _decided(run_dir: str, scene, estimator: str) -> str:
    """The statistics film of ``estimator`` on ``scene``: reference, mean of
    K renders, and their relative error; '' where the images are absent."""
    d = layout.images_dir(run_dir, scene.name)
    mean_file = os.path.join(d, f"{estimator}_spp{scene.ladder[-1]}_mean.exr")
    ref_file = os.path.join(d, "reference.exr")
    if not (os.path.isfile(mean_file) and os.path.isfile(ref_file)):
        return ""
    ref, mean = files.read_exr(ref_file)[0][..., :3], files.read_exr(mean_file)[0][..., :3]
    ev = images.exposure_for(ref)
    err = metrics.relative_error_map(mean, ref)
    vmax = max(float(err.max()), 1e-3)
    return (img(render(images.tonemap(ref, ev)), "reference", 72)
            + img(render(images.tonemap(mean, ev)), f"mean of {scene.renders}", 72)
            + img(error_map(err, vmax / 1e3, vmax), f"rel. error, max {vmax:.2g}", 72))


def attention(res: Results, run_dir: str) -> str:
    """The failed, then the inconclusive checks, each with its reason, a link
    to its evidence and (a scene's check) the pixels that decided it."""
    scenes = {s.name: s for s in res.scenes}
    cases = {c.id for c in res.failures}
    items = []
    for check in res.failed + res.inconclusive:
        where, est, what = _split(check)
        glyph, cls = GLYPHS[check.outcome]
        if where in scenes and est:
            link, crop = f"#{evidence_anchor(where, est)}", _decided(run_dir, scenes[where], est)
        else:
            link, crop = (f"#{where}" if where in cases else "#failures"), ""
        items.append(
            f"<li class=att><span class={cls}>{glyph}</span> <a href='{html.escape(link)}'>"
            f"<code>{html.escape(check.id)}</code></a> "
            f"<span title='{html.escape(check.message, quote=True)}'>"
            f"{html.escape(_one_line(check.message))}</span>"
            + (f"<div class=row>{crop}</div>" if crop else "") + "</li>")
    if not items:
        return ("<section id=attention><h2>Needs attention</h2><p class=ok>Nothing: every "
                f"check of the {len(res.checks)} passed.</p></section>")
    return ("<section id=attention><h2>Needs attention</h2><p>Every failed, then every "
            "inconclusive check: its reason (the whole of it on hover), a link to its "
            "evidence and, for a scene's check, its statistics film: the mean of K renders "
            "against the reference.</p>"
            f"<ul class=attention>{''.join(items)}</ul></section>")


def _verdict(checks: list[Check]) -> tuple[str, str, str]:
    """(glyph, class, title) of the worst of ``checks``."""
    for o in ORDER:
        mine = [c for c in checks if c.outcome == o]
        if mine:
            glyph, cls = GLYPHS[o]
            title = "; ".join(f"{_split(c)[2]}: {_one_line(c.message)}" for c in mine)
            return glyph, cls, title
    return "", "", ""


def _efficiency(ratio) -> tuple[str, str, str]:
    """(value, what qualifies it, class) of an efficiency ÷ path: the class
    ok where its interval lies above 1, bad where below, plain where it
    straddles 1 or is a bound."""
    text = ratio_text(ratio)
    if ratio is None or text == "—":
        return "", "", ""
    if ratio.kind == "off_budget":                   # (the reason: on hover)
        return "withheld", "(off its time budget)", ""
    # the value ("0.48", "≤ 3e-05", "≥ 2.1"), then its interval or what bounds it
    head, rest = re.match(r"(.*?)(?: ([\[(].*))?$", text).groups()
    rest = rest or ""
    if ratio.kind != "unbiased":
        return head, rest, ""
    low, high = ratio.ci.low, ratio.ci.high
    return head, rest, "effup" if low > 1 else "effdown" if high < 1 else ""


def matrix(res: Results, colours: dict) -> str:
    """Estimators (rows) × scenes (columns): verdict glyph and efficiency ÷
    path; each cell links to that scene's row of that estimator."""
    if not res.scenes:
        return ""
    by_design = {n for n, f in res.estimator_facts.items() if not f.unbiased}
    checks: dict[tuple[str, str], list[Check]] = {}
    for c in res.checks:
        where, est, _ = _split(c)
        checks.setdefault((where, est), []).append(c)
    names = list(res.estimator_facts) or sorted({e.name for s in res.scenes
                                                 for e in s.estimators})
    head = "".join(f"<th><a href='#{html.escape(s.name)}'>{html.escape(s.name)}</a></th>"
                   for s in res.scenes)
    rows = []
    for n in names:
        cells = []
        for s in res.scenes:
            rendered = any(e.name == n for e in s.estimators)
            if not rendered:
                cells.append(f"<td class=cell title='{html.escape(n)} does not render "
                             f"{html.escape(s.name)} (see its notes)'><span class="
                             f"{REFUSED[1]}>{REFUSED[0]}</span></td>")
                continue
            glyph, cls, title = _verdict(checks.get((s.name, n), []))
            if n in by_design and cls != "bad":
                glyph, cls, title = BY_DESIGN[0], BY_DESIGN[1], "biased by design: " + title
            value, detail, eff_cls = "", "", ""
            if s.speed is not None and n in s.speed.efficiency_vs_path and n != "path":
                ratio = s.speed.efficiency_vs_path[n]
                value, detail, eff_cls = _efficiency(ratio)
                if ratio.kind == "off_budget":
                    title = f"{title}; efficiency {ratio_text(ratio)}"
            cells.append(
                f"<td class='cell {eff_cls}' title='{html.escape(title, quote=True)}'>"
                f"<a href='#{html.escape(evidence_anchor(s.name, n))}'><span class={cls}>"
                f"{glyph}</span> {html.escape(value)}"
                + (f"<br><small>{html.escape(detail)}</small>" if detail else "")
                + "</a></td>")
        rows.append(f"<tr><th>{swatch(n, colours)}</th>{''.join(cells)}</tr>")
    return f"""<section id=matrix><h2>Estimators × scenes</h2>
<p>Each cell: the worst verdict of that estimator's checks on that scene (✓ pass, ✗ fail,
? inconclusive, ≈ biased by design, — refused: the scene holds what it cannot reach) and,
where the speed stage ran, its efficiency ÷ path at the largest budget with its 95 %
interval: <span class=effup>green</span> where the whole interval lies above 1,
<span class=effdown>red</span> where below. Hover for the checks' reasons; click for the
evidence.</p>
<div class=wide><table class=matrix><tr><th>estimator</th>{head}</tr>{''.join(rows)}</table></div>
</section>"""


CSS = """
.attention{padding-left:18px} .att{margin:6px 0} .att .row{margin:4px 0 0}
.wide{overflow-x:auto} .matrix td.cell{text-align:left;font-size:12px;min-width:70px}
.matrix td.cell small{color:#555} .matrix th{white-space:nowrap}
.matrix a{color:inherit;text-decoration:none} .matrix th{text-align:left;font-weight:normal}
.matrix tr:first-child th{font-weight:bold}
.effup{background:#e6f4ea} .effdown{background:#fdecea}
"""

