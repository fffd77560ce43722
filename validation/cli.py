"""The ``mcillum`` command: render, bench, envmap, validate, report
(``mcillum COMMAND --help``). It parses arguments (one parser per
subcommand: arguments.py) and calls the library.

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

import os
import sys

from mcillum import errors, files
from mcillum import plugins as mcillum_plugins
from mcillum.envmaps import catalog
from mcillum.integrators.core import registry

from . import arguments, results
from .plan import profiles, scenes, seeds
from .results import layout
from .run import executors, jobs, renders, timing

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143

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
    try:
        seeds.check_set(args.seed_set)
    except ValueError:
        raise _Usage(f"--seed-set must be in 0…{seeds.SETS - 1}, got {args.seed_set}") from None
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
    setup = pipeline.set_up(profile, args.variant, args.plugin)
    estimators = args.estimators and list(dict.fromkeys([*args.estimators,
                                                         registry.REFERENCE]))
    for name in estimators or []:          # (unknown names: a usage error, now)
        renders.make_integrator(name, {})
    settings = {"max_depth": args.max_depth, "rr_depth": args.rr_depth,
                "hide_emitters": None if args.hide_emitters is None
                else args.hide_emitters == "true"}
    out = pipeline.validate(profile, names, estimators, args.out, cache,
                            groups=tuple(args.groups),
                            seed_set=args.seed_set, speed_stage=not args.no_speed,
                            executor=args.executor, ray_address=args.ray_address,
                            ray_workers=args.ray_workers, setup=setup,
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
    args = arguments.parser({"render": _render, "bench": _bench, "envmap": _envmap,
                             "validate": _validate, "report": _report}).parse_args(argv)
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
