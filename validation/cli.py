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

Exit codes: 0 success, 1 the render failed (message on stderr), 2 usage error,
130 interrupted (Ctrl-C). Usage errors are what the command line alone shows to
be wrong (a bad option value, an output path that cannot be written); what is
found on loading or rendering (a broken scene, an unknown integrator or
property, a refused envmap) exits 1. Either way one message, no traceback, and
no partial file at an output path.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


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
    r.set_defaults(run=_render, subparser=r)

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
    b.set_defaults(run=_bench, subparser=b)

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
    e.set_defaults(run=_envmap, subparser=e)

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
    v.set_defaults(run=_validate, subparser=v)

    rp = sub.add_parser(
        "report", help="(re)write the HTML report of an existing validation run",
        description="Read RESULTS_DIR/results.json and its images and write "
                    "RESULTS_DIR/report/index.html (self-contained) and summary.md.")
    rp.add_argument("results_dir", help="a directory written by `mcillum validate --out`")
    rp.set_defaults(run=_report, subparser=rp)
    return parser


def _report(args) -> int:
    import json

    from . import report, results

    path = os.path.join(args.results_dir, "results.json")
    if not os.path.isfile(path):
        raise _Usage(f"no results.json in {args.results_dir}: run `mcillum validate "
                     f"--out {args.results_dir}` first")
    again = f"run `mcillum validate --out {args.results_dir}` again"
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (ValueError, UnicodeDecodeError) as err:
        raise _Failed(f"{path} is not valid JSON ({err}): {again}") from None
    if not isinstance(data, dict) or data.get("schema") != results.SCHEMA:
        raise _Failed(f"{path} is not an mcillum results file (no \"schema\": "
                      f"\"{results.SCHEMA}\")")
    if data.get("version") != results.VERSION:
        raise _Failed(f"{path} has results version {data.get('version')!r}; this mcillum "
                      f"reads version {results.VERSION}: {again}")
    _check_writable_dir(args.results_dir)
    try:
        print(report.build(args.results_dir))
    except KeyError as err:
        raise _Failed(f"{path} lacks the field {err}: {again}") from None
    except FileNotFoundError as err:
        raise _Failed(f"{err.filename or err} is missing (the report needs every image "
                      f"of the run): {again}") from None
    return EXIT_OK


