"""The quadrature estimators' benchmark: a lone diffuse sphere seen by an
orthographic camera (every pixel on the sphere), direct light, under one
environment map after another.

For N directions × ``spp`` camera samples against cosine_hemisphere at N·spp
spp (equal rays), K seeds each, against a `path` reference whose own
variance is subtracted:

* relMSE of cosine_hemisphere, fibonacci_hemisphere and bayesian_hemisphere,
  and the ratios the issue's goals name;
* seconds per render (median), efficiency 1/(relMSE · seconds) and its ratio
  to cosine_hemisphere's at equal rays;
* bayesian_hemisphere's relMSE against ℓ (``--length-scales``), beside the
  ℓ its ``auto`` setting chose;
* with ``--slopes N…``: relMSE against N at fixed camera spp and the slope
  of log relMSE on log N with its 95 % interval.

    python benchmarks/quadrature.py --maps sg gradient courtyard \\
        --directions 16 64 --out bench.md
    python benchmarks/quadrature.py --slopes 16 32 64 128 256

A script, not part of the installed package: it needs mcillum installed
(``make test`` or ``pip install -e .``).

Timings are wall-clock on a shared machine: the ratios, taken in one
process, are what carries over.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import mcillum  # noqa: F401  (LLVM set-up before drjit)
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.validation.stats import metrics
from mcillum.validation.stats.statistics import loglog_fit


def relmse_stack(images, ref_mean, ref_var) -> tuple[float, float]:
    """(mean relMSE over renders less the reference's relative variance, its se)."""
    values = metrics.net_relmse(images, ref_mean, ref_var)
    return float(values.mean()), float(values.std(ddof=1) / np.sqrt(len(values)))


def run_case(envmap: str, directions: int, spp: int, k: int, res: int, ref_spp: int,
             length_scales=(), mappings=("cosine",)) -> list[dict]:
    scene = renders.load_scene(scenes.path("lone_sphere"), res=res, envmap=envmap)
    ref_mean, ref_var = reference(scene, ref_spp)
    rows = []
    setups = [("cosine_hemisphere", {"max_depth": 2}, spp * directions),
              ("fibonacci_hemisphere", {"directions": directions}, spp),
              ("bayesian_hemisphere", {"directions": directions}, spp)]
    setups += [("bayesian_hemisphere", {"directions": directions, "mapping": mapping,
                                         **({"length_scale": float(ell)} if ell else {})}, spp)
               for mapping in mappings for ell in (0, *length_scales)
               if mapping != "cosine" or ell]
    for name, params, n_spp in setups:
        integrator = renders.make_integrator(name, params)
        renders.render(scene, integrator, n_spp, 999_999)            # compile, fit ℓ
        out = [renders.render(scene, integrator, n_spp, seed) for seed in range(k)]
        rel, se = relmse_stack([r.image for r in out], ref_mean, ref_var)
        seconds = float(np.median([r.seconds for r in out]))
        label = name if params.get("mapping", "cosine") == "cosine" else \
            f"{name} ({params['mapping']})"
        rows.append({"map": envmap, "N": directions, "estimator": label,
                     "length_scale": getattr(integrator, "length_scale", None),
                     "given": "length_scale" in params, "spp": n_spp, "relmse": rel,
                     "relmse_se": se, "seconds": seconds,
                     "efficiency": 1.0 / (max(rel, 1e-300) * seconds)})
    return rows


def reference(scene, ref_spp: int):
    """(mean, variance of the mean) of 8 passes of `path` at max_depth 2."""
    integrator = renders.make_integrator("path", {"max_depth": 2})
    passes = [renders.render(scene, integrator, ref_spp, 1_000_000 + i).image for i in range(8)]
    return (np.mean(passes, axis=0).astype(np.float64),
            np.var(passes, axis=0, ddof=1) / len(passes))


def slopes(envmap: str, ladder, spp: int, k: int, res: int, ref_spp: int) -> list[str]:
    """Rows of relMSE against N at fixed camera spp (cosine_hemisphere at
    N·spp), with the least-squares slope of log relMSE on log N and its 95 %
    interval (MC: −1; a quadrature faster on smooth light)."""
    scene = renders.load_scene(scenes.path("lone_sphere"), res=res, envmap=envmap)
    ref_mean, ref_var = reference(scene, ref_spp)
    out = []
    for name in ("cosine_hemisphere", "fibonacci_hemisphere", "bayesian_hemisphere"):
        values = []
        for n in ladder:
            params, n_spp = ({"max_depth": 2}, spp * n) if name == "cosine_hemisphere" \
                else ({"directions": n}, spp)
            integrator = renders.make_integrator(name, params)
            images = [renders.render(scene, integrator, n_spp, seed).image for seed in range(k)]
            values.append(relmse_stack(images, ref_mean, ref_var)[0])
        slope, _, (low, high) = loglog_fit(ladder, np.maximum(values, 1e-300))
        out.append(f"| {envmap} | {name} | " + " | ".join(f"{v:.3g}" for v in values)
                   + f" | {slope:+.2f} [{low:+.2f}, {high:+.2f}] |")
    return out


def table(rows) -> str:
    lines = ["| map | N | estimator | ℓ | spp | relMSE ± se | ratio to cosine | ratio to "
             "fibonacci | s/render | efficiency × cosine |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        base = next(b for b in rows if b["map"] == r["map"] and b["N"] == r["N"]
                    and b["estimator"] == "cosine_hemisphere")
        fib = next(b for b in rows if b["map"] == r["map"] and b["N"] == r["N"]
                   and b["estimator"] == "fibonacci_hemisphere")
        ell = "" if r["length_scale"] is None else \
            f"{r['length_scale']:.3g}{'' if r['given'] else ' (auto)'}"
        lines.append(
            f"| {r['map']} | {r['N']} | {r['estimator']} | {ell} | {r['spp']} | "
            f"{r['relmse']:.3g} ± {r['relmse_se']:.2g} | {r['relmse'] / base['relmse']:.3g} | "
            f"{r['relmse'] / fib['relmse']:.3g} | {r['seconds']:.4f} | "
            f"{r['efficiency'] / base['efficiency']:.3g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--maps", nargs="+", default=["sg", "gradient", "courtyard"])
    p.add_argument("--directions", nargs="+", type=int, default=[16, 64])
    p.add_argument("--spp", type=int, default=4, help="camera samples per pixel")
    p.add_argument("--renders", type=int, default=8, help="K seeds per estimator")
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--reference-spp", type=int, default=4096)
    p.add_argument("--length-scales", nargs="*", type=float, default=[])
    p.add_argument("--mappings", nargs="+", default=["cosine"],
                   help="bayesian_hemisphere's node mappings to compare")
    p.add_argument("--variant", default=None)
    p.add_argument("--slopes", nargs="*", type=int, default=None, metavar="N",
                   help="instead: relMSE against these N at fixed spp, and the slopes")
    p.add_argument("--out", default=None, help="also write the table to this file")
    args = p.parse_args(argv)
    variant = renders.set_variant(args.variant)
    start = time.perf_counter()
    if args.slopes:
        lines = ["| map | estimator | " + " | ".join(f"N = {n}" for n in args.slopes)
                 + " | slope [95 % CI] |", "|---" * (len(args.slopes) + 3) + "|"]
        for m in args.maps:
            lines += slopes(m, args.slopes, args.spp, args.renders, args.res,
                            args.reference_spp)
            print("\n".join(lines), flush=True)
        text = (f"relMSE against N at {args.spp} camera spp (cosine at N·spp), {args.res}² px, "
                f"K = {args.renders}; {variant}; {time.perf_counter() - start:.0f} s\n\n"
                + "\n".join(lines) + "\n")
        if args.out:
            with open(args.out, "w", encoding="utf-8") as f:
                f.write(text)
        print(text)
        return 0
    rows = []
    for m in args.maps:
        for n in args.directions:
            rows += run_case(m, n, args.spp, args.renders, args.res, args.reference_spp,
                             args.length_scales, args.mappings)
            print(table(rows), flush=True)
    text = (f"{table(rows)}\n\n{args.res}² px, {args.spp} camera spp × N directions "
            f"(cosine at N·spp), K = {args.renders}, reference path {8 * args.reference_spp} "
            f"spp; {variant}; {time.perf_counter() - start:.0f} s\n")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
