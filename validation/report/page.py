"""The reference-comparison report: one self-contained HTML page.

Reads the run's :class:`~mcillum.validation.results.Results`
(``DIR/results.json``) and the EXR images beside it, renders nothing, and
writes ``DIR/report/index.html``: at the top what needs attention and the
estimators × scenes matrix (:mod:`.overview`); per scene a viewer of the
equal-time renders as half floats (:mod:`.viewer`); small pictures as data
URIs (AVIF where that keeps their noise, else lossless WebP or PNG, see
:mod:`.parts`); charts as inline SVG; inline CSS and one inline script; a
Content-Security-Policy that forbids every external request.

Tone mapping, the same for every image of a scene: x · 2^EV, clipped to
[0, 1], sRGB curve; EV puts the reference's 99th-percentile channel value at 1.
Error maps: :func:`metrics.relative_error_map`, |x − r| / (|r| + 0.01) per
pixel (channel mean), on one shared logarithmic colour scale per scene, in
16 steps; FLIP maps on FLIP's linear scale in 48 (:mod:`.parts`).
"""

from __future__ import annotations

import html
import os
import time

from mcillum import files
from mcillum.errors import UserError
from mcillum.integrators.core.scene_checks import KIND_NAMES

from .. import results
from ..results import Results, layout
from ..stats import metrics
from . import charts, overview, viewer
from .failures import failures_section
from .parts import swatch
from .scenes import display, scene_section


def _executor(where: dict) -> str:
    """Where the renders ran (results ``executor``), in a few words."""
    if where.get("kind") != "ray":
        return "rendered in one process"
    nodes = len(where.get("nodes", []))
    return (f"rendered on Ray ({where.get('workers', '?')} workers on {nodes} "
            f"node{'s' if nodes != 1 else ''})")



def _estimators(res: Results, colours: dict) -> str:
    """The estimators of the run: name, what they are, what they cannot reach."""
    rows = "".join(
        f"<tr><td>{swatch(name, colours)}</td><td>{html.escape(f.display_name)}</td>"
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
.loaded{background:#fff4e0;padding:6px 10px;border-radius:4px}
"""


#: The bytes the viewers' data may take on one page, all scenes together: the
#: renders are most of a page, and a page of much over 10 MB is slow to open
#: and to mail. The full profile's exact renders would take about 15 MB.
VIEWER_BYTES = 6_000_000


def allot(wanted: list[int], budget: int) -> list[int | None]:
    """Each scene's limit on its viewer's data: an equal share of ``budget``,
    where a scene that needs less leaves the rest to the others; None (no
    limit) where all fit."""
    if sum(wanted) <= budget:
        return [None] * len(wanted)
    limits, left = [0] * len(wanted), budget
    order = sorted(range(len(wanted)), key=wanted.__getitem__)
    for k, i in enumerate(order):
        limits[i] = min(wanted[i], left // (len(order) - k))
        left -= limits[i]
    return [None if limits[i] >= wanted[i] else limits[i] for i in range(len(wanted))]


def build(run_dir: str, res: Results | None = None) -> str:
    """Write ``run_dir/report/index.html`` from ``res`` (read from
    ``run_dir/results.json`` when not given); return its path. Raises
    UserError naming an image of the run that is missing."""
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
    # (a run without a speed stage, e.g. failure cases only, has nothing to sum up)
    timed = any(s.speed is not None for s in res.scenes)
    contents = " · ".join(['<a href="#attention">needs attention</a>']
                          + (['<a href="#matrix">estimators × scenes</a>'] if res.scenes else [])
                          + ([f"Scenes: {toc}"] if res.scenes else [])
                          + ['<a href="#failures">where methods fail</a>']
                          + (['<a href="#summary">summary</a>'] if timed else []))
    summary = (f'<section id="summary"><h2>Summary across scenes</h2>'
               f'{charts.efficiency_summary(res, colours)}</section>') if timed else ""
    by_design = {n for n, f in res.estimator_facts.items() if not f.unbiased}
    shots = [display(s, run_dir, colours) for s in res.scenes]
    limits = allot([0 if d is None else d.viewer_bytes() for d in shots], VIEWER_BYTES)
    body = "".join(scene_section(s, run_dir, colours, by_design, d, limit)
                   for s, d, limit in zip(res.scenes, shots, limits))
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'">
<title>mcillum validation report</title><style>{CSS}{overview.CSS}{viewer.CSS}</style></head><body>
<h1>mcillum: estimators against Mitsuba's path tracer</h1>
<p>{html.escape(res.created)} · {html.escape(m['platform'])}, {m['cpus']} CPUs ·
variant <code>{html.escape(res.variant)}</code> · mitsuba {html.escape(res.mitsuba_version)},
drjit {html.escape(res.drjit_version)} · profile <b>{html.escape(res.profile)}</b> ·
{_executor(res.executor)} · {html.escape(results.wall_text(res))} · report written {time.strftime('%Y-%m-%d %H:%M')}</p>
<p class="verdict {verdict[0]}">{verdict[1]}</p>
<p>{contents}</p>
{overview.attention(res, run_dir)}
{overview.matrix(res, colours)}
<p>Each estimator renders every scene K times per spp; Mitsuba's <code>path</code> at the same
max_depth is the reference. Unbiasedness: per-pixel Welch tests with each side's own variance
(Šidák-corrected) and an image-mean test, family-wise α = {res.alpha} spent over the looks of
a sequential test that renders on until it decides; a pass means the image mean is unbiased
within the profile's ±ε, which each check's message states.
relMSE = mean (x−r)²/(r²+{metrics.EPSILON}); efficiency = 1/(relMSE·time).</p>
{_estimators(res, colours)}
{body}
{failures_section(res, run_dir, colours)}
{summary}
<script>{viewer.SCRIPT}</script>
</body></html>
"""
    target = layout.report_html(run_dir)
    layout.made(os.path.dirname(target))
    files.write_text(target, page)
    return target
