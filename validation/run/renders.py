"""Load a scene, make an integrator, render once and time it honestly.

``mi.render`` returns after launching the kernel; the clock stops only after
``dr.sync_thread()``. The first render of a kernel in a process includes its
compilation (or a load from Dr.Jit's disk cache).

Loading and making integrators raise :class:`~mcillum.errors.SceneError` and
:class:`~mcillum.errors.IntegratorError` with messages that say what was wrong and
what to do (Mitsuba's own say where in its source it noticed).
"""

from __future__ import annotations

import os
import re
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mcillum import envmaps, files, images, integrators
from mcillum.integrators.core import passes, registry
from mcillum.integrators.quadrature import gp_quadrature

from mcillum.errors import IntegratorError, SceneError, message, plugin_not_found
from mcillum.errors import unreferenced_properties, unused_defines

from ..plan import scene_files, scenes
from . import load

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


# ----------------------------------- Scenes -----------------------------------

def resolve_defines(path: str | os.PathLike, envmap_policy: str = "clamp", **defines) -> dict:
    """The ``$``-parameters a scene will be loaded with, as strings.

    An ``envmap`` parameter (given, or the scene's default) may be a map name
    (``envmaps.entries()``) or a file; either way it becomes the path of a
    checked file that obeys ``envmap_policy`` (see :mod:`mcillum.envmaps.safety`).
    A relative file is taken from the scene's directory.
    """
    path = os.fspath(path)
    default = scenes.defaults(path).get("envmap")
    if "envmap" in defines or default is not None:
        value = str(defines.get("envmap", default))
        relative = value not in envmaps.entries() and not os.path.isabs(value)
        if relative:
            value = os.path.join(os.path.dirname(os.path.abspath(path)), value)
        try:
            defines["envmap"] = envmaps.resolve(value, envmap_policy)[0]
        except envmaps.EnvmapError as err:
            if relative and "not found" in str(err):
                raise envmaps.EnvmapError(
                    f"{err} (a relative path is taken from the scene's directory, "
                    f"{os.path.dirname(os.path.abspath(path))})") from None
            raise
    return {k: _xml_value(v) for k, v in defines.items()}


def load_scene(path: str | os.PathLike, envmap_policy: str = "clamp", **defines) -> mi.Scene:
    """Load a Mitsuba XML scene with ``$``-parameters ``defines`` (see
    :func:`resolve_defines` for ``envmap``). Raises :class:`SceneError` (or
    ``EnvmapError``) with a message naming the file, and the line where
    Mitsuba gives one, and what to do."""
    path = os.fspath(path)
    shown = " ".join(f"-D {k}={v}" for k, v in defines.items())
    if os.path.isdir(path):
        raise SceneError(f"cannot load scene {path}: it is a directory; give an XML file")
    if not os.path.isfile(path):
        raise SceneError(f"scene file not found: {path}")
    try:
        scene = load_resolved(path, resolve_defines(path, envmap_policy, **defines))
    except envmaps.EnvmapError:
        raise
    except UnicodeDecodeError:
        raise SceneError(f"cannot load scene {path}: not a UTF-8 text (XML) file") from None
    except Exception as err:  # Mitsuba's parser and plugins
        text = message(err)
        unused = unused_defines(text)
        if unused:
            declared = ", ".join(scenes.defaults(path)) or "none declared"
            raise SceneError(f"scene {path} has no $-parameter {', '.join(unused)} (given "
                             f"with -D); its parameters: {declared}") from None
        hint = f" (check the values of {shown})" if shown else ""
        if "Parsing of XML file" in text:
            hint = ": fix the XML at that line"
        raise SceneError(f"cannot load scene {path}: {text}{hint}") from None
    for sensor in scene.sensors():
        w, h = (int(x) for x in sensor.film().crop_size())
        if w < 1 or h < 1:
            raise SceneError(f"scene {path} has a {w}x{h} film: nothing to render; give it "
                             f"a positive size" + (f" (got {shown})" if shown else ""))
    return scene


def load_resolved(path: str | os.PathLike, resolved: dict,
                  film: tuple[int, int] | None = None) -> mi.Scene:
    """Load a scene with ``$``-parameters already passed through
    :func:`resolve_defines` (so the envmap is not read and checked again);
    with ``film`` = (width, height), at that film size (a user's scene at the
    reduced film of the statistics: plan/scene_files.py). Loaded on this
    thread: a Python plugin that logs on a loader thread deadlocks a Python log."""
    path = os.fspath(path)
    if film is None:
        return mi.load_file(path, parallel=False, **resolved)
    text, folders = scene_files.with_film(path, film, resolved)
    # (a $-parameter that set the film size is used no more: Mitsuba refuses it)
    used = {k: v for k, v in resolved.items() if re.search(rf"\${k}\b", text)}
    with _resolving(folders):
        return mi.load_string(text, parallel=False, **used)


def environment_texels(scene: mi.Scene) -> np.ndarray | None:
    """The texels (H, W, C) of the scene's environment map as Mitsuba holds
    them (an ``envmap`` emitter's ``data``), or None where it has none."""
    emitter = scene.environment()
    params = mi.traverse(emitter) if emitter is not None else {}
    return np.array(params["data"]) if "data" in params else None


