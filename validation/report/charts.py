"""Charts of a validation run (matplotlib, Agg, headless), as SVG text.

Every builder takes records of :mod:`~mcillum.validation.results` and returns an SVG string, so
the report can inline it and tests can check it without rendering anything.
Each estimator keeps one colour on every chart: its registry colour, as the
run recorded it (:func:`palette`).
"""

from __future__ import annotations

import hashlib
import io
import re
from collections import Counter

import matplotlib
import numpy as np

from mcillum.integrators.core import registry

from ..results import CaseResult, Results, SceneResult

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)
import matplotlib.patches  # noqa: E402
import matplotlib.ticker  # noqa: E402
import matplotlib.transforms  # noqa: E402


def palette(results: Results) -> dict[str, str]:
    """Estimator name → colour for every estimator of a run: the colour its
    facts recorded, else a spare one (stable for the run)."""
    names = list(dict.fromkeys([e.name for s in results.scenes for e in s.estimators]
                               + [e.name for c in results.failures for e in c.estimators]))
    spare = registry.palette([n for n in names if n not in results.estimator_facts])
    return {n: results.estimator_facts[n].colour if n in results.estimator_facts
            else spare[n] for n in names}


def finish(fig, ax, xlabel: str, ylabel: str, title: str) -> str:
    """Label a log-log axis, grid and legend it, and return the figure as SVG
    (every chart of the report, report/axis.py's too)."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    # beside the axes: with eight estimators the lines fill every corner
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    return _svg(fig)


_SUPERSCRIPT = str.maketrans("-−0123456789", "⁻⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _plain_power(label: str) -> str:
    """A log axis's mathtext label (``$\\mathdefault{2\\times10^{-3}}$``) as
    plain text (2×10⁻³)."""
    text = label.strip("$").replace("\\times", "×")
    text = re.sub(r"\\mathdefault\{(.*)\}", r"\1", text)
    return re.sub(r"\^\{([^}]*)\}", lambda m: m[1].translate(_SUPERSCRIPT), text)


class _PlainLog(matplotlib.ticker.LogFormatterSciNotation):
    """Matplotlib's log-axis labels, the same ticks labelled, as plain text:
    mathtext parsing was a fifth of the report's charting time."""

    def __call__(self, x, pos=None):
        return _plain_power(super().__call__(x, pos))


def _plain_log_labels(fig) -> None:
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            for get, put in ((axis.get_major_formatter, axis.set_major_formatter),
                             (axis.get_minor_formatter, axis.set_minor_formatter)):
                f = get()
                if type(f) is matplotlib.ticker.LogFormatterSciNotation:
                    put(_PlainLog(f._base, labelOnlyBase=f.labelOnlyBase,
                                  minor_thresholds=f.minor_thresholds, linthresh=f._linthresh))


def _svg(fig) -> str:
    """The figure as compact SVG text for inlining (no XML prolog, no metadata);
    closes the figure."""
    _plain_log_labels(fig)
    buf = io.StringIO()
    # text as <text> in the page's fonts, not a path per glyph: 40 % fewer bytes
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        fig.savefig(buf, format="svg", bbox_inches="tight",
                    metadata={k: None for k in ("Creator", "Date", "Format", "Type")})
    plt.close(fig)
    text = buf.getvalue()
    return _compact(text[text.index("<svg"):])


_NUMBER = re.compile(r"-?\d+\.\d+")
_GEOMETRY = re.compile(r' (d|x|y|transform)="([^"]*)"')
_STYLE = re.compile(r' style="([^"]*)"')


def _rounded(m: re.Match) -> str:
    """A geometry attribute to 0.01 pt (a scale or matrix stays exact)."""
    if "scale" in m[2] or "matrix" in m[2]:
        return m[0]
    short = _NUMBER.sub(lambda n: f"{float(n[0]):.2f}".rstrip("0").rstrip("."), m[2])
    return f' {m[1]}="{short}"'


def _unwrapped(svg: str) -> str:
    """``svg`` without its plain groups (<g> without attributes draws nothing)."""
    out, plain = [], []
    for part in re.split(r"(<g>|<g\s[^>]*>|</g>)", svg):
        if part == "<g>":
            plain.append(True)
            continue
        if part.startswith("<g") and not part.endswith("/>"):
            plain.append(False)
        elif part == "</g>" and plain.pop():
            continue
        out.append(part)
    return "".join(out)


