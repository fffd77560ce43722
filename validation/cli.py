"""The ``mcillum`` command.

    mcillum render SCENE.xml --integrator NAME [--spp N] [--seed S]
                   [--param K=V ...] [--define K=V ...] [--variant V]
                   [--exposure EV] -o OUT.exr
    mcillum bench SCENE.xml [--integrators a,b,c] [--spp N] [--runs R] [--json F]
    mcillum envmap NAME [-p K=V ...] [--policy clamp|strict] -o FILE.exr
    mcillum envmap --list
    mcillum validate [--profile quick|full] [--scenes ...] [--estimators ...] [--out DIR]
                     [--junit FILE]
    mcillum report RESULTS_DIR

Exit codes: 0 success, 1 the render failed (message on stderr), 2 usage error.
"""

from __future__ import annotations

import argparse
import os
import sys

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mcillum",
        description="Monte Carlo estimators of the illumination integral for Mitsuba 3.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser(
        "render", help="render a Mitsuba XML scene with one integrator",
        description="Render SCENE with an mcillum estimator (or any Mitsuba integrator) "
                    "to a float32 EXR with metadata, plus a tone-mapped PNG beside it.")
    r.add_argument("scene", help="Mitsuba 3 XML scene file")
    r.add_argument("--integrator", "-i", required=True,
                   help="integrator plugin, e.g. cosine_hemisphere, uniform_hemisphere, path")
    r.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    r.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    r.add_argument("--param", "-p", action="append", default=[], metavar="K=V",
                   help="integrator property, e.g. max_depth=2 (repeatable)")
    r.add_argument("--define", "-D", action="append", default=[], metavar="K=V",
                   help="scene $-parameter, e.g. res=128 (repeatable)")
    r.add_argument("--variant", default=None,
                   help="Mitsuba variant (default $MCILLUM_VARIANT or llvm_ad_rgb)")
    r.add_argument("--exposure", type=float, default=0.0,
                   help="exposure of the PNG preview in stops (default 0)")
    r.add_argument("--output", "-o", required=True, help="output .exr path")
    r.set_defaults(run=_render)

    b = sub.add_parser(
        "bench", help="time integrators against each other on one scene",
        description="Render SCENE once per integrator (compile), then RUNS interleaved "
                    "warm rounds; print median warm times and ratios to the first "
                    "integrator, and optionally write them as JSON.")
    b.add_argument("scene", help="Mitsuba 3 XML scene file")
    b.add_argument("--integrators", default="path,uniform_hemisphere,cosine_hemisphere",
                   help="comma-separated plugin names; ratios are to the first "
                        "(default path,uniform_hemisphere,cosine_hemisphere)")
    b.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    b.add_argument("--runs", type=int, default=5, help="warm rounds (default 5)")
    b.add_argument("--param", "-p", action="append", default=[], metavar="K=V",
                   help="property given to every integrator, e.g. max_depth=8")
    b.add_argument("--define", "-D", action="append", default=[], metavar="K=V",
                   help="scene $-parameter, e.g. res=256")
    b.add_argument("--variant", default=None, help="Mitsuba variant")
    b.add_argument("--json", default=None, metavar="FILE", help="also write results here")
    b.set_defaults(run=_bench)

    e = sub.add_parser(
        "envmap", help="list, generate or check environment maps",
        description="Write environment map NAME (a procedural map or a real light probe, "
                    "sanitised by the loading policy) to an EXR; or list every map.")
    e.add_argument("name", nargs="?", help="map name (see --list) or an EXR file to check")
    e.add_argument("--list", action="store_true", help="list every map with its licence")
    e.add_argument("--param", "-p", action="append", default=[], metavar="K=V",
                   help="generator parameter, e.g. alpha_deg=30 or radiance=2 (repeatable)")
    e.add_argument("--policy", choices=("clamp", "strict"), default="clamp",
                   help="NaN/Inf/negative policy for files (default clamp: negatives → 0, "
                        "NaN/Inf refused)")
    e.add_argument("--output", "-o", help="output .exr path")
    e.set_defaults(run=_envmap)

    v = sub.add_parser(
        "validate", help="compare the estimators with Mitsuba's path tracer",
        description="Render each scene of a profile with every estimator over an spp "
                    "ladder, build an adaptive `path` reference, test unbiasedness, fit "
                    "convergence, compare at equal time; write results.json, results.csv, "
                    "summary.md and images to --out. Exit 0 if every check passes, 1 if "
                    "one fails, 2 on usage errors.")
    v.add_argument("--profile", choices=("quick", "full"), default="quick")
    v.add_argument("--scenes", nargs="+", metavar="SCENE", help="subset of the profile's scenes")
    v.add_argument("--estimators", nargs="+", metavar="NAME",
                   help="integrator plugins to validate (default: uniform_hemisphere "
                        "cosine_hemisphere path)")
    v.add_argument("--out", default="out/validate", help="output directory (default out/validate)")
    v.add_argument("--junit", metavar="FILE", help="also write JUnit XML, one case per check")
    v.add_argument("--cache", metavar="DIR", help="reference cache (default $MCILLUM_CACHE "
                                                  "or ~/.cache/mcillum)")
    v.add_argument("--variant", default=None, help="Mitsuba variant")
    v.set_defaults(run=_validate)

    rp = sub.add_parser(
        "report", help="(re)write the HTML report of an existing validation run",
        description="Read RESULTS_DIR/results.json and its images and write "
                    "RESULTS_DIR/report/index.html (self-contained) and summary.md.")
    rp.add_argument("results_dir", help="a directory written by `mcillum validate --out`")
    rp.set_defaults(run=_report)
    return parser


