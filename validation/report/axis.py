"""The report's budget axis of one scene (stages/budget_axis.py): accuracy
against time from a tenth of a second to a minute, which estimator wins at
each budget, and where one overtakes path."""

from __future__ import annotations

import html

import numpy as np

from mcillum.integrators.core.registry import REFERENCE

from ..results import SceneResult, seconds_text
from . import charts
from .parts import fmt, swatch

plt = charts.plt            # (pyplot, after charts chose the headless backend)


def _cell(p) -> str:
    """One estimator at one budget: efficiency ÷ path [interval], marked
    where the model drew it; its relMSE and spp beneath."""
    if p is None:
        return "<td>—</td>"
    r, ci = p.efficiency_vs_path, p.efficiency_vs_path_ci
    ratio = f"{r:.3g} [{ci.low:.3g}, {ci.high:.3g}]" if r is not None else "1 (path)"
    cls = ""
    if ci is not None:
        cls = " class=ok" if ci.low > 1 else " class=bad" if ci.high < 1 else ""
    how = (f"{p.spp} spp, {p.seconds:.3g} s" if p.measured else "model")
    return (f"<td{cls}>{html.escape(ratio)}<br><span class=desc>relMSE {fmt(p.relmse)}; "
            f"{how}</span></td>")


def axis_section(scene: SceneResult, colours: dict) -> str:
    """The section: two charts (relMSE against time, efficiency ÷ path
    against budget), the leader at each budget, and a table of every
    estimator's efficiency ÷ path at every budget."""
    a = scene.budget_axis
    names = list(a.curves)
    at = {n: {p.budget: p for p in ps} for n, ps in a.curves.items()}
    leaders = []
    for b in a.rankings:
        first = [p.estimator for p in b.ranking if p.rank == 1]
        leaders.append(f"<li><b>{seconds_text(b.seconds)}</b>: "
                       f"{html.escape(first[0])}"
                       + (f" <span class=desc>(tied: {html.escape(', '.join(first[1:]))})</span>"
                          if len(first) > 1 else "") + "</li>")
    crossings = "".join(f"<li>{html.escape(c.text)}</li>" for c in a.crossings) or \
        "<li>no estimator's efficiency crosses path's between these budgets</li>"
    models = "".join(
        f"<li>{html.escape(n)}: c/(t − t₀) fitted up to {seconds_text(m.fitted_to)}, predicted "
        f"{fmt(m.predicted)} at {seconds_text(m.checked_at)} where the measured point agrees; "
        "drawn from it above</li>" for n, m in a.models.items())
    head = "".join(f"<th>{swatch(n, colours)}</th>" for n in names)
    rows = "".join(f"<tr><td>{seconds_text(b)}</td>" + "".join(_cell(at[n].get(b)) for n in names)
                   + "</tr>" for b in a.budgets)
    # (the crossings and leaders are above; summary.md has them as notes)
    said = {c.text for c in a.crossings}
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in a.notes
                    if n not in said and not n.startswith("most efficient at each budget"))
    return f"""
<h3 id="{scene.name}--budgets">Budgets from {seconds_text(a.budgets[0])} to {seconds_text(a.budgets[-1])}
per render at {a.res}²</h3>
<p>Each estimator rendered K = {a.renders} times (more below a second) at each budget,
interleaved; relMSE is that of one render, from the spread of its renders (their per-pixel
variance over r² + ε: no reference can resolve a minute of <code>path</code>, and the scene's
unbiasedness tests above check what the spread cannot see). Path, mis and every estimator that
learns are measured at every budget; another is measured up to {seconds_text(_fitted(a))} and at
the budget after, which checks the model relMSE = c/(t − t₀) it is drawn from above (dashed).
Efficiency is 1/(relMSE·t) at the render's measured time.</p>
<ul class=notes>{crossings}</ul>
<div class=row>{error_vs_budget(scene, colours)}{ratios_vs_budget(scene, colours)}</div>
<p>Most efficient at each budget (ties: intervals that overlap):</p>
<ul class=notes>{''.join(leaders)}</ul>
{'<ul class=notes>' + models + '</ul>' if models else ''}
<table><tr><th>budget</th>{head}</tr>{rows}</table>
<p class=desc>Cells: efficiency ÷ path [95 % interval] (green: above 1 throughout, red: below),
relMSE of one render, spp and median time, or "model".</p>
{'<ul class=notes>' + notes + '</ul>' if notes else ''}"""


# --------------------------------- Charts ---------------------------------------