def _compact(svg: str) -> str:
    """Matplotlib's SVG drawn the same in fewer bytes: no comments, indentation,
    unused group ids or plain groups, coordinates to 0.01 pt, and each style used
    twice or more as a class (named by its hash: one rule in every chart of a page)."""
    svg = re.sub(r"<!--.*?-->", "", svg, flags=re.DOTALL)
    svg = re.sub(r'base64,[^"]*', lambda m: re.sub(r"\s+", "", m[0]), svg)
    svg = re.sub(r">\s+<", "><", re.sub(r"\s*\n\s*", " ", svg))
    svg = _GEOMETRY.sub(_rounded, svg)
    used = set(re.findall(r'(?:url\(#|href="#)([^")]+)', svg))
    svg = _unwrapped(re.sub(r'<g id="([^"]+)"', lambda m: m[0] if m[1] in used else "<g", svg))
    # a font without a generic fallback would fall back to the browser's serif
    svg = re.sub(r'(font-family: [^;"]*?)(?<!sans-serif)(?=[;"])', r"\1, sans-serif", svg)
    styles = Counter(_STYLE.findall(svg))
    names = {s: "c" + hashlib.sha1(s.encode()).hexdigest()[:8]
             for s, n in styles.items() if n > 1 and "url(" not in s}
    svg = _STYLE.sub(lambda m: f' class="{names[m[1]]}"' if m[1] in names else m[0], svg)
    rules = "".join(f".{c}{{{s}}}" for s, c in names.items())
    return re.sub(r"<svg[^>]*>", lambda m: f"{m[0]}<style>{rules}</style>", svg, count=1)


def error_vs_time(scene: SceneResult, colours: dict) -> str:
    """The speed stage: relMSE against wall time per render at each budget,
    log-log, with 95 % intervals on both axes (relMSE: Student-t over the K
    renders, an arrow up where it has a lower bound only; time: the range of
    the K renders); the budgets as dotted lines.
    An estimator too slow for a smaller budget has points at the others."""
    sp = scene.speed
    fig, ax = plt.subplots(figsize=(5.6, 4.0))
    for name in sp.budgets[-1].estimators:
        runs = [b.estimators[name] for b in sp.budgets if name in b.estimators]
        t = np.array([np.mean(r.wall_seconds) for r in runs]) * 1e3
        t_err = np.array([[t_ - min(r.wall_seconds) * 1e3, max(r.wall_seconds) * 1e3 - t_]
                          for t_, r in zip(t, runs)]).T
        e = np.array([r.relmse for r in runs])
        # a relMSE with a lower bound only (heavy-tailed, stats/tails.py):
        # its lower bar, and an arrow up from the point, a factor 2 long
        bound = np.array([not np.isfinite(r.relmse_ci.high) for r in runs])
        e_err = np.array([[r.relmse - r.relmse_ci.low,
                           0.0 if b else r.relmse_ci.high - r.relmse]
                          for r, b in zip(runs, bound)]).T
        ax.errorbar(t, e, yerr=np.maximum(e_err, 0), xerr=np.maximum(t_err, 0), fmt="o-",
                    color=colours[name], label=name, ms=4, capsize=2, lw=1.2)
        if bound.any():
            ax.errorbar(t[bound], e[bound], yerr=[np.zeros(bound.sum()), e[bound]],
                        fmt="none", ecolor=colours[name], lw=1.2, lolims=True)
    for b in sp.budgets:
        ax.axvline(b.seconds * 1e3, color="#999999", ls=":", lw=1)
    share = sp.budgets[-1].reference_relmse
    if share and np.isfinite(share) and share > 0:
        ax.axhline(share, color="#999999", ls="--", lw=1,
                   label="the reference's own noise")
    ax.set_xscale("log")
    ax.set_yscale("log")
    return finish(fig, ax, f"wall time per render at {sp.res}² [ms] (budgets dotted)",
                   "relMSE (ε = 0.01), 95 % interval", f"{scene.name}: accuracy vs time")


def error_vs_spp(scene: SceneResult, colours: dict) -> str:
    """relMSE against spp with the fitted slope in the legend and an ideal
    −1 slope through the first point of the noisiest estimator."""
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    worst = None
    for est in scene.estimators:
        spp = [r.spp for r in est.runs]
        e = [r.relmse for r in est.runs]
        c = est.convergence
        slope = "exact" if c.exact else f"slope {c.slope:+.2f}"
        ax.loglog(spp, e, "o-", color=colours[est.name], ms=4, label=f"{est.name} ({slope})")
        if worst is None or e[0] > worst[1]:
            worst = (spp[0], e[0], spp[-1])
    if worst:
        s0, e0, s1 = worst
        xs = np.array([s0, s1], float)
        ax.loglog(xs, e0 * (xs / s0) ** -1.0, "k--", lw=1, label="ideal slope −1")
    return finish(fig, ax, "samples per pixel", "relMSE (ε = 0.01)",
                   f"{scene.name}: convergence")