def _report(args) -> int:
    from . import report

    if not os.path.isfile(os.path.join(args.results_dir, "results.json")):
        raise _Usage(f"no results.json in {args.results_dir}: run `mcillum validate "
                     f"--out {args.results_dir}` first")
    print(report.build(args.results_dir))
    return EXIT_OK


def _validate(args) -> int:
    from . import profiles, results, validate

    profile = profiles.PROFILES[args.profile]
    known = {r.scene for r in profile.runs}
    for name in args.scenes or []:
        if name not in known:
            raise _Usage(f"scene '{name}' is not in profile '{args.profile}' "
                         f"({', '.join(sorted(known))})")
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as err:
        raise _Usage(f"cannot create --out {args.out}: {err.strerror}") from None
    if not os.access(args.out, os.W_OK):
        raise _Usage(f"--out is not writable: {args.out}")
    if args.estimators:
        from . import renders

        renders.set_variant(args.variant)
        for name in args.estimators:
            try:
                renders.make_integrator(name)
            except Exception as err:
                raise _Usage(f"estimator '{name}' cannot be loaded: "
                             f"{str(renders.root_cause(err)).splitlines()[0]}") from None
    out = validate.validate(args.profile, args.scenes, args.estimators, args.out, args.cache,
                            args.variant)
    if args.junit:
        results.write_junit(args.junit, out)
    print(results.summary(out))
    print(f"report: {os.path.join(args.out, 'report', 'index.html')}")
    return EXIT_OK if out["passed"] else EXIT_FAILED


def _envmap(args) -> int:
    import envmaps
    from envmaps import catalog, procedural, safety

    if args.list:
        rows = catalog.entries()
        width = max(len(n) for n in rows)
        for name, entry in rows.items():
            print(f"{name:<{width}}  {entry.kind:<10}  {entry.description}")
            print(f"{'':<{width}}  licence: {entry.licence}")
            if entry.closed_form:
                print(f"{'':<{width}}  exact: {entry.closed_form}")
        return EXIT_OK
    if not args.name:
        raise _Usage("give a map NAME (or --list)")
    if not args.output:
        raise _Usage("give an output path with -o FILE.exr")
    if not args.output.lower().endswith(".exr"):
        raise _Usage(f"output must be an .exr path, got '{args.output}'")
    from .renders import parse_assignments

    try:
        params = parse_assignments(args.param)
    except ValueError as err:
        raise _Usage(str(err)) from None
    if args.name in catalog.PROCEDURAL:
        rgb, report = catalog.generate(args.name, **params), None
    else:
        if params:
            raise _Usage("--param applies to procedural maps only")
        path = envmaps.probes.path(args.name) if args.name in envmaps.probes.names() \
            else args.name
        rgb, report = safety.load(path, args.policy)
    procedural.write(args.output, rgb)
    h, w = rgb.shape[:2]
    print(f"{args.output}: {args.name}, {w}x{h}" + (f"; {report}" if report else ""))
    return EXIT_OK


