"""Render a scene with one integrator and time it honestly.

``mi.render`` returns after launching the kernel; the clock stops only after
``dr.sync_thread()``. The first render of a kernel in a process includes its
compilation (or a load from Dr.Jit's disk cache).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from mcillum import integrators
import drjit as dr
import mitsuba as mi
from mcillum.integrators import passes

DEFAULT_VARIANT = "llvm_ad_rgb"


def set_variant(variant: str | None = None) -> str:
    """Select ``variant`` (default: $MCILLUM_VARIANT or llvm_ad_rgb)."""
    variant = variant or os.environ.get("MCILLUM_VARIANT") or DEFAULT_VARIANT
    if variant not in mi.variants():
        raise ValueError(f"unknown Mitsuba variant '{variant}'; available: "
                         f"{', '.join(mi.variants())}")
    if mi.variant() != variant:
        mi.set_variant(variant)
    integrators.register()
    return variant


def parse_value(text: str):
    """Turn a command-line ``value`` into bool, int, float or str (in that order)."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_assignments(items) -> dict:
    """``['k=v', ...]`` → ``{k: parse_value(v)}``; raises ValueError on bad items."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"expected KEY=VALUE, got '{item}'")
        out[key.strip()] = parse_value(value)
    return out


def resolve_defines(path: str | os.PathLike, envmap_policy: str = "clamp", **defines) -> dict:
    """The ``$``-parameters a scene will be loaded with, as strings.

    An ``envmap`` parameter (given, or the scene's default) may be a map name
    (``envmaps.entries()``) or a file; either way it becomes the path of a
    checked file that obeys ``envmap_policy`` (see :mod:`envmaps.safety`).
    """
    from mcillum import envmaps

    from .scenes import defaults

    path = os.fspath(path)
    default = defaults(path).get("envmap")
    if "envmap" in defines or default is not None:
        value = str(defines.get("envmap", default))
        if value not in envmaps.entries() and not os.path.isabs(value):
            value = os.path.join(os.path.dirname(os.path.abspath(path)), value)
        defines["envmap"] = envmaps.resolve(value, envmap_policy)[0]
    return {k: _xml_value(v) for k, v in defines.items()}


def load_scene(path: str | os.PathLike, envmap_policy: str = "clamp", **defines) -> mi.Scene:
    """Load a Mitsuba XML scene with ``$``-parameters ``defines`` (see
    :func:`resolve_defines` for the ``envmap`` parameter)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    return load_resolved(path, resolve_defines(path, envmap_policy, **defines))


def load_resolved(path: str | os.PathLike, resolved: dict) -> mi.Scene:
    """Load a scene with ``$``-parameters already passed through
    :func:`resolve_defines` (so the envmap is not read and checked again)."""
    return mi.load_file(os.fspath(path), **resolved)


def _xml_value(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def make_integrator(name: str, params: dict | None = None) -> mi.Integrator:
    """Instantiate integrator plugin ``name`` with properties ``params``."""
    return mi.load_dict({"type": name, **(params or {})})


@dataclass
class Render:
    """One rendered image and how long it took."""

    image: np.ndarray  # (H, W, C) float32, linear radiance
    seconds: float     # wall time from launch to sync
    spp: int
    seed: int
    meta: dict = field(default_factory=dict)


def render(scene: mi.Scene, integrator: mi.Integrator, spp: int, seed: int = 0) -> Render:
    """Render ``scene`` with ``integrator`` at ``spp`` samples/pixel and ``seed``."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    # mcillum plugins split over-long wavefronts themselves; Mitsuba's own
    # integrators fail when spp does not divide into their pass count.
    plan = [spp] if hasattr(integrator, "unreachable") else passes.plan_passes(
        passes.film_lanes(scene.sensors()[0].film()), spp)
    start = time.perf_counter()
    image = passes.render_in_passes(
        plan, seed, lambda s, n: mi.render(scene, integrator=integrator, spp=n, seed=s))
    dr.sync_thread()
    seconds = time.perf_counter() - start
    return Render(np.array(image, dtype=np.float32), seconds, spp, seed,
                  {"passes": len(plan)} if len(plan) > 1 else {})


def root_cause(exc: BaseException) -> BaseException:
    """The innermost exception of a chain (``mi.render`` wraps plugin errors)."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return exc