def _validate(args) -> int:
    from . import profiles, results, validate

    profile = profiles.PROFILES[args.profile]
    known = {r.scene for r in profile.runs}
    for name in args.scenes or []:
        if name not in known:
            raise _Usage(f"scene '{name}' is not in profile '{args.profile}' "
                         f"({', '.join(sorted(known))})")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise _Usage(f"--out {args.out} is a file, not a directory: give a directory")
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as err:
        raise _Usage(f"cannot create --out {args.out}: {err.strerror}") from None
    _check_writable_dir(args.out, "--out")
    if args.junit:
        _check_output(args.junit, "--junit")
    cache = args.cache or os.environ.get("MCILLUM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "mcillum")
    try:
        os.makedirs(cache, exist_ok=True)
    except OSError as err:
        raise _Usage(f"cannot create the reference cache {cache}: {err.strerror} "
                     "(choose another with --cache DIR)") from None
    _check_writable_dir(cache, "the reference cache (--cache)")
    if args.estimators:
        from . import renders

        renders.set_variant(args.variant)
        for name in args.estimators:
            try:
                _make_integrator(renders, name, {})
            except _Failed as err:
                raise _Usage(str(err)) from None
    results_json = os.path.join(args.out, "results.json")
    before = _stamp(results_json)
    try:
        out = validate.validate(args.profile, args.scenes, args.estimators, args.out,
                                args.cache, args.variant)
    except (KeyboardInterrupt, Exception) as err:
        if not _is_interrupt(err):
            raise
        after = _stamp(results_json)
        if after is None:
            raise _Interrupted(f"no results were written; finished renders are kept in "
                               f"{args.out} and reused: run the same command again to "
                               "resume") from None
        if after == before:
            raise _Interrupted(f"{results_json} is from an earlier run (created "
                               f"{after[1]}), not this one; finished renders are kept in "
                               f"{args.out} and reused: run the same command again to "
                               "resume") from None
        raise _Interrupted(f"while writing the report: {results_json} is complete; run "
                           f"`mcillum report {args.out}` to write the report") from None
    if args.junit:
        results.write_junit(args.junit, out)
    print(results.summary(out))
    print(f"report: {os.path.join(args.out, 'report', 'index.html')}")
    return EXIT_OK if out["passed"] else EXIT_FAILED


def _stamp(path: str):
    """(mtime, ``created``) of a results.json; None if absent or unreadable."""
    import json

    try:
        with open(path, encoding="utf-8") as f:
            created = json.load(f).get("created") or "at an unknown date"
        return os.stat(path).st_mtime_ns, created
    except (OSError, ValueError, AttributeError):
        return None


def _envmap(args) -> int:
    from mcillum import envmaps
    from mcillum.envmaps import catalog, procedural, safety

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
    _check_output(args.output)
    from .renders import parse_assignments

    try:
        params = parse_assignments(args.param)
    except ValueError as err:
        raise _Usage(str(err)) from None
    try:
        if args.name in catalog.PROCEDURAL:
            rgb, report = catalog.generate(args.name, **params), None
        else:
            if params:
                raise _Usage("--param applies to procedural maps only")
            path = envmaps.probes.path(args.name) if args.name in envmaps.probes.names() \
                else args.name
            rgb, report = safety.load(path, args.policy)
    except (safety.EnvmapError, ValueError) as err:
        raise _Failed(_envmap_message(err, args.name, params)) from None
    try:
        procedural.write(args.output, rgb)
    except OSError as err:
        raise _Failed(f"cannot write {args.output}: {err.strerror or err}") from None
    h, w = rgb.shape[:2]
    print(f"{args.output}: {args.name}, {w}x{h}" + (f"; {report}" if report else ""))
    return EXIT_OK


def _envmap_message(err: Exception, value: str, params: dict | None = None,
                    base_dir: str | None = None) -> str:
    """``err`` from loading or generating map ``value``, with what to do about it."""
    from mcillum.envmaps import catalog

    text = str(err)
    if "not found" in text and value not in catalog.entries():
        where = (f" (a relative path is taken from the scene's directory, {base_dir})"
                 if base_dir and not os.path.isabs(value) else "")
        return (f"{text}; give a map name (see `mcillum envmap --list`) or the path of "
                f"an existing .exr file{where}")
    if params and value in catalog.PROCEDURAL:
        words = [f"{k}={v}" for k, v in params.items() if isinstance(v, str)]
        if words:
            text += f" (not numbers: {', '.join(words)})"
        try:
            import inspect

            from mcillum.envmaps import procedural

            known = inspect.signature(getattr(procedural, value)).parameters
            text += f"; map '{value}' takes {', '.join(known)}"
        except (AttributeError, TypeError, ValueError):
            pass
    return text


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
    if args.json:
        _check_output(args.json, "--json")

    variant = renders.set_variant(args.variant)
    scene = _load_scene(renders, args.scene, defines)
    integrators = {n: _make_integrator(renders, n, params) for n in names}
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
        try:
            with images.atomic_path(args.json) as tmp, open(tmp, "w") as f:
                json.dump(report, f, indent=2)
        except OSError as err:
            raise _Failed(f"cannot write {args.json}: {err.strerror or err}") from None
    return EXIT_OK


def _render(args) -> int:
    # Imported here so that `mcillum --help` works without loading Mitsuba.
    from . import images, renders

    if not args.output.lower().endswith(".exr"):
        raise _Usage(f"output must be an .exr path, got '{args.output}'")
    if args.spp < 1:
        raise _Usage(f"--spp must be >= 1, got {args.spp}")
    if not 0 <= args.seed < 2 ** 32:
        raise _Usage(f"--seed must be in [0, 2^32 - 1] (Mitsuba's seeds are 32-bit "
                     f"unsigned), got {args.seed}")
    try:
        params = renders.parse_assignments(args.param)
        defines = renders.parse_assignments(args.define)
    except ValueError as e:
        raise _Usage(str(e)) from None
    png = os.path.splitext(args.output)[0] + ".png"
    _check_output(args.output)
    _check_output(png, "the PNG preview")

    variant = renders.set_variant(args.variant)
    scene = _load_scene(renders, args.scene, defines)
    integrator = _make_integrator(renders, args.integrator, params)
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
    missing = getattr(integrator, "unreachable", [])
    if missing:   # allow_unreachable=true: the file must say it is biased
        meta["biased"] = "; ".join(p.what for p in missing)
    for path, write in ((args.output, lambda p: images.write_exr(p, result.image, meta)),
                        (png, lambda p: images.write_png(p, result.image, args.exposure))):
        try:
            write(path)
        except OSError as err:
            raise _Failed(f"cannot write {path}: {err.strerror or err}") from None
    h, w = result.image.shape[:2]
    print(f"{args.output}: {w}x{h}, {args.spp} spp, {args.integrator}, "
          f"{result.seconds:.3f} s ({variant}); preview {png}")
    if missing:
        print(f"warning: BIASED image (allow_unreachable=true): it lacks {meta['biased']}; "
              "the EXR header records this as mcillum.biased", file=sys.stderr)
    return EXIT_OK


# ------------------------- checks and messages -------------------------------

def _check_output(path: str, what: str = "output") -> None:
    """Refuse (usage error) an output file path that cannot be written, before
    any work is done: a directory, a missing or non-directory parent, or a
    parent where no file can be created (tried, not guessed from permission
    bits, which root ignores)."""
    if os.path.isdir(path):
        raise _Usage(f"{what} {path} is a directory: give a file path")
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.exists(directory) and not os.path.isdir(directory):
        raise _Usage(f"cannot write {what} {path}: {directory} is a file, not a directory")
    if not os.path.isdir(directory):
        raise _Usage(f"output directory does not exist: {directory} (create it first)")
    _check_writable_dir(directory, f"{what} {path}")


def _check_writable_dir(directory: str, what: str | None = None) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=".partial-probe-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise _Usage(f"cannot write {what or directory}: no file can be created in "
                     f"{directory} ({err.strerror}); choose a writable location") from None