@contextmanager
def _resolving(folders):
    """Mitsuba's file resolver looks in ``folders`` first, then where it
    looked before (restored on exit): a scene loaded from a string finds its
    relative files as if loaded from its own file."""
    resolver = mi.file_resolver()
    before = [resolver[i] for i in range(len(resolver))]
    for folder in reversed(folders):
        resolver.prepend(folder)
    try:
        yield
    finally:
        resolver.clear()
        for folder in before:
            resolver.append(folder)


def _xml_value(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


# --------------------------------- Integrators ---------------------------------

def _known() -> str:
    return (f"mcillum's integrators are {', '.join(registry.names())}; any Mitsuba "
            "integrator also works (e.g. path, volpath, direct)")


def make_integrator(name: str, params: dict | None = None) -> mi.Integrator:
    """Integrator plugin ``name`` with properties ``params``; raises
    :class:`IntegratorError` for an unknown name, a plugin that is not an
    integrator, or a property it refuses."""
    params = params or {}
    shown = " ".join(f"-p {k}={v}" for k, v in params.items())
    try:
        integrator = mi.load_dict({"type": name, **params}, parallel=False)
    except Exception as err:  # noqa: BLE001  (Mitsuba's loader raises plain errors)
        text = message(err, context=False)
        if plugin_not_found(text):
            raise IntegratorError(f"unknown integrator '{name}': {_known()}") from None
        unknown = unreferenced_properties(text)
        if unknown:
            refused = IntegratorError(
                f"integrator '{name}' has no parameter {', '.join(unknown)}: mcillum's "
                "integrators take max_depth, rr_depth, hide_emitters and "
                "allow_unreachable; Mitsuba's own are listed in its documentation "
                "(Plugin reference > Integrators)")
            refused.unknown = list(unknown)
            raise refused from None
        raise IntegratorError(f"integrator '{name}' rejected {shown or 'its defaults'}: "
                              f"{text}") from None
    if not isinstance(integrator, mi.Integrator):
        kind = next((k for c, k in ((mi.BSDF, "a BSDF"), (mi.Emitter, "an emitter"),
                                    (mi.Shape, "a shape"), (mi.Texture, "a texture"),
                                    (mi.Sensor, "a sensor")) if isinstance(integrator, c)),
                    "another kind of")
        raise IntegratorError(f"'{name}' is {kind} plugin, not an integrator: {_known()}")
    try:                     # a user's integrator: the facts its class declares
        registry.learn(name, type(integrator))
    except ValueError as err:
        raise IntegratorError(str(err)) from None
    return integrator


def make_taking(name: str, settings: dict) -> tuple[mi.Integrator, dict]:
    """(integrator ``name`` given those of ``settings`` it takes, those
    settings). A user's direct-light integrator may take no ``max_depth``:
    it is made without it, and the comparison still renders the reference
    with it (validation/run/jobs.py). Raises :class:`IntegratorError` as
    :func:`make_integrator` for anything else."""
    taken = dict(settings)
    while True:
        try:
            return make_integrator(name, taken), taken
        except IntegratorError as err:
            unknown = [k for k in getattr(err, "unknown", ()) if k in taken]
            if not unknown:
                raise
            for key in unknown:
                del taken[key]


# ----------------------------------- Render ------------------------------------

@dataclass
class Render:
    """One rendered image and how long it took."""

    image: np.ndarray  # (H, W, C) float32, linear radiance
    seconds: float     # wall time from launch to sync
    spp: int
    seed: int
    meta: dict = field(default_factory=dict)
    #: The integrator's AOVs by group ("posterior_var.R" → "posterior_var"),
    #: each (H, W, k); bayesian_hemisphere's ``posterior_var`` and
    #: ``sample_sq`` also give ``posterior_std``, each pixel's error bar.
    aovs: dict = field(default_factory=dict)
    #: CPU seconds other processes used meanwhile (run/load.py; None: unknown).
    others_seconds: float | None = None

    @property
    def first_seconds(self) -> float:
        """The time of this job's first render, compilation included: the
        render :func:`timed_render` set aside, if it did, else ``seconds``."""
        return self.meta.get("compile_seconds", self.seconds)


def split_aovs(image: np.ndarray, names, spp: int = 1) -> tuple[np.ndarray, dict]:
    """(radiance channels, AOV groups) of a developed film of ``spp``
    samples whose last ``len(names)`` channels are the integrator's AOVs
    ``names``; bayesian_hemisphere's give ``posterior_std`` (see its
    docstring)."""
    names = list(names)
    if not names:
        return image, {}
    groups: dict[str, list[int]] = {}
    first = image.shape[-1] - len(names)
    for i, name in enumerate(names):
        groups.setdefault(name.split(".")[0], []).append(first + i)
    aovs = {g: image[..., idx] for g, idx in groups.items()}
    radiance = image[..., :first]
    if "posterior_var" in aovs:
        aovs["posterior_std"] = gp_quadrature.pixel_std(
            aovs["posterior_var"], aovs.get("sample_sq"), radiance, spp)
    return radiance, aovs


def render(scene: mi.Scene, integrator: mi.Integrator, spp: int, seed: int = 0,
           replay=None, watch_load: bool = False) -> Render:
    """Render ``scene`` with ``integrator`` at ``spp`` samples/pixel and ``seed``;
    a single pass by ``replay(scene, integrator, spp, seed)`` where given
    (replays.py), else by :func:`launch`. With ``watch_load``, record the
    CPU seconds other processes used meanwhile (``others_seconds``; reading
    the counters twice a render cost 1 % of a quick profile's untimed
    renders, which do not need them)."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    # mcillum's estimators split over-long wavefronts themselves; Mitsuba's own
    # integrators fail when spp does not divide into their pass count.
    lanes = passes.plan_passes(passes.film_lanes(scene.sensors()[0].film()), spp)
    plan = [spp] if registry.is_estimator(integrator) else lanes
    # (passes beyond 2³² lanes are split in Python, by an estimator or here:
    # they are never replayed)
    one_pass = replay if replay is not None and len(lanes) == 1 else launch
    before = load.snapshot() if watch_load else None
    start = time.perf_counter()
    image = passes.render_in_passes(plan, seed, lambda s, n: one_pass(scene, integrator, n, s))
    dr.sync_thread()
    seconds = time.perf_counter() - start
    others = load.others_seconds(before, load.snapshot()) if watch_load else None
    image, aovs = split_aovs(np.array(image, dtype=np.float32), integrator.aov_names(), spp)
    return Render(image, seconds, spp, seed, {"passes": len(plan)} if len(plan) > 1 else {},
                  aovs, others)


def timed_render(scene: mi.Scene, integrator: mi.Integrator, spp: int,
                 seed: int = 0) -> Render:
    """:func:`render`, timed warm: where the render compiled a kernel (one
    in neither of Dr.Jit's caches: a kernel read from its disk cache costs
    no more than a warm one), the same render again, whose time is kept
    (its image is the same: same job, same seed). The time of a
    render that compiles is the compiler's: Mitsuba splits the sample index
    by a shift where spp is a power of two and by a division otherwise, so
    an estimator's first spp of the other kind compiles its kernel (1-7×
    the render), and guided_path compiles its training passes at each new
    spp; a correction may ask either (docs/measurements.md#2026-12-05-timed-renders-compile-are).
    ``meta["compile_seconds"]``: the time of the render set aside, if any
    (:attr:`Render.first_seconds`)."""
    first, compiled = _watched(scene, integrator, spp, seed)
    if not compiled:
        return first
    # (once: a kernel that compiles in every render is the render's cost)
    out, _ = _watched(scene, integrator, spp, seed)
    out.meta["compile_seconds"] = first.seconds
    return out


def _watched(scene, integrator, spp: int, seed: int) -> tuple[Render, bool]:
    """(:func:`render` watching the load, whether it compiled a kernel)."""
    out, kernels = launched(lambda: render(scene, integrator, spp, seed, watch_load=True))
    return out, any(not k["cache_hit"] for k in kernels)


def launched(fn) -> tuple:
    """(``fn()``, the JIT kernels it launched: Dr.Jit's kernel history
    entries, with ``cache_hit``, ``cache_disk``, ``size``, ``hash`` …). The
    history is on for this call only and left as it was."""
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.kernel_history()                          # (empty it: this call's kernels only)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        out = fn()
        return out, [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)


def launch(scene, integrator, spp: int, seed):
    """Mitsuba's render of ``scene``: one pass, as :func:`render` and a
    replay (replays.py) launch it."""
    return mi.render(scene, integrator=integrator, spp=spp, seed=seed)


def provenance(scene_path: str, name: str, integrator, params: dict, defines: dict,
               result: Render, variant: str) -> dict:
    """What an EXR written by ``mcillum render`` records in its header; a
    render with ``allow_unreachable`` says it is biased (``biased``)."""
    meta = {
        "scene": os.path.abspath(scene_path),
        "integrator": name,
        "params": " ".join(f"{k}={v}" for k, v in sorted(params.items())),
        "defines": " ".join(f"{k}={v}" for k, v in sorted(defines.items())),
        "spp": result.spp,
        "seed": result.seed,
        "variant": variant,
        "mitsuba_version": mi.__version__,
        "drjit_version": dr.__version__,
        "render_seconds": result.seconds,
    }
    missing = getattr(integrator, "unreachable", [])
    if missing:
        meta["biased"] = "; ".join(p.what for p in missing)
    return meta


def preview_path(path: str) -> str:
    """The tone-mapped PNG written beside the EXR at ``path``."""
    return os.path.splitext(path)[0] + ".png"


def save(path: str, result: Render, meta: dict, exposure: float = 0.0) -> str:
    """Write the render as EXR at ``path`` and a tone-mapped PNG beside it;
    returns the PNG's path."""
    png = preview_path(path)
    files.write_exr(path, result.image, meta,
                    {k: v for k, v in result.aovs.items()
                     if k not in ("posterior_var", "sample_sq") and v.shape[-1] in (1, 3, 4)})
    images.write_png(png, result.image, exposure)
    return png
