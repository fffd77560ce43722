"""guided_path's benchmark: efficiency ÷ `path` at equal spp, training
included in every timing, on the scenes issue 28 names.

For each case and spp: K renders of `path` and of `guided_path`
(interleaved, so that a drifting machine loads both alike), each timed
after a warm-up render; relMSE against 8 passes of `path` at ``--ref-spp``
(its own share subtracted, validation.stats.costs); efficiency
1/(net relMSE · mean seconds) and the ratio with its 95 % interval (delta
method, as the speed stage); relMSE and time ÷ path's apart, so that what
the learning buys and what it costs can be read separately.

    python benchmarks/guiding.py --cases sunlit_room sunlit_room_hole \\
        --spp 64 256 --renders 6
    python benchmarks/guiding.py --cases cornell_box -p directional_res=8
    python benchmarks/guiding.py --cases sky_sphere --against combine_passes=False

``--against`` adds a second `guided_path` with those properties changed to
the same interleaved renders (its rows marked "against"): two settings
compared in one process.

A script, not part of the installed package: it needs mcillum installed
(``make test`` or ``pip install -e .``). Timings are wall-clock on a
shared machine: the ratios, taken in one process, are what carries over.
"""

from __future__ import annotations

import argparse
import ast

import numpy as np

import mcillum  # noqa: F401  (LLVM set-up before drjit)
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.validation.stats import costs, metrics

#: name → (bundled scene, its defines, max_depth: None keeps the scene's)
CASES = {
    "sunlit_room": ("sunlit_room", {}, None),
    # (the sun 25× stronger: the hole lets in 25× less light)
    "sunlit_room_hole": ("sunlit_room", {"gap": "hole", "sun": 500}, None),
    "cornell_box": ("cornell_box", {}, None),
    "probe_spheres_sunrise": ("probe_spheres", {"envmap": "sunrise"}, 4),
    "probe_spheres_city": ("probe_spheres", {"envmap": "city"}, 4),
    "cap_plane": ("cap_plane", {}, 2),
    "sky_sphere": ("sky_sphere", {}, None),
}


def reference(scene, depth, ref_spp: int):
    """(mean, variance of the mean, passes) of 8 passes of `path`."""
    integrator = renders.make_integrator("path", depth)
    passes = [renders.render(scene, integrator, ref_spp, 1_000_000 + i).image for i in range(8)]
    return (np.mean(passes, axis=0).astype(np.float64),
            np.var(passes, axis=0, ddof=1) / len(passes), len(passes))


def run_case(case: str, res: int, spp: int, k: int, ref, params: dict,
             against: dict | None = None) -> list[str]:
    name, defines, max_depth = CASES[case]
    scene = renders.load_scene(scenes.path(name), res=res, **defines)
    depth = {} if max_depth is None else {"max_depth": max_depth}
    ref_mean, ref_var, passes = ref
    share = costs.reference_share(ref_mean, ref_var, passes)
    made = {"path": renders.make_integrator("path", depth),
            "guided_path": renders.make_integrator("guided_path", {**depth, **params})}
    if against:
        made["against"] = renders.make_integrator("guided_path", {**depth, **params, **against})
    for integrator in made.values():            # (warm-up: kernels compiled)
        renders.render(scene, integrator, spp, seed=10_000)
    errors = {n: [] for n in made}
    seconds = {n: [] for n in made}
    for seed in range(k):
        for n, integrator in made.items():
            out = renders.render(scene, integrator, spp, seed)
            errors[n].append(float(metrics.per_render_relmse([out.image], ref_mean)[0]))
            seconds[n].append(out.seconds)
    eff = {n: costs.efficiency(errors[n], seconds[n], share) for n in made}
    net = {n: np.mean(errors[n]) - share.value for n in made}
    rows = []
    for n in made:
        if n == "path":
            continue
        value, ci = costs.ratio(eff[n], eff["path"], k)
        training = made[n].training
        learned = f"{training[-1]['leaves']} leaves" if training else "no training"
        rows.append(f"| {case}{' (against)' if n == 'against' else ''} | {res}² × {spp} | "
                    f"{net[n] / net['path']:.2f} | "
                    f"{np.mean(seconds[n]) / np.mean(seconds['path']):.2f} | "
                    f"{value:.2f} [{ci.low:.2f}, {ci.high:.2f}] | {net['path']:.3g} | "
                    f"{learned} |")
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--spp", nargs="+", type=int, default=[64, 256])
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--renders", type=int, default=6)
    parser.add_argument("--ref-spp", type=int, default=2048)
    parser.add_argument("--variant", default="llvm_ad_rgb")
    parser.add_argument("-p", dest="params", action="append", default=[],
                        help="guided_path property, key=value (repeatable)")
    parser.add_argument("--against", action="append", default=[],
                        help="a second guided_path with this property changed (repeatable)")
    args = parser.parse_args(argv)
    renders.set_variant(args.variant)
    params, against = _properties(args.params), _properties(args.against)
    print("| case | film × spp | relMSE ÷ path's | time ÷ path's | efficiency ÷ path "
          "[95 %] | path's relMSE | guide |")
    print("|---|---|---|---|---|---|---|")
    for case in args.cases:
        name, defines, max_depth = CASES[case]
        scene = renders.load_scene(scenes.path(name), res=args.res, **defines)
        depth = {} if max_depth is None else {"max_depth": max_depth}
        ref = reference(scene, depth, args.ref_spp)
        del scene
        for spp in args.spp:
            for row in run_case(case, args.res, spp, args.renders, ref, params, against):
                print(row, flush=True)


def _properties(items: list[str]) -> dict:
    """key=value strings → properties (values as Python literals, else text)."""
    out = {}
    for item in items:
        key, _, text = item.partition("=")
        try:
            out[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            out[key] = text
    return out


if __name__ == "__main__":
    main()
