"""The ``mcillum`` command.

    mcillum render SCENE.xml --integrator NAME [--spp N] [--seed S]
                   [--param K=V ...] [--define K=V ...] [--variant V]
                   [--exposure EV] -o OUT.exr

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
    return parser


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
