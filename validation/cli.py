"""The ``mcillum`` command: render, bench, envmap, validate, report
(``mcillum COMMAND --help``). It parses arguments and calls the library.

Exit codes, the same rule for every subcommand: 0 success; 2 usage error, what
the command line alone shows to be wrong (a bad option value, an unknown
integrator or integrator parameter, an unknown or ill-typed map parameter, a
scene path that names no file, an output path that cannot be written); 1 what
is found while loading or rendering (a broken scene, an unknown $-parameter, a
refused map, a failed check); 130 interrupted (Ctrl-C), 143 terminated
(SIGTERM). Either way one message, no traceback, and no partial file at an
output path.
"""

from __future__ import annotations

import argparse
import os
import sys

from mcillum import errors, files
from mcillum import plugins as mcillum_plugins
from mcillum.envmaps import catalog, safety

from . import results
from mcillum.integrators.core import registry

from .plan import profiles, scenes
from .results import layout
from .run import executors, jobs, renders, timing

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143


def _scene_arguments(p, param_help: str) -> None:
    """SCENE, -p, -D and --variant, shared by render and bench."""
    p.add_argument("scene", help="Mitsuba 3 XML scene file")
    p.add_argument("--param", "-p", action="append", default=[], metavar="K=V",
                   help=param_help)
    p.add_argument("--define", "-D", action="append", default=[], metavar="K=V",
                   help="scene $-parameter, e.g. res=256 (repeatable)")
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default $MCILLUM_VARIANT or llvm_ad_rgb)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    _plugin_argument(p)