def error_vs_budget(scene: SceneResult, colours: dict) -> str:
    """The budget axis (stages/budget_axis.py): relMSE of one render against
    its wall time, log-log, from a tenth of a second to a minute. Measured
    points with 95 % intervals (relMSE: bootstrap over tiles; time: the
    range of the K renders) on solid lines; where a fixed-pdf estimator is
    drawn from its checked model c/(t − t0), a dashed line and hollow
    points; the budgets dotted; each crossing of path marked."""
    ax_ = scene.budget_axis
    fig, ax = plt.subplots(figsize=(5.8, 4.2))
    for name, points in ax_.curves.items():
        measured = [p for p in points if p.measured]
        modelled = [p for p in points if not p.measured]
        if measured:
            t = np.array([p.seconds for p in measured])
            e = np.array([p.relmse for p in measured])
            t_err = np.array([[p.seconds - min(p.wall_seconds), max(p.wall_seconds) - p.seconds]
                              for p in measured]).T
            e_err = np.array([[p.relmse - p.relmse_ci.low, p.relmse_ci.high - p.relmse]
                              for p in measured]).T
            ax.errorbar(t, e, yerr=np.maximum(e_err, 0), xerr=np.maximum(t_err, 0), fmt="o-",
                        color=colours[name], label=name, ms=4, capsize=2, lw=1.2)
        if modelled:
            first = measured[-1:] if measured else []
            t = [p.seconds for p in first + modelled]
            e = [p.relmse for p in first + modelled]
            ax.plot(t, e, "--", color=colours[name], lw=1.2,
                    label=None if measured else name)
            ax.plot([p.seconds for p in modelled], [p.relmse for p in modelled], "o",
                    mfc="none", color=colours[name], ms=4)
    for b in ax_.budgets:
        ax.axvline(b, color="#999999", ls=":", lw=1)
    for c in ax_.crossings:
        ax.axvline(c.seconds, color=colours.get(c.estimator, "k"), ls="-.", lw=1, alpha=0.8)
        ax.annotate(f"{c.estimator} {'>' if c.overtakes else '<'} path", (c.seconds, 1.0),
                    xycoords=("data", "axes fraction"), xytext=(3, -12),
                    textcoords="offset points", fontsize=7, rotation=90, va="top",
                    color=colours.get(c.estimator, "k"))
    if ax_.models:
        ax.plot([], [], "k--", lw=1, label="model c/(t − t₀), checked")
    ax.set_xscale("log")
    ax.set_yscale("log")
    return charts.finish(fig, ax, f"wall time per render at {ax_.res}² [s] (budgets dotted)",
                   "relMSE of one render, 95 % interval",
                   f"{scene.name}: accuracy from {ax_.budgets[0]:g} s to {ax_.budgets[-1]:g} s")


def ratios_vs_budget(scene: SceneResult, colours: dict) -> str:
    """Efficiency ÷ path at each budget of the axis, log scale, with 95 %
    intervals as bands; 1 (path) dashed: above it an estimator beats path
    at that budget, and where its line crosses 1 it changes sides."""
    ax_ = scene.budget_axis
    fig, ax = plt.subplots(figsize=(5.8, 3.6))
    for name, points in ax_.curves.items():
        shown = [p for p in points if p.efficiency_vs_path is not None]
        if not shown:
            continue
        b = np.array([p.budget for p in shown])
        v = np.array([p.efficiency_vs_path for p in shown])
        lo = np.array([p.efficiency_vs_path_ci.low for p in shown])
        hi = np.array([p.efficiency_vs_path_ci.high for p in shown])
        ax.plot(b, v, "o-", color=colours[name], label=name, ms=4, lw=1.2)
        ax.fill_between(b, lo, hi, color=colours[name], alpha=0.15, lw=0)
        model = [p for p in shown if not p.measured]
        if model:
            ax.plot([p.budget for p in model], [p.efficiency_vs_path for p in model], "o",
                    mfc="white", color=colours[name], ms=4)
    ax.axhline(1.0, color=colours.get(REFERENCE, "k"), ls="--", lw=1, label="path = 1")
    ax.set_xscale("log")
    ax.set_yscale("log")
    return charts.finish(fig, ax, "budget per render [s]", "efficiency ÷ path, 95 % interval",
                   f"{scene.name}: which estimator wins at which budget")


def _fitted(a) -> float:
    return max((m.fitted_to for m in a.models.values()), default=a.budgets[-1])