def settings_curve(q) -> str:
    """An estimator's held-out error against ℓ, a line per (mapping, noise):
    the noise by colour, the mapping by dash; the chosen setting starred
    (quadrature stage's ``settings``)."""
    st = q.settings
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    lines = {}
    for c in st.candidates:
        if np.isfinite(c.relmse) and c.relmse > 0:
            lines.setdefault((c.mapping, c.noise), []).append((c.length_scale, c.relmse))
    styles = {"cosine": "-", "uniform": "--"}
    noises = sorted({noise for _, noise in lines})
    cmap = plt.get_cmap("viridis")
    for (mapping, noise), pts in sorted(lines.items()):
        pts.sort()
        shade = cmap(0.85 * noises.index(noise) / max(len(noises) - 1, 1))
        ax.loglog(*zip(*pts), styles.get(mapping, ":"), marker="o", ms=3, color=shade,
                  label=f"{mapping}, σ_n²/σ² = {noise:g}")
    best = [c.relmse for c in st.candidates if (c.mapping, c.noise, c.length_scale)
            == (st.mapping, st.noise, st.length_scale)]
    if best and best[0] > 0:
        ax.loglog([st.length_scale], best, "*", color="#d62728", ms=14,
                  label=f"chosen: {st.mapping}, {st.noise:g}, ℓ = {st.length_scale:.2g}")
    ax.set_xticks([0.1, 0.2, 0.5, 1.0, 2.0], ["0.1", "0.2", "0.5", "1", "2"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    return finish(fig, ax, "length scale ℓ (radians)",
                   f"held-out relMSE at {st.spp} spp",
                   f"{q.name}, N = {q.directions}: settings")


def learning_curve(learned, colours: dict) -> str:
    """relMSE of an estimator's image at a fixed spp against the training
    spp before it, with 95 % intervals (learning stage); 0 training spp is
    drawn at the axis' left end."""
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    pts = learned.points
    unit = min((p.training_spp for p in pts if p.training_spp > 0), default=1)
    # (no training on a log axis: half the first pass's spp, labelled 0)
    x = [p.training_spp if p.training_spp > 0 else unit / 2 for p in pts]
    y = [p.relmse for p in pts]
    err = [[max(p.relmse - p.relmse_low, 0) for p in pts],
           [max(p.relmse_high - p.relmse, 0) for p in pts]]
    ax.errorbar(x, y, yerr=err, fmt="o-", ms=4, capsize=3, color=colours[learned.name],
                label=f"{learned.name}, {learned.spp} spp in the image")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(x, ["0" if p.training_spp == 0 else str(p.training_spp) for p in pts])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    return finish(fig, ax, "training samples per pixel before the image",
                   "relMSE (ε = 0.01)", f"{learned.name}: learning")


def error_spread(scene: SceneResult, colours: dict) -> str:
    """Per-render relMSE over seeds at the top spp (heavy-tail evidence):
    one strip of points per estimator, median marked."""
    fig, ax = plt.subplots(figsize=(5.2, 2.8))
    names = [e.name for e in scene.estimators]
    for i, est in enumerate(scene.estimators):
        per = np.asarray(est.top.relmse_per_render, float)
        jitter = np.linspace(-0.15, 0.15, len(per)) if len(per) > 1 else np.zeros(1)
        ax.semilogy(i + jitter, per, "o", color=colours[est.name], ms=3, alpha=0.7)
        ax.hlines(np.median(per), i - 0.25, i + 0.25, color="k", lw=1)
    ax.set_xticks(range(len(names)), names, fontsize=7, rotation=25, ha="right")
    ax.set_ylabel("relMSE of one render")
    ax.set_title(f"{scene.name}: error over seeds at {scene.estimators[0].top.spp} spp")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    return _svg(fig)


def efficiency_summary(results: Results, colours: dict) -> str:
    """Efficiency of each estimator relative to `path` at each scene's largest
    equal-time budget (speed stage), with 95 % intervals, log bars; a bound
    hatched at the bound, and a "?" where a heavy-tailed figure has no bound
    either way."""
    reference = registry.REFERENCE
    scenes = [s for s in results.scenes if s.speed is not None]
    names = [n for n in dict.fromkeys(n for s in scenes for n in s.speed.efficiency_vs_path)
             if n != reference]
    fig, ax = plt.subplots(figsize=(max(7.5, 2.0 + 0.75 * len(scenes)), 3.9))
    width = 0.8 / max(len(names), 1)
    hatch = {"reference_limited": "//", "biased": "xx", "heavy_tailed": "\\\\"}
    foot = matplotlib.transforms.blended_transform_factory(ax.transData, ax.transAxes)
    for j, name in enumerate(names):
        ratio, low, high, kinds = [], [], [], []
        x = np.arange(len(scenes)) + (j - (len(names) - 1) / 2) * width
        for s, x_ in zip(scenes, x):
            r = s.speed.efficiency_vs_path.get(name)
            heavy = r is not None and r.kind == "heavy_tailed"
            bound = r is not None and not np.isfinite(r.ci.high) and not heavy
            upper = heavy and np.isfinite(r.ci.high)
            if heavy and not upper:
                # (heavy-tailed with no upper end either: nothing to draw)
                ax.text(x_, 0.01, "?", transform=foot, color=colours[name], fontsize=8,
                        ha="center", va="bottom", fontweight="bold")
                r = None
            # a bound (lower or upper) is drawn at its bound, with no interval
            ratio.append((r.ci.low if bound else r.ci.high if upper else r.ratio)
                         if r else np.nan)
            low.append(0.0 if bound or upper or not r else r.ratio - r.ci.low)
            high.append(0.0 if bound or upper or not r else r.ci.high - r.ratio)
            kinds.append("reference_limited" if bound else (r.kind if r else "unbiased"))
        bars = ax.bar(x, ratio, width, color=colours[name], label=name,
                      yerr=[np.maximum(low, 0), np.maximum(high, 0)], capsize=2,
                      error_kw={"lw": 0.8})
        for bar, kind in zip(bars, kinds):
            if kind in hatch:
                bar.set_hatch(hatch[kind])
                bar.set_edgecolor("white")
    line = ax.axhline(1.0, color=colours.get(reference, "k"), lw=1, ls="--", label="path = 1")
    ax.set_yscale("log")
    ax.set_xticks(range(len(scenes)), [s.name for s in scenes], fontsize=8, rotation=30,
                  ha="right")
    ax.set_ylabel("efficiency / efficiency of path")
    ax.set_title("Efficiency 1/(relMSE·time) relative to Mitsuba's path, at equal time\n"
                 "(hatched //: a lower bound only; \\: an upper bound only, heavy-tailed; "
                 "?: heavy-tailed, no bound; xx: biased by design)",
                 fontsize=9)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    # (plain swatches: a hatched first bar would hatch its estimator's key;
    # beside the axes: with eight estimators it hid the last scene's bars)
    ax.legend([line] + [matplotlib.patches.Patch(color=colours[n]) for n in names],
              ["path = 1", *names], fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0),
              borderaxespad=0.0)
    return _svg(fig)


def colour_bar(vmin: float, vmax: float, cmap, label: str, log: bool = True) -> str:
    """A horizontal colour bar of ``cmap`` (a name or a Colormap) from vmin to vmax."""
    fig, ax = plt.subplots(figsize=(4.5, 0.5))
    norm = (matplotlib.colors.LogNorm if log else matplotlib.colors.Normalize)(vmin=vmin,
                                                                              vmax=vmax)
    bar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), cax=ax,
                       orientation="horizontal", label=label)
    bar.solids.set_rasterized(True)     # one image: a few steps as shapes show seams
    return _svg(fig)


def failure_sweep(case: CaseResult, colours: dict) -> str:
    """A glossy sweep: relMSE at fixed spp, and relMSE × seconds per render
    (error at equal time, lower is better), against the swept parameter."""
    values = np.asarray(case.sweep.values, float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for est in case.estimators:
        rel = np.asarray(est.relmse, float)
        work = rel * np.asarray(est.seconds, float)
        for ax, y in zip(axes, (rel, work)):
            ax.loglog(values, y, "o-", color=colours.get(est.name, "#777777"), ms=4,
                      label=est.name)
    for ax, label in zip(axes, (f"relMSE at {case.spp} spp", "relMSE × seconds per render")):
        ax.set_xlabel(case.sweep.param)
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        # ticks at the swept values only (log minor labels overprint each other)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xticks(values, [f"{v:g}" for v in values])
        if case.sweep.param == "alpha":
            ax.invert_xaxis()         # narrower lobes to the right
    axes[0].set_title(f"{case.label}: error as the lobe narrows")
    axes[1].set_title("error against time")
    axes[1].legend(fontsize=7)
    return _svg(fig)