#: Mitsuba's "[parser.cpp:1718] " source locations.
_SOURCE = re.compile(r"\[[\w./\\-]+\.(?:cpp|h|inl|py):\d+\]\s*")
_TRACEBACK = "Traceback (most recent call last):"
#: The head of Mitsuba's errors from ``mi.load_dict`` (no file, no line: noise).
_DICT_HEAD = re.compile(r'^(?:While loading|At) dictionary node "[^"]*":\s*'
                        r'(?:failed to instantiate [\w ]*plugin of type "[^"]*":\s*)?')


def _message(err: BaseException, context: bool = True) -> str:
    """The innermost cause of ``err`` as one clean message: no Mitsuba source
    locations, and no Python traceback (Mitsuba embeds one in the message of a
    Python plugin's exception): only its last exception line. ``context=False``
    drops Mitsuba's "At dictionary node ...: failed to instantiate ..." head."""
    cause = _root_cause(err)
    text = str(cause).strip() or f"{type(cause).__name__} (no message)"
    head, marker, _ = text.partition(_TRACEBACK)
    if marker:
        lines = text.rpartition(_TRACEBACK)[2].splitlines()[1:]
        start = next((k for k, line in enumerate(lines) if line and not line[0].isspace()),
                     len(lines))
        last = re.sub(r"^[A-Za-z_][\w.]*(?:Error|Exception): ", "",
                      "\n".join(lines[start:]).strip())
        head = head.strip().rstrip(":").strip()
        text = f"{head}: {last}" if head and context else last
    text = _SOURCE.sub("", text).replace("unknown plugin of type", "plugin of type")
    if not context:
        text = _DICT_HEAD.sub("", text)
    return text.strip()


def _load_scene(renders, path: str, defines: dict):
    """``renders.load_scene`` with each failure turned into a message that
    names the file (and line, where Mitsuba gives one) and what to do."""
    from mcillum import envmaps

    shown = " ".join(f"-D {k}={v}" for k, v in defines.items())
    if os.path.isdir(path):
        raise _Failed(f"cannot load scene {path}: it is a directory; give an XML file")
    try:
        scene = renders.load_scene(path, **defines)
    except envmaps.EnvmapError as err:
        from . import scenes

        value = str(defines.get("envmap", scenes.defaults(path).get("envmap", "")))
        raise _Failed(_envmap_message(err, value, None,
                                      os.path.dirname(os.path.abspath(path)))) from None
    except FileNotFoundError as err:
        raise _Failed(str(err)) from None
    except UnicodeDecodeError:
        raise _Failed(f"cannot load scene {path}: not a UTF-8 text (XML) file") from None
    except Exception as err:  # Mitsuba's parser and plugins
        text = _message(err)
        unused = re.findall(r"^\s*- \$(\w+)=", text, re.M)
        if unused:
            from . import scenes

            declared = ", ".join(scenes.defaults(path)) or "none declared"
            raise _Failed(f"scene {path} has no $-parameter {', '.join(unused)} (given "
                          f"with -D); its parameters: {declared}") from None
        hint = f" (check the values of {shown})" if shown else ""
        if "Parsing of XML file" in text:
            hint = ": fix the XML at that line"
        raise _Failed(f"cannot load scene {path}: {text}{hint}") from None
    for sensor in scene.sensors():
        w, h = (int(x) for x in sensor.film().crop_size())
        if w < 1 or h < 1:
            raise _Failed(f"scene {path} has a {w}x{h} film: nothing to render; give it a "
                          f"positive size" + (f" (got {shown})" if shown else ""))
    return scene