def _plugin_argument(p) -> None:
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE_OR_FILE",
                   help="import a module or Python file that registers your own "
                        "integrators (mi.register_integrator) before anything runs "
                        "(repeatable)")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mcillum",
        description="Monte Carlo estimators of the illumination integral for Mitsuba 3.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    r = sub.add_parser(
        "render", help="render a Mitsuba XML scene with one integrator",
        description="Render SCENE with an mcillum estimator (or any Mitsuba integrator) "
                    "to a float32 EXR with metadata, plus a tone-mapped PNG beside it.")
    _scene_arguments(r, "integrator property, e.g. max_depth=2 (repeatable)")
    r.add_argument("--integrator", "-i", required=True,
                   help="integrator plugin, e.g. cosine_hemisphere, uniform_hemisphere, path")
    r.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    r.add_argument("--exposure", type=float, default=0.0,
                   help="exposure of the PNG preview in stops (default 0)")
    r.add_argument("--output", "-o", required=True, help="output .exr path")

    b = sub.add_parser(
        "bench", help="time integrators against each other on one scene",
        description="Render SCENE once per integrator (compile), then RUNS interleaved "
                    "warm rounds at SPP/4 and SPP; fit t = a + b*spp per integrator and "
                    "print a (fixed cost) and b (seconds per spp) with 95 %% bootstrap "
                    "intervals, and b as a ratio to the first integrator's; optionally "
                    "write them as JSON.")
    _scene_arguments(b, "property given to every integrator, e.g. max_depth=8")
    b.add_argument("--integrators", default="path,uniform_hemisphere,cosine_hemisphere",
                   help="comma-separated plugin names; ratios are to the first "
                        "(default path,uniform_hemisphere,cosine_hemisphere)")
    b.add_argument("--runs", type=int, default=5, help="warm rounds (default 5)")
    b.add_argument("--json", default=None, metavar="FILE", help="also write results here")

    e = sub.add_parser(
        "envmap", help="list, generate or check environment maps",
        description="Write environment map NAME (a procedural map or a real light probe, "
                    "sanitised by the loading policy) to an EXR; or list every map.")
    e.add_argument("name", nargs="?", help="map name (see --list) or an EXR file to check")
    e.add_argument("--list", action="store_true", help="list every map with its licence")
    e.add_argument("--param", "-p", action="append", default=[], metavar="K=V",
                   help="generator parameter, e.g. alpha_deg=30 or radiance=2 (repeatable)")
    e.add_argument("--policy", choices=safety.POLICIES, default=safety.DEFAULT_POLICY,
                   help="NaN/Inf/negative policy for files (default clamp: negatives → 0, "
                        "NaN/Inf refused)")
    e.add_argument("--output", "-o", help="output .exr path")

    v = sub.add_parser(
        "validate", help="compare the estimators with Mitsuba's path tracer",
        description="Compare every estimator with an adaptive `path` reference on the "
                    "profile's scenes (unbiasedness, convergence, equal time) and drive "
                    "each into the cases where it fails; write results.json, results.csv, "
                    "summary.md, images and the report to --out. Every check passes, fails "
                    "or is inconclusive (the evidence cannot decide at this budget). Exit 0 "
                    "if no check fails (with --strict: if every check passes), 1 otherwise, "
                    "2 on usage errors.")
    v.add_argument("scene", nargs="*", metavar="SCENE",
                   help="Mitsuba XML scene files to compare on (your own: its <integrator> "
                        "is replaced by each compared one and by the reference, its "
                        "max_depth, rr_depth and hide_emitters kept), or names of the "
                        "profile's scenes; default: the profile's scenes")
    v.add_argument("--profile", default="quick", metavar="NAME_OR_FILE",
                   help="quick (default), full, or a profile file (.toml)")
    v.add_argument("--groups", nargs="+", choices=profiles.GROUPS,
                   default=list(profiles.GROUPS),
                   help="run the scene comparisons and/or the failures group (default both)")
    v.add_argument("--scenes", nargs="+", metavar="SCENE",
                   help="subset of the profile's scenes (filters both groups)")
    v.add_argument("--estimators", nargs="+", metavar="NAME",
                   help="integrator plugins to validate; path, the reference, is added "
                        "(default: every registered mcillum estimator, then path)")
    _plugin_argument(v)
    v.add_argument("--define", "-D", action="append", default=[], metavar="K=V",
                   help="$-parameter of the scene files given (repeatable)")
    v.add_argument("--max-depth", type=int, metavar="N",
                   help="max_depth of every integrator and the reference on the scene "
                        "files given (default: the scene's integrator's)")
    v.add_argument("--rr-depth", type=int, metavar="N",
                   help="rr_depth, likewise (default: the scene's)")
    v.add_argument("--hide-emitters", choices=("true", "false"),
                   help="hide_emitters, likewise (default: the scene's)")
    v.add_argument("--res", type=int, metavar="N",
                   help="longest side of the statistics film of the scene files given "
                        "(default: the profile's reduced-film rule)")
    v.add_argument("--out", default="out/validate", help="output directory (default out/validate)")
    v.add_argument("--junit", metavar="FILE", help="also write JUnit XML, one case per check")
    v.add_argument("--cache", metavar="DIR", help="reference cache (default $MCILLUM_CACHE "
                                                  "or ~/.cache/mcillum)")
    v.add_argument("--variant", default=None, help="Mitsuba variant")
    v.add_argument("--seed-set", type=int, default=0, metavar="S",
                   help="an independent repeat of the whole run, references included "
                        "(0…999, default 0): for measuring how often the tests reject "
                        "correct estimators")
    v.add_argument("--budget", type=float, default=None, metavar="X",
                   help="how far a check that cannot decide may render on: X times its "
                        "first look's samples per pixel (default: the profile's "
                        "[sequential] budgets); an inconclusive check says which budget "
                        "would decide")
    v.add_argument("--strict", action="store_true",
                   help="exit 1 when a check is inconclusive, not only when one fails "
                        "(JUnit then reports inconclusive checks as failures, not skipped)")
    v.add_argument("--no-speed", action="store_true",
                   help="leave out the speed-and-images stage (no verdict depends on it)")
    v.add_argument("--quiet", "-q", action="store_true",
                   help="no progress on stderr (default: one updating line on a terminal; "
                        "in a log, a line as each stage starts and about every 30 s)")
    v.add_argument("--executor", choices=executors.KINDS, default="local",
                   help="where the renders run: this process (local, default) or a Ray "
                        "cluster (ray; pip install 'mcillum[ray]'); the images are the same")
    v.add_argument("--ray-address", metavar="ADDR",
                   help="with --executor ray: the cluster to join (auto, or ray://HOST:10001); "
                        "default: start a Ray instance on this machine")
    v.add_argument("--ray-workers", type=int, metavar="N",
                   help="with --executor ray: render workers (default one per CPU of the "
                        "cluster, or per GPU for a cuda variant)")

    rp = sub.add_parser(
        "report", help="(re)write the HTML report of an existing validation run",
        description="Read RESULTS_DIR/results.json and its images and write "
                    "RESULTS_DIR/report/index.html (self-contained) and RESULTS_DIR/summary.md.")
    rp.add_argument("results_dir", help="a directory written by `mcillum validate --out`")
    for p, run in ((r, _render), (b, _bench), (e, _envmap), (v, _validate), (rp, _report)):
        p.set_defaults(run=run, subparser=p)
    return parser


