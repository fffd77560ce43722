"""The run's files for people and CI: results.csv (one row per scene ×
estimator × spp), summary.md (the verdict, then a table per scene and the
failures group) and JUnit XML (one test case per check)."""

from __future__ import annotations

import csv
import io
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from mcillum import files

from . import layout
from .cases import CaseResult
from .learning import Learning
from .quadrature import Quadrature
from .run import Results
from .speed import KINDS, Placement, Speed


CSV_FIELDS = ["scene", "estimator", "spp", "renders", "relmse", "mse", "mape", "bias",
              "bias_se", "variance_per_render", "nonfinite_fraction", "median_seconds",
              "samples_per_second", "efficiency"]


def write_csv(path: str, results: Results) -> None:
    """results.csv: one row per scene × estimator × spp."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, CSV_FIELDS)
    w.writeheader()
    for scene in results.scenes:
        for est in scene.estimators:
            for run in est.runs:
                w.writerow({"scene": scene.name, "estimator": est.name,
                            **{k: getattr(run, k) for k in CSV_FIELDS[2:]}})
    files.write_text(path, buf.getvalue())


def counts_line(results: Results) -> str:
    """One line for CI logs: ``pass P, fail F, inconclusive I of N checks``."""
    n = results.counts()
    return (f"pass {n['pass']}, fail {n['fail']}, inconclusive {n['inconclusive']} "
            f"of {len(results.checks)} checks")


def summary(results: Results) -> str:
    """summary.md: the verdict, then a table per scene and the failures group."""
    checks, failed, n = results.checks, results.failed, results.counts()
    lines = [f"# mcillum validation — profile {results.profile}: {counts_line(results)}",
             "",
             f"{n['pass']} of {len(checks)} checks pass, {n['inconclusive']} inconclusive, "
             f"{n['fail']} fail; "
             f"{results.variant}, mitsuba {results.mitsuba_version}, "
             f"drjit {results.drjit_version}, {wall_text(results)}.", ""]
    for scene in results.scenes:
        ref = scene.reference
        capped = f", capped: {ref.capped}" if ref.capped else ""
        lines += [f"## {scene.name} ({scene.res}², max_depth {scene.max_depth})",
                  "", f"Reference: `path`, {ref.spp} spp in {ref.passes} passes{capped}.",
                  "", *(f"- {n}" for n in scene.notes or ()), *([""] if scene.notes else []),
                  "| estimator | relMSE @ top spp | bias ± se | unbiased (pass %) | slope [95% CI] "
                  "| samples/s | efficiency |",
                  "|---|---|---|---|---|---|---|"]
        for est in scene.estimators:
            top, u, c = est.top, est.unbiasedness, est.convergence
            facts = results.estimator_facts.get(est.name)
            by_design = facts is not None and not facts.unbiased
            lines.append(
                f"| {est.name} | {top.relmse:.3g} | {top.bias:+.2e} ± {top.bias_se:.1e} | "
                + ("biased by design " if by_design else f"{_word(u.outcome)} ")
                + f"({100 * u.pass_fraction:.1f})"
                + (f" split: {u.sun.sunless_outcome}/{u.sun.widened_outcome or '–'}"
                   if u.sun is not None else "") + " | "
                + ("exact" if c.exact else
                   ("not tested " if by_design else f"{_word(c.outcome)} ") +
                   f"{c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]")
                + f" | {top.samples_per_second / 1e6:.2f} M | {top.efficiency:.3g} |")
        if scene.speed:
            lines += ["", *speed_summary(scene.speed)]
        if scene.budget_axis:
            lines += ["", *axis_summary(scene.budget_axis)]
        for q in scene.quadrature or []:
            lines += ["", quadrature_summary(q)]
        for learned in scene.learning or []:
            lines += ["", learning_summary(learned)]
        lines.append("")
    if results.failures:
        lines += ["## Where methods fail", "",
                  "| case | estimator | verdict | relMSE median / p99 / max | fireflies "
                  "| spp to match path |", "|---|---|---|---|---|---|"]
        for case in results.failures:
            for est in case.estimators:
                lines.append(f"| {case.label} | {est.name} | {est.verdict} | "
                             f"{_failure_cells(case, est)} |")
        lines.append("")
    if failed:
        lines += ["## Failed checks", ""] + [f"- `{c.id}`: {c.message}" for c in failed]
    if results.inconclusive:
        lines += ["", "## Inconclusive at this budget", ""] + \
            [f"- `{c.id}`: {c.message}" for c in results.inconclusive]
    return "\n".join(lines) + "\n"


def write_summary(run_dir: str, results: Results) -> None:
    """``run_dir/summary.md`` (:func:`summary`)."""
    files.write_text(layout.summary_md(run_dir), summary(results))


def _word(outcome: str) -> str:
    """pass, **FAIL** or *inconclusive* for summary.md."""
    return {"fail": "**FAIL**", "inconclusive": "*inconclusive*"}.get(outcome, outcome)


def ranking_text(ranking: list[Placement]) -> str:
    """"a > b = c > d": ">" where the intervals separate, "=" for a tie."""
    out = ""
    for i, p in enumerate(ranking):
        if i:
            tied = ranking[i - 1].estimator in p.tied_with
            out += " = " if tied else " > "
        out += p.estimator
    return out


def quadrature_summary(q: Quadrature) -> str:
    """One line of what the quadrature stage measured of ``q.name``."""
    parts = []
    if q.equal_rays:
        r = q.equal_rays
        parts.append(f"relMSE {r.ratio:.3g}× {r.baseline}'s at equal rays "
                     f"[{r.ratio_low:.3g}, {r.ratio_high:.3g}]")
    if q.bias:
        parts.append("rms bias " + ", ".join(f"{100 * b.rms_bias:.2f} % at N = {b.directions}"
                                             for b in q.bias))
    if q.calibration:
        c = q.calibration
        parts.append(f"posterior std {c.verdict} (RMSE/std median {c.median:.2f}"
                     + (f" at {c.spp} spp)" if c.spp else ")"))
    return f"{q.name} (N = {q.directions}, {q.spp} spp): " + "; ".join(parts) + "."


def learning_summary(learned: Learning) -> str:
    """One line of what the learning stage measured of ``learned.name``."""
    first, last = learned.points[0], learned.points[-1]
    steps = ", ".join(f"{p.relmse:.3g} after {p.training_spp}" for p in learned.points)
    change = f"{last.relmse / first.relmse:.2f}×" if first.relmse > 0 else "—"
    return (f"{learned.name} learning ({learned.spp} spp in the image): relMSE {steps} "
            f"training spp; the last {change} the first.")


def wall_text(results: Results) -> str:
    """The run's wall time, a re-run's own where it rendered nothing, and
    the machine's time for the fixed workload where it was probed
    (run/probe.py)."""
    again = (f" (re-run into the finished directory: {results.rerun_seconds:.0f} s, "
             "nothing rendered)" if results.rerun_seconds is not None else "")
    speed = results.machine.get("speed")
    probe = (f" (this machine renders {speed['workload']} in {speed['seconds'] * 1e3:.0f} ms)"
             if speed else "")
    return f"{results.wall_seconds:.0f} s{again}{probe}"


def ratio_text(r) -> str:
    """An efficiency ratio (speed.Ratio) as the summary and the report show
    it: "0.48 [0.39, 0.59]"; a lower bound as "≥ 2.1 (reference-limited)"
    (the error is the reference's noise) or "≥ 0.02 (its relMSE too
    uncertain …)" (rare large errors); an upper bound as "≤ 3e-05
    (heavy-tailed)" (fireflies its renders cannot bound); an estimator
    biased by design's with "(biased: this budget only)"; one withheld off
    its budget as "withheld: <reason>"."""
    if r is not None and r.kind == "off_budget":
        return f"withheld: {r.reason or 'off budget'}"
    if r is None or not np.isfinite(r.ratio):
        return "—"
    if r.kind == "heavy_tailed":
        return (f"≤ {r.ci.high:.3g} (heavy-tailed)" if np.isfinite(r.ci.high) else
                f"{r.ratio:.3g}, unbounded either way (heavy-tailed)")
    if not np.isfinite(r.ci.high):          # (the net relMSE may be 0)
        why = ("reference-limited" if r.kind == "reference_limited"
               else "its relMSE too uncertain for an upper end")
        return f"≥ {r.ci.low:.3g} ({why})"
    text = f"{r.ratio:.3g} [{r.ci.low:.3g}, {r.ci.high:.3g}]"
    extra = {"reference_limited": " (reference-limited)",
             "biased": " (biased: this budget only)"}.get(r.kind, "")
    return text + extra


def relmse_text(run, number=lambda x: f"{x:.3g}") -> str:
    """A budget run's relMSE and its 95 % interval, "0.21 [0.14, 0.28]"; one
    with a lower bound only (heavy-tailed fireflies, stats/tails.py) as
    "0.21 [0.14, ∞)". ``number`` formats each figure."""
    high = run.relmse_ci.high
    end = f"{number(high)}]" if np.isfinite(high) else "∞)"
    return f"{number(run.relmse)} [{number(run.relmse_ci.low)}, {end}"


def speed_summary(speed: Speed) -> list[str]:
    """The speed stage's lines of summary.md: budgets, ratios, ranking, notes."""
    top = speed.budgets[-1]
    lines = [f"Equal time at {speed.res}² ({', '.join(f'{b.seconds * 1e3:.0f}' for b in speed.budgets)}"
             f" ms per render, K = {speed.renders}); at {top.seconds * 1e3:.0f} ms, most "
             f"efficient first: {ranking_text(speed.ranking)}.", "",
             "| estimator | spp | wall ms (median) | relMSE [95% CI] | efficiency ÷ path [95% CI] |",
             "|---|---|---|---|---|"]
    for name, run in top.estimators.items():
        ratio = ratio_text(speed.efficiency_vs_path.get(name))
        wall = sorted(run.wall_seconds)[len(run.wall_seconds) // 2] * 1e3
        lines.append(f"| {name} | {run.spp} | {wall:.0f}{'' if run.on_budget else ' (off budget)'}"
                     f" | {relmse_text(run)}"
                     f" | {ratio} |")
    return lines + [f"- {n}" for n in speed.notes] + \
        [f"- efficiency: {k}: {v}" for k, v in kinds_shown(speed).items()]


def axis_summary(axis) -> list[str]:
    """The budget axis's lines of summary.md: efficiency ÷ path per budget,
    then its crossings, leaders and notes (stages/budget_axis.py)."""
    names = [n for n in axis.curves if n != "path"]
    lines = [f"Budgets from {axis.budgets[0]:g} s to {axis.budgets[-1]:g} s per render at "
             f"{axis.res}² (K = {axis.renders}): efficiency ÷ path [95% CI]; (model): drawn "
             "from the estimator's checked model c/(t − t0).", "",
             "| budget | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for b in axis.budgets:
        cells = []
        for n in names:
            p = next((p for p in axis.curves[n] if p.budget == b), None)
            cells.append("—" if p is None or p.efficiency_vs_path is None else
                         f"{p.efficiency_vs_path:.3g} [{p.efficiency_vs_path_ci.low:.3g}, "
                         f"{p.efficiency_vs_path_ci.high:.3g}]" + ("" if p.measured else
                                                                   " (model)"))
        lines.append(f"| {b:g} s | " + " | ".join(cells) + " |")
    return lines + [f"- {n}" for n in axis.notes]


def kinds_shown(speed: Speed) -> dict[str, str]:
    """What the stage's efficiency figures other than plain unbiased ones
    mean (KINDS), by the name the page and summary give them."""
    found = {r.kind for r in speed.efficiency_vs_path.values()}
    return {k.replace("_", "-"): v for k, v in KINDS.items() if k != "unbiased" and k in found}


def _failure_cells(case: CaseResult, est) -> str:
    if case.sweep is not None:
        return (f"relMSE {', '.join(f'{r:.3g}' for r in est.relmse)} over {case.sweep.param} = "
                f"{', '.join(str(v) for v in case.sweep.values)} | | ")
    n = est.numbers
    if n is None:
        return " | | "
    r, m = n.relmse, n.spp_to_match_path
    return (f"{r.median:.3g} / {r.p99:.3g} / {r.max:.3g} | {100 * n.firefly_fraction:.3f} % | "
            + (f"{m.spp:.3g} [{m.low:.3g}, {m.high:.3g}]" if m else "never (biased)"))


def write_junit(path: str, results: Results, strict: bool = False) -> None:
    """One test case per check: a fail is a <failure>, an inconclusive check a
    <skipped> with its reason (a <failure> with ``strict``)."""
    checks = results.checks
    n = results.counts()
    failures = n["fail"] + (n["inconclusive"] if strict else 0)
    skipped = 0 if strict else n["inconclusive"]
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<testsuite name="mcillum.validate.{results.profile}" tests="{len(checks)}" '
           f'failures="{failures}" skipped="{skipped}" time="{results.wall_seconds:.3f}">']
    for c in checks:
        scene, _, rest = c.id.partition("/")
        out.append(f'  <testcase classname={quoteattr("mcillum." + scene)} '
                   f'name={quoteattr(rest)}>')
        if c.outcome == "fail" or (strict and c.outcome == "inconclusive"):
            out.append(f'    <failure message={quoteattr(c.message)}>'
                       f'{escape(c.message)}</failure>')
        elif c.outcome == "inconclusive":
            out.append(f'    <skipped message={quoteattr("inconclusive: " + c.message)}/>')
        out.append("  </testcase>")
    out.append("</testsuite>")
    files.write_text(path, "\n".join(out) + "\n")