def _mcillum_integrators() -> list:
    from mcillum import integrators
    import mitsuba as mi

    names = []
    for name in integrators.PLUGINS:
        try:
            if isinstance(mi.load_dict({"type": name}), mi.Integrator):
                names.append(name)
        except Exception:  # noqa: BLE001  (a plugin that needs properties)
            pass
    return names


def _integrator_hint() -> str:
    return (f"mcillum's integrators are {', '.join(_mcillum_integrators())}; any "
            "Mitsuba integrator also works (e.g. path, volpath, direct)")


def _make_integrator(renders, name: str, params: dict):
    """``renders.make_integrator`` with each failure as a message saying what to
    do; refuses plugins that are not integrators."""
    import mitsuba as mi

    shown = " ".join(f"-p {k}={v}" for k, v in params.items())
    try:
        integrator = renders.make_integrator(name, params)
    except Exception as err:
        text = _message(err, context=False)
        if re.search(r'Plugin "[^"]*" not found', text):
            raise _Failed(f"unknown integrator '{name}': {_integrator_hint()}") from None
        unknown = re.findall(r'^\s*- \w+ "([^"]+)"', text, re.M)
        if "unreferenced propert" in text and unknown:
            raise _Failed(
                f"integrator '{name}' has no parameter {', '.join(unknown)}: mcillum's "
                "integrators take max_depth, rr_depth, hide_emitters and "
                "allow_unreachable; Mitsuba's own are listed in its documentation "
                "(Plugin reference > Integrators)") from None
        raise _Failed(f"integrator '{name}' rejected {shown or 'its defaults'}: "
                      f"{text}") from None
    if not isinstance(integrator, mi.Integrator):
        kind = next((k for c, k in ((mi.BSDF, "a BSDF"), (mi.Emitter, "an emitter"),
                                    (mi.Shape, "a shape"), (mi.Texture, "a texture"),
                                    (mi.Sensor, "a sensor")) if isinstance(integrator, c)),
                    "another kind of")
        raise _Failed(f"'{name}' is {kind} plugin, not an integrator: {_integrator_hint()}")
    return integrator


class _Usage(Exception):
    """A usage error detected after argument parsing (exit code 2)."""


class _Failed(Exception):
    """A failure whose message is already written for the user (exit code 1)."""


class _Interrupted(Exception):
    """Ctrl-C, with what is left and what to do (exit code 130)."""


def _root_cause(err: BaseException) -> BaseException:
    """The innermost exception of a chain (``mi.render`` wraps plugin errors);
    as ``renders.root_cause``, without importing Mitsuba to print an error."""
    while err.__cause__ is not None:
        err = err.__cause__
    return err


def _is_interrupt(err: BaseException) -> bool:
    """Ctrl-C, possibly wrapped by Mitsuba or Dr.Jit on its way out of a render."""
    return isinstance(_root_cause(err), KeyboardInterrupt) or "KeyboardInterrupt" in str(err)


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except _Usage as e:
        args.subparser.error(str(e))  # exits with 2
    except _Interrupted as e:
        print(f"mcillum {args.command}: interrupted: {e}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _Failed as e:
        print(f"mcillum {args.command}: error: {e}", file=sys.stderr)
        return EXIT_FAILED
    except (KeyboardInterrupt, Exception) as e:  # the real cause, not Dr.Jit's wrapper
        if _is_interrupt(e):
            print(f"mcillum {args.command}: interrupted; no partial output files are left",
                  file=sys.stderr)
            return EXIT_INTERRUPTED
        print(f"mcillum {args.command}: error: {_message(e)}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
