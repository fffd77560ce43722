"""Charts of a validation run (matplotlib, Agg, headless), as SVG text.

Every builder takes plain data from results.json and returns an SVG string,
so the report can inline it and tests can check it without rendering
anything. One colour per estimator on every chart (:func:`colours`).
"""

from __future__ import annotations

import io

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

#: Fixed colours for the known estimators; others get the next free ones.
KNOWN = {"path": "#444444", "uniform_hemisphere": "#d62728", "cosine_hemisphere": "#1f77b4",
         "bsdf_sampling": "#2ca02c", "emitter_sampling": "#9467bd", "mis": "#ff7f0e"}
_SPARE = ["#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f"]


def colours(names) -> dict:
    """Estimator name → colour, stable across charts of one report."""
    out, spare = {}, iter(_SPARE * 4)
    for n in names:
        out[n] = KNOWN.get(n) or next(spare)
    return out


def _svg(fig) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    plt.close(fig)
    text = buf.getvalue()
    return text[text.index("<svg"):]  # drop the XML prolog for inlining


def error_vs_time(scene: dict, palette: dict) -> str:
    """relMSE against median seconds per render, one line per estimator,
    a marker per spp (labelled), log-log: equal time reads off vertically."""
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    for est in scene["estimators"]:
        t = [r["median_seconds"] * 1e3 for r in est["runs"]]
        e = [r["relmse"] for r in est["runs"]]
        ax.loglog(t, e, "o-", color=palette[est["name"]], label=est["name"], ms=4)
        for r, x, y in zip(est["runs"], t, e):
            ax.annotate(str(r["spp"]), (x, y), textcoords="offset points", xytext=(3, 3),
                        fontsize=6, color=palette[est["name"]])
    et = scene.get("equal_time")
    if et:
        ax.axvline(et["budget_seconds"] * 1e3, color="#999999", ls=":", lw=1,
                   label="equal-time budget")
    ax.set_xlabel("wall time per render [ms]")
    ax.set_ylabel("relMSE (ε = 0.01)")
    ax.set_title(f"{scene['name']}: accuracy vs time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _svg(fig)


def error_vs_spp(scene: dict, palette: dict) -> str:
    """relMSE against spp with the fitted slope in the legend and an ideal
    −1 slope through the first point of the noisiest estimator."""
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    worst = None
    for est in scene["estimators"]:
        spp = [r["spp"] for r in est["runs"]]
        e = [r["relmse"] for r in est["runs"]]
        c = est["convergence"]
        slope = "exact" if c.get("exact") else f"slope {c['slope']:+.2f}"
        ax.loglog(spp, e, "o-", color=palette[est["name"]], ms=4,
                  label=f"{est['name']} ({slope})")
        if worst is None or e[0] > worst[1]:
            worst = (spp[0], e[0], spp[-1])
    if worst:
        s0, e0, s1 = worst
        xs = np.array([s0, s1], float)
        ax.loglog(xs, e0 * (xs / s0) ** -1.0, "k--", lw=1, label="ideal slope −1")
    ax.set_xlabel("samples per pixel")
    ax.set_ylabel("relMSE (ε = 0.01)")
    ax.set_title(f"{scene['name']}: convergence")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _svg(fig)


def error_spread(scene: dict, palette: dict) -> str:
    """Per-render relMSE over seeds at the top spp (heavy-tail evidence):
    one strip of points per estimator, median marked."""
    fig, ax = plt.subplots(figsize=(5.2, 2.8))
    names = [e["name"] for e in scene["estimators"]]
    for i, est in enumerate(scene["estimators"]):
        per = np.asarray(est["runs"][-1]["relmse_per_render"], float)
        jitter = np.linspace(-0.15, 0.15, len(per)) if len(per) > 1 else np.zeros(1)
        ax.semilogy(i + jitter, per, "o", color=palette[est["name"]], ms=3, alpha=0.7)
        ax.hlines(np.median(per), i - 0.25, i + 0.25, color="k", lw=1)
    ax.set_xticks(range(len(names)), names, fontsize=7)
    ax.set_ylabel("relMSE of one render")
    ax.set_title(f"{scene['name']}: error over seeds at "
                 f"{scene['estimators'][0]['runs'][-1]['spp']} spp")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    return _svg(fig)


def efficiency_summary(results: dict, palette: dict) -> str:
    """Efficiency of each estimator relative to `path`, per scene (log bars)."""
    scenes = [s for s in results["scenes"]
              if any(e["name"] == "path" for e in s["estimators"])]
    names = sorted({e["name"] for s in scenes for e in s["estimators"]} - {"path"})
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    width = 0.8 / max(len(names), 1)
    for j, name in enumerate(names):
        ratios = []
        for s in scenes:
            by = {e["name"]: e["runs"][-1]["efficiency"] for e in s["estimators"]}
            ratios.append(by.get(name, np.nan) / by["path"])
        x = np.arange(len(scenes)) + (j - (len(names) - 1) / 2) * width
        ax.bar(x, ratios, width, color=palette[name], label=name)
    ax.axhline(1.0, color=palette.get("path", "k"), lw=1, ls="--", label="path = 1")
    ax.set_yscale("log")
    ax.set_xticks(range(len(scenes)), [s["name"] for s in scenes], fontsize=8)
    ax.set_ylabel("efficiency / efficiency of path")
    ax.set_title("Efficiency 1/(relMSE·time) relative to Mitsuba's path, at the top spp")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _svg(fig)


def colour_bar(vmin: float, vmax: float, cmap: str, label: str) -> str:
    fig, ax = plt.subplots(figsize=(4.5, 0.5))
    norm = matplotlib.colors.LogNorm(vmin=vmin, vmax=vmax)
    fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), cax=ax,
                 orientation="horizontal", label=label)
    return _svg(fig)


def failure_sweep(case: dict, palette: dict) -> str:
    """A glossy sweep: relMSE at fixed spp, and relMSE × seconds per render
    (error at equal time, lower is better), against the swept parameter."""
    sweep = case["sweep"]
    values = np.asarray(sweep["values"], float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for est in case["estimators"]:
        rel = np.asarray(est["relmse"], float)
        work = rel * np.asarray(est["seconds"], float)
        for ax, y in zip(axes, (rel, work)):
            ax.loglog(values, y, "o-", color=palette.get(est["name"], "#777777"), ms=4,
                      label=est["name"])
    for ax, label in zip(axes, (f"relMSE at {case['spp']} spp",
                                "relMSE × seconds per render")):
        ax.set_xlabel(sweep["param"])
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if sweep["param"] == "alpha":
            ax.invert_xaxis()         # narrower lobes to the right
    axes[0].set_title(f"{case['label']}: error as the lobe narrows")
    axes[1].set_title("error against time")
    axes[1].legend(fontsize=7)
    return _svg(fig)