def _bench(args) -> int:
    import json
    import platform

    from . import images, renders, timing

    if args.spp < 1 or args.runs < 1:
        raise _Usage("--spp and --runs must be >= 1")
    try:
        params = renders.parse_assignments(args.param)
        defines = renders.parse_assignments(args.define)
    except ValueError as e:
        raise _Usage(str(e)) from None
    names = [n.strip() for n in args.integrators.split(",") if n.strip()]
    if not names:
        raise _Usage("--integrators is empty")

    variant = renders.set_variant(args.variant)
    scene = renders.load_scene(args.scene, **defines)
    integrators = {n: renders.make_integrator(n, params) for n in names}
    times = timing.alternate(scene, integrators, args.spp, args.runs)

    base = times[names[0]].median
    w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
    rows = []
    for n in names:
        t = times[n]
        rows.append({"integrator": n, "first_seconds": t.first_seconds,
                     "warm_seconds": t.warm_seconds, "median_seconds": t.median,
                     "ratio_to_first": t.median / base,
                     "samples_per_second": w * h * args.spp / t.median})
        print(f"{n:>22}: median {t.median:.4f} s over {len(t.warm_seconds)} warm runs "
              f"(first {t.first_seconds:.3f} s), {t.median / base:.2f}x {names[0]}, "
              f"{rows[-1]['samples_per_second'] / 1e6:.2f} Msamples/s")
    if args.json:
        import drjit as dr
        import mitsuba as mi

        report = {"scene": os.path.abspath(args.scene), "defines": defines,
                  "params": params, "spp": args.spp, "resolution": [w, h],
                  "variant": variant, "mitsuba_version": mi.__version__,
                  "drjit_version": dr.__version__, "machine": platform.platform(),
                  "cpus": os.cpu_count(), "results": rows}
        with images.atomic_path(args.json) as tmp, open(tmp, "w") as f:
            json.dump(report, f, indent=2)
    return EXIT_OK


def _render(args) -> int:
    # Imported here so that `mcillum --help` works without loading Mitsuba.
    from . import images, renders

    if not args.output.lower().endswith(".exr"):
        raise _Usage(f"output must be an .exr path, got '{args.output}'")
    if args.spp < 1:
        raise _Usage(f"--spp must be >= 1, got {args.spp}")
    try:
        params = renders.parse_assignments(args.param)
        defines = renders.parse_assignments(args.define)
    except ValueError as e:
        raise _Usage(str(e)) from None
    out_dir = os.path.dirname(os.path.abspath(args.output))
    if not os.path.isdir(out_dir):
        raise _Usage(f"output directory does not exist: {out_dir}")

    variant = renders.set_variant(args.variant)
    scene = renders.load_scene(args.scene, **defines)
    integrator = renders.make_integrator(args.integrator, params)
    result = renders.render(scene, integrator, args.spp, args.seed)

    import drjit as dr
    import mitsuba as mi

    meta = {
        "scene": os.path.abspath(args.scene),
        "integrator": args.integrator,
        "params": " ".join(f"{k}={v}" for k, v in sorted(params.items())),
        "defines": " ".join(f"{k}={v}" for k, v in sorted(defines.items())),
        "spp": args.spp,
        "seed": args.seed,
        "variant": variant,
        "mitsuba_version": mi.__version__,
        "drjit_version": dr.__version__,
        "render_seconds": result.seconds,
    }
    png = os.path.splitext(args.output)[0] + ".png"
    images.write_exr(args.output, result.image, meta)
    images.write_png(png, result.image, args.exposure)
    h, w = result.image.shape[:2]
    print(f"{args.output}: {w}x{h}, {args.spp} spp, {args.integrator}, "
          f"{result.seconds:.3f} s ({variant}); preview {png}")
    return EXIT_OK


class _Usage(Exception):
    """A usage error detected after argument parsing (exit code 2)."""


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except _Usage as e:
        parser.error(str(e))  # exits with 2
    except KeyboardInterrupt:
        print("mcillum: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # report the real cause, not Dr.Jit's wrapper
        from .renders import root_cause

        cause = root_cause(e)
        print(f"mcillum {args.command}: error: {cause}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