_Usage = errors.UsageError


def _assignments(items) -> dict:
    try:
        return renders.parse_assignments(items)
    except ValueError as err:
        raise _Usage(str(err)) from None


# --------------------------------- Commands ------------------------------------

def _exr_output(path: str) -> None:
    if not path.lower().endswith(".exr"):
        raise _Usage(f"output must be an .exr path, got '{path}'")
    files.check_output(path)


def _scene_file(path: str) -> None:
    """Raise a usage error (exit 2) for a scene path that names no file: the
    command line alone shows it, in every subcommand alike."""
    if os.path.isdir(path):
        raise _Usage(f"cannot load scene {path}: it is a directory; give an XML file")
    if not os.path.isfile(path):
        raise _Usage(f"scene file not found: {path}")


def _render(args) -> int:
    _scene_file(args.scene)
    _exr_output(args.output)
    if args.spp < 1:
        raise _Usage(f"--spp must be >= 1, got {args.spp}")
    if not 0 <= args.seed < 2 ** 32:
        raise _Usage(f"--seed must be in [0, 2^32 - 1] (Mitsuba's seeds are 32-bit "
                     f"unsigned), got {args.seed}")
    params, defines = _assignments(args.param), _assignments(args.define)
    png = renders.preview_path(args.output)
    files.check_output(png, "the PNG preview")
    files.remove_stale_partials(os.path.dirname(os.path.abspath(args.output)))

    variant = renders.set_variant(args.variant)
    _load_plugins(args.plugin, variant)
    integrator = renders.make_integrator(args.integrator, params)
    scene = renders.load_scene(args.scene, **defines)
    result = renders.render(scene, integrator, args.spp, args.seed)
    meta = renders.provenance(args.scene, args.integrator, integrator, params, defines,
                              result, variant)
    renders.save(args.output, result, meta, args.exposure)
    h, w = result.image.shape[:2]
    print(f"{args.output}: {w}x{h}, {args.spp} spp, {args.integrator}, "
          f"{result.seconds:.3f} s ({variant}); preview {png}")
    if "biased" in meta:
        print(f"warning: BIASED image (allow_unreachable=true): it lacks {meta['biased']}; "
              "the EXR header records this as mcillum.biased", file=sys.stderr)
    return EXIT_OK


def _bench(args) -> int:
    _scene_file(args.scene)
    if args.spp < 1 or args.runs < 2:
        raise _Usage("--spp must be >= 1 and --runs >= 2 (an interval needs repeats)")
    params, defines = _assignments(args.param), _assignments(args.define)
    names = [n.strip() for n in args.integrators.split(",") if n.strip()]
    if not names:
        raise _Usage("--integrators is empty")
    if args.json:
        files.check_output(args.json, "--json")
    variant = renders.set_variant(args.variant)
    _load_plugins(args.plugin, variant)
    integrators = {n: jobs.make(n, params) for n in names}
    scene = renders.load_scene(args.scene, **defines)
    rows = timing.bench(scene, integrators, args.spp, args.runs)
    for row in rows:
        print(timing.bench_line(row, names[0]))
    if args.json:
        timing.write_json(args.json, args.scene, scene, defines, params, args.spp, variant,
                          rows)
    return EXIT_OK


def _envmap(args) -> int:
    if args.list:
        print(catalog.listing())
        return EXIT_OK
    if not args.name:
        raise _Usage("give a map NAME (or --list)")
    if not args.output:
        raise _Usage("give an output path with -o FILE.exr")
    _exr_output(args.output)
    rgb, report = catalog.load(args.name, args.policy, **_assignments(args.param))
    files.write_exr(args.output, rgb)
    h, w = rgb.shape[:2]
    print(f"{args.output}: {args.name}, {w}x{h}" + (f"; {report}" if report else ""))
    return EXIT_OK


