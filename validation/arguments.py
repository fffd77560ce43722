"""The ``mcillum`` command's arguments: one parser per subcommand
(validation/cli.py runs them). Each help text is what ``mcillum COMMAND
--help`` prints."""

from __future__ import annotations

import argparse

from mcillum.envmaps import safety

from .plan import profiles
from .run import executors


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


def parser(runs: dict) -> argparse.ArgumentParser:
    """The ``mcillum`` parser: one subparser per command, each knowing the
    function that runs it (``run``, from ``runs``: command → function) and
    itself (``subparser``, for usage errors)."""
    top = argparse.ArgumentParser(
        prog="mcillum",
        description="Monte Carlo estimators of the illumination integral for Mitsuba 3.")
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, add in (("render", _render_parser), ("bench", _bench_parser),
                      ("envmap", _envmap_parser), ("validate", _validate_parser),
                      ("report", _report_parser)):
        p = add(sub)
        p.set_defaults(run=runs[name], subparser=p)
    return top


def _render_parser(sub) -> argparse.ArgumentParser:
    """``mcillum render``'s parser, added to ``sub``."""
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
    return r


def _bench_parser(sub) -> argparse.ArgumentParser:
    """``mcillum bench``'s parser, added to ``sub``."""
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
    return b


def _envmap_parser(sub) -> argparse.ArgumentParser:
    """``mcillum envmap``'s parser, added to ``sub``."""
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
    return e


def _validate_parser(sub) -> argparse.ArgumentParser:
    """``mcillum validate``'s parser, added to ``sub``: what to compare,
    the scene files' settings, where to write, and how to run."""
    v = sub.add_parser(
        "validate", help="compare the estimators with Mitsuba's path tracer",
        description="Compare every estimator with an adaptive `path` reference on the "
                    "profile's scenes (unbiasedness, convergence, equal time) and drive "
                    "each into the cases where it fails; write results.json, results.csv, "
                    "summary.md, images and the report to --out. Every check passes, fails "
                    "or is inconclusive (the evidence cannot decide at this budget). Exit 0 "
                    "if no check fails (with --strict: if every check passes), 1 otherwise, "
                    "2 on usage errors.")
    _validate_what(v)
    _validate_scene_files(v)
    _validate_output(v)
    _validate_how(v)
    return v


def _validate_what(v) -> None:
    """validate: which scenes, profile, groups and estimators."""
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


def _validate_scene_files(v) -> None:
    """validate: the settings of scene files given by path."""
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


def _validate_output(v) -> None:
    """validate: where the results and the references' cache go."""
    v.add_argument("--out", default="out/validate", help="output directory (default out/validate)")
    v.add_argument("--junit", metavar="FILE", help="also write JUnit XML, one case per check")
    v.add_argument("--cache", metavar="DIR", help="reference cache (default $MCILLUM_CACHE "
                                                  "or ~/.cache/mcillum)")


def _validate_how(v) -> None:
    """validate: variant, seed set, budget, strictness, progress and executor."""
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


def _report_parser(sub) -> argparse.ArgumentParser:
    """``mcillum report``'s parser, added to ``sub``."""
    rp = sub.add_parser(
        "report", help="(re)write the HTML report of an existing validation run",
        description="Read RESULTS_DIR/results.json and its images and write "
                    "RESULTS_DIR/report/index.html (self-contained) and RESULTS_DIR/summary.md.")
    rp.add_argument("results_dir", help="a directory written by `mcillum validate --out`")
    return rp
