"""guided_path against `path` at equal wall time, training included, on
sunlit_room under its hole (or ``--scene``) at the display film (256²), at
renders of about ``--seconds`` each (1, 10, 60 by default).

Each estimator's spp for a budget comes from its own timed render at a
small spp (t = a + b·spp, fitted from two; guided_path's training share
grows with spp, so its fit is checked by the renders themselves, whose
times are printed). At each budget, ``--pairs`` pairs of independent
renders per estimator, interleaved: a pair's half squared difference
(X₁ − X₂)²/2 per pixel is the variance of one render (both are unbiased),
over (ref² + 0.01) with ref the mean of every render of the budget (tev's
ε, as validation/stats/metrics.py); relMSE the mean over pixels;
efficiency 1/(relMSE · seconds). The ratio's 95 % interval is a bootstrap
over 16 × 16 blocks of pixels (with the pairs), the time ratio taken as
measured.

    python benchmarks/guide_budget.py --seconds 1 10 60 --pairs 3 2 1

A script, not part of the installed package: it needs mcillum installed.
Timings are wall-clock on a shared machine: the ratios, taken in one
process, are what carries over.
"""

from __future__ import annotations

import argparse
import ast

import numpy as np

import mcillum  # noqa: F401  (LLVM set-up before drjit)
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders

BLOCK = 16


def spp_for(scene, integrator, seconds: float) -> int:
    """spp whose render takes about ``seconds``: t = a + b·spp fitted from
    renders at 8 and 32 spp (warm)."""
    renders.render(scene, integrator, 8, seed=99)          # (compiles)
    t8 = renders.render(scene, integrator, 8, seed=98).seconds
    t32 = renders.render(scene, integrator, 32, seed=97).seconds
    b = max((t32 - t8) / 24, 1e-6)
    a = max(t8 - 8 * b, 0.0)
    return max(int((seconds - a) / b), 2)


def block_sums(x: np.ndarray) -> np.ndarray:
    """Sums of ``x`` (H, W) over BLOCK × BLOCK blocks, flat."""
    h, w = x.shape
    return x[:h - h % BLOCK, :w - w % BLOCK].reshape(h // BLOCK, BLOCK, w // BLOCK,
                                                     BLOCK).sum(axis=(1, 3)).ravel()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, nargs="+", default=[1.0, 10.0, 60.0])
    parser.add_argument("--pairs", type=int, nargs="+", default=[3, 2, 1])
    parser.add_argument("--res", type=int, default=256)
    parser.add_argument("--scene", default=None,
                        help="an XML scene taking -D res (default: sunlit_room under its hole)")
    parser.add_argument("-p", dest="params", action="append", default=[],
                        help="guided_path property, key=value (repeatable)")
    args = parser.parse_args(argv)
    renders.set_variant("llvm_ad_rgb")
    scene = (renders.load_scene(args.scene, res=args.res) if args.scene else
             renders.load_scene(scenes.path("sunlit_room"), res=args.res, gap="hole", sun=500))
    params = {k: ast.literal_eval(v) for k, v in (p.split("=", 1) for p in args.params)}
    made = {"path": renders.make_integrator("path", {}),
            "guided_path": renders.make_integrator("guided_path", params)}
    rng = np.random.default_rng(0)
    print("| budget | estimator | spp | seconds (mean) | relMSE | efficiency ÷ path [95 %] |")
    print("|---|---|---|---|---|---|")
    for seconds, pairs in zip(args.seconds, args.pairs + [args.pairs[-1]] * len(args.seconds)):
        spp = {n: spp_for(scene, it, seconds) for n, it in made.items()}
        images = {n: [] for n in made}
        times = {n: [] for n in made}
        for k in range(2 * pairs):
            for n, it in made.items():
                out = renders.render(scene, it, spp[n], seed=1000 * k + 7)
                images[n].append(np.asarray(out.image, np.float64)[..., :3].mean(axis=-1))
                times[n].append(out.seconds)
        ref = np.mean([im for n in made for im in images[n]], axis=0)
        weight = 1.0 / (ref ** 2 + 0.01)
        blocks = {}
        for n in made:
            half = [0.5 * (images[n][2 * j] - images[n][2 * j + 1]) ** 2 * weight
                    for j in range(pairs)]
            blocks[n] = np.stack([block_sums(h) for h in half])     # (pairs, blocks)
        rel = {n: blocks[n].sum() / (pairs * ref.size) for n in made}
        eff = {n: 1.0 / (rel[n] * np.mean(times[n])) for n in made}
        boot = []
        nb = blocks["path"].shape[1]
        for _ in range(2000):
            pick = rng.integers(0, nb, nb)
            r = blocks["path"][:, pick].sum() / blocks["guided_path"][:, pick].sum()
            boot.append(r * np.mean(times["path"]) / np.mean(times["guided_path"]))
        lo, hi = np.percentile(boot, [2.5, 97.5])
        for n in made:
            ratio = (f"{eff[n] / eff['path']:.2f} [{lo:.2f}, {hi:.2f}]"
                     if n != "path" else "1")
            print(f"| {seconds:g} s | {n} | {spp[n]} | {np.mean(times[n]):.2f} | "
                  f"{rel[n]:.4g} | {ratio} |", flush=True)
        log = made["guided_path"].training
        print(f"<!-- guided_path training: {[(e['spp'], e.get('weight')) for e in log]} -->",
              flush=True)


if __name__ == "__main__":
    main()
