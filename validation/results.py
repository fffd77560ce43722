"""The run's results as files: results.json (versioned schema), results.csv,
summary.md and an optional JUnit XML, one test case per check.

Schema: ``validation/results.schema.json`` (JSON Schema 2020-12), documented
in the README. ``version`` changes whenever a field changes meaning.
"""

from __future__ import annotations

import csv
import io
import json
import os
from xml.sax.saxutils import escape, quoteattr

from . import images, metrics

SCHEMA = "mcillum.results"
VERSION = 1
SCHEMA_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results.schema.json")

DEFINITIONS = {
    "mse": "mean over pixels and channels of (x - r)^2",
    "relmse": f"mean of (x - r)^2 / (r^2 + {metrics.EPSILON}) (tev convention)",
    "mape": f"mean of |x - r| / (|r| + {metrics.EPSILON})",
    "bias": "image mean of (mean of K renders - reference), with standard error",
    "variance_per_render": "mean over pixels of the sample variance over K renders",
    "nonfinite_fraction": "share of NaN/Inf values in the K renders (must be 0)",
    "efficiency": "1 / (relmse * median seconds per render)",
    "unbiasedness": "per-pixel-channel Welch t-tests (Sidak) + pooled per-channel tests "
                    "(Bonferroni), family-wise alpha, variances from each side's own renders",
    "slope": "least-squares slope of log relmse vs log spp, Student-t interval",
}


def write_text(path: str, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with images.atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)


def write_json(path: str, results: dict) -> None:
    write_text(path, json.dumps(results, indent=2, allow_nan=False, default=float) + "\n")


CSV_FIELDS = ["scene", "estimator", "spp", "renders", "relmse", "mse", "mape", "bias",
              "bias_se", "variance_per_render", "nonfinite_fraction", "median_seconds",
              "samples_per_second", "efficiency"]


def write_csv(path: str, results: dict) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, CSV_FIELDS)
    w.writeheader()
    for scene in results["scenes"]:
        for est in scene["estimators"]:
            for run in est["runs"]:
                w.writerow({"scene": scene["name"], "estimator": est["name"],
                            **{k: run[k] for k in CSV_FIELDS[2:]}})
    write_text(path, buf.getvalue())


def summary(results: dict) -> str:
    checks = results["checks"]
    failed = [c for c in checks if not c["passed"]]
    lines = [f"# mcillum validation — profile {results['profile']}",
             "",
             f"{len(checks) - len(failed)} of {len(checks)} checks passed; "
             f"{results['variant']}, mitsuba {results['mitsuba_version']}, "
             f"drjit {results['drjit_version']}, {results['wall_seconds']:.0f} s.", ""]
    for scene in results["scenes"]:
        ref = scene["reference"]
        capped = f", capped: {ref['capped']}" if ref["capped"] else ""
        lines += [f"## {scene['name']} ({scene['res']}², max_depth {scene['max_depth']})",
                  "", f"Reference: `path`, {ref['spp']} spp in {ref['passes']} passes"
                  f"{capped}.", "",
                  "| estimator | relMSE @ top spp | bias ± se | unbiased (pass %) | slope [95% CI] "
                  "| samples/s | efficiency |",
                  "|---|---|---|---|---|---|---|"]
        for est in scene["estimators"]:
            top = est["runs"][-1]
            u, c = est["unbiasedness"], est["convergence"]
            lines.append(
                f"| {est['name']} | {top['relmse']:.3g} | {top['bias']:+.2e} ± "
                f"{top['bias_se']:.1e} | {'yes' if u['passed'] else '**NO**'} "
                f"({100 * u['pass_fraction']:.1f}) | "
                + ("exact" if c["exact"] else
                   f"{c['slope']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}]")
                + f" | {top['samples_per_second'] / 1e6:.2f} M | "
                  f"{top['efficiency']:.3g} |")
        et = scene.get("equal_time")
        if et:
            measured = ", ".join(et["measured_ranking"]) if et["measured_ranking"] else "—"
            lines += ["", f"Equal time ({et['budget_seconds'] * 1e3:.1f} ms per render): "
                          f"predicted best first: {', '.join(et['predicted_ranking'])}; "
                          f"measured: {measured}."]
        lines.append("")
    if results.get("failures"):
        lines += ["## Where methods fail", "",
                  "| case | estimator | verdict | relMSE median / p99 / max | fireflies "
                  "| spp to match path |", "|---|---|---|---|---|---|"]
        for case in results["failures"]:
            for est in case["estimators"]:
                n = est.get("numbers") or {}
                if case.get("sweep"):
                    cells = (f"relMSE {', '.join(f'{r:.3g}' for r in est['relmse'])} over "
                             f"{case['sweep']['param']} = "
                             f"{', '.join(str(v) for v in case['sweep']['values'])} | | ")
                elif n:
                    r, m = n["relmse"], n["spp_to_match_path"]
                    cells = (f"{r['median']:.3g} / {r['p99']:.3g} / {r['max']:.3g} | "
                             f"{100 * n['firefly_fraction']:.3f} % | "
                             + (f"{m['spp']:.3g} [{m['low']:.3g}, {m['high']:.3g}]" if m
                                else "never (biased)"))
                else:
                    cells = " | | "
                lines.append(f"| {case['label']} | {est['name']} | {est['verdict']} | {cells} |")
        lines.append("")
    if failed:
        lines += ["## Failed checks", ""] + [f"- `{c['id']}`: {c['message']}" for c in failed]
    return "\n".join(lines) + "\n"


def write_junit(path: str, results: dict) -> None:
    checks = results["checks"]
    failures = sum(not c["passed"] for c in checks)
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<testsuite name="mcillum.validate.{results["profile"]}" tests="{len(checks)}" '
           f'failures="{failures}" time="{results["wall_seconds"]:.3f}">']
    for c in checks:
        scene, _, rest = c["id"].partition("/")
        out.append(f'  <testcase classname={quoteattr("mcillum." + scene)} '
                   f'name={quoteattr(rest)}>')
        if not c["passed"]:
            out.append(f'    <failure message={quoteattr(c["message"])}>'
                       f'{escape(c["message"])}</failure>')
        out.append("  </testcase>")
    out.append("</testsuite>")
    write_text(path, "\n".join(out) + "\n")