def _validate(args) -> int:
    # (the pipeline pulls in scipy and matplotlib, imports that the other
    # commands do not need)
    from . import pipeline

    profile = profiles.resolve(args.profile)
    names = [*args.scene, *(args.scenes or [])]
    profile.check_scenes([n for n in names if not scenes.is_path(n)])
    for name in names:
        if scenes.is_path(name):
            _scene_file(name)
    given = [n for n in (args.max_depth, args.rr_depth, args.hide_emitters, args.res)
             if n is not None]
    if given and not (any(scenes.is_path(n) for n in names)
                      or (not names and profile.scene_files)):
        raise _Usage("--max-depth, --rr-depth, --hide-emitters and --res apply to scene "
                     "files given by path; the profile's scenes have their own")
    if args.res is not None and args.res < 1:
        raise _Usage(f"--res must be >= 1, got {args.res}")
    if not 0 <= args.seed_set < 1000:
        raise _Usage(f"--seed-set must be in 0…999, got {args.seed_set}")
    if args.budget is not None and not args.budget >= 1:
        raise _Usage(f"--budget must be >= 1 (× a check's first samples), got {args.budget}")
    if args.executor != "ray" and (args.ray_address or args.ray_workers is not None):
        raise _Usage("--ray-address and --ray-workers need --executor ray")
    if args.ray_workers is not None and args.ray_workers < 1:
        raise _Usage(f"--ray-workers must be >= 1, got {args.ray_workers}")
    if args.executor == "ray":
        executors.check_ray()
    files.make_dir(args.out, "--out")
    if args.junit:
        files.check_output(args.junit, "--junit")
    cache = args.cache or files.cache_dir()
    files.make_dir(cache, "the reference cache", "choose another with --cache DIR")
    variant = renders.set_variant(args.variant)
    plugins = [*profile.plugins, *args.plugin]
    _load_plugins(plugins, variant)
    estimators = args.estimators and list(dict.fromkeys([*args.estimators,
                                                         registry.REFERENCE]))
    for name in estimators or []:          # (unknown names: a usage error, now)
        renders.make_integrator(name, {})
    settings = {"max_depth": args.max_depth, "rr_depth": args.rr_depth,
                "hide_emitters": None if args.hide_emitters is None
                else args.hide_emitters == "true"}
    out = pipeline.validate(profile, names, estimators, args.out, cache,
                            args.variant, groups=tuple(args.groups),
                            seed_set=args.seed_set, speed_stage=not args.no_speed,
                            executor=args.executor, ray_address=args.ray_address,
                            ray_workers=args.ray_workers, plugins=args.plugin,
                            budget=args.budget,
                            settings=settings, defines=_assignments(args.define),
                            res=args.res, progress=False if args.quiet else None)
    if args.junit:
        results.write_junit(args.junit, out, strict=args.strict)
    print(results.summary(out))
    print(f"report: {layout.report_html(args.out)}")
    ok = out.passed and not (args.strict and out.inconclusive)
    print(f"{'PASSED' if ok else 'FAILED'}: {results.counts_line(out)}"
          + (" (--strict: inconclusive fails)" if args.strict and out.inconclusive else ""))
    return EXIT_OK if ok else EXIT_FAILED


def _load_plugins(specs, variant: str) -> list:
    """Import each ``--plugin`` (mcillum/plugins.py); a failure is a usage
    error naming the file and the exception's last line."""
    return [mcillum_plugins.load(spec, variant) for spec in dict.fromkeys(specs)]


def _report(args) -> int:
    from . import report  # (matplotlib: see _validate)

    res = results.load(args.results_dir)
    files.check_writable_dir(args.results_dir)
    print(report.build(args.results_dir, res))
    results.write_summary(args.results_dir, res)
    return EXIT_OK


# ---------------------------------- Entry --------------------------------------

def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    with errors.sigterm_as_interrupt():
        return _run(args)


def _run(args) -> int:
    name = f"mcillum {args.command}"
    try:
        return args.run(args)
    except errors.UserError as err:
        if err.usage:
            args.subparser.error(str(err))  # exits with 2
        print(f"{name}: error: {err}", file=sys.stderr)
    except errors.Interrupted as err:
        return _stopped(name, err.__context__, f": {err}")
    except (KeyboardInterrupt, Exception) as err:  # the real cause, not Dr.Jit's wrapper
        if errors.is_interrupt(err):
            return _stopped(name, err, "; no partial output files are left")
        print(f"{name}: error: {errors.message(err)}", file=sys.stderr)
    return EXIT_FAILED


def _stopped(name: str, cause, what: str) -> int:
    terminated = isinstance(errors.root_cause(cause), errors.Terminated) if cause else False
    print(f"{name}: {'terminated (SIGTERM)' if terminated else 'interrupted'}{what}",
          file=sys.stderr)
    return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
