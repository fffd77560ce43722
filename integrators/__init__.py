"""mcillum integrators: Monte Carlo estimators of the illumination integral as
Mitsuba 3 plugins, one per file, in folders by family:

* ``mc/`` — the course's five estimators: uniform, cosine, BSDF and emitter
  sampling, MIS;
* ``quadrature/`` — N directions per shading point: the Fibonacci set, the
  Bayesian estimators and their Gaussian-process modules;
* ``guiding/`` — ``guided_path`` and the tree it learns (``guide``);
* ``bsdfs/`` — the Phong BSDF;
* ``core/`` — what they share: the two loops (``estimator``,
  ``direction_set``) and the render's entry before them (``checked_render``:
  the scene check, passes), the facts (``registry``), what a scene holds that a
  strategy cannot reach (``scene_checks``), renders beyond 2³² samples
  (``passes``).

Importing this package (``import mcillum`` does) does three things, in order:

1. points Dr.Jit at the libLLVM of the pinned ``karellen-llvm-core`` wheel
   (unless ``DRJIT_LIBLLVM_PATH`` is set), *before* drjit is first imported;
2. registers every plugin for the current Mitsuba variant (if one is set):
   every module of the folders in :data:`FAMILIES` that registers one
   (:func:`is_plugin`), after the base classes in :data:`BASES`;
3. registers them again whenever ``mi.set_variant`` switches.

:func:`register` does step 2 by hand; calling it twice is harmless. The
estimators' facts are in :mod:`.core.registry` (``registry.names()``).
The modules' paths before the folders (``mcillum.integrators.registry``, …)
import until mcillum 0.2, with a DeprecationWarning (:data:`MOVED`).

Imports point down the table below, as in validation/__init__.py's table of
the whole package, whose row ``integrators`` this table spells out: a family
imports only its own modules and those of the rows beneath it, never in a
cycle. tests/test_layout.py reads both tables.

Layers, top to bottom:

    integrators             this package: the LLVM set-up, then every family's plugins registered
    integrators.guiding     guided_path and what it learns; takes mc's sampling routines
    integrators.quadrature  N directions per point, their Gaussian processes; takes Phong's lobe
    integrators.mc          the course's five estimators
    integrators.bsdfs       the Phong BSDF
    integrators.core        the two loops, the facts, scene checks, passes
    integrators._llvm       Dr.Jit's libLLVM, chosen before drjit is imported
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import pkgutil
import re
import sys
import warnings
from pathlib import Path

# _llvm stays here, not in core/: it must run before the first `import
# drjit`. In core/ it would run after core/__init__.py, which would then have
# to stay free of every import that reaches drjit.
from . import _llvm

_llvm.configure()  # must precede the first `import drjit` in the process

import mitsuba as mi  # noqa: E402  (after the LLVM set-up on purpose)

from .core.scene_checks import UnreachableContentError  # noqa: E402,F401  (variant-free)

#: The plugin folders, in the order their modules are (re)loaded: a family's
#: modules may use an earlier family's (guiding takes mc's sampling routines).
FAMILIES = ("mc", "bsdfs", "quadrature", "guiding")
#: Base classes the plugins derive from, (re)loaded in this order before them:
#: every estimator's render entry, the estimator loop, then that of the
#: estimators of N directions per point.
BASES = ("core.checked_render", "core.estimator", "core.direction_set")

#: A line that begins with one of these calls registers a plugin at module
#: level (column 0), as every plugin file does at its bottom.
REGISTERS = re.compile(r"^(registry\.register|mi\.register_\w+)\(", re.MULTILINE)

_registered_for: str | None = None


def is_plugin(path: str | Path) -> bool:
    """Does the module at ``path`` register a plugin (:data:`REGISTERS`)?
    Raises OSError if its source cannot be read."""
    return REGISTERS.search(Path(path).read_text(encoding="utf-8")) is not None


def plugin_modules() -> list[str]:
    """The plugin modules, relative to this package (``mc.cosine_hemisphere``),
    family by family (:data:`FAMILIES`), each family's in name order (a
    class another plugin derives from must sort first: ``mc.bsdf_sampling``
    before ``mc.emitter_sampling`` and ``mc.mis``). Raises OSError if a
    family's folder or a module's source is missing (an install without them
    would register fewer plugins)."""
    out = []
    for family in FAMILIES:
        folder = Path(__path__[0], family)
        if not (folder / "__init__.py").is_file():
            raise FileNotFoundError(f"mcillum's plugin folder {folder} is missing")
        out += [f"{family}.{m.name}" for m in sorted(pkgutil.iter_modules([str(folder)]),
                                                      key=lambda m: m.name)
                if not m.ispkg and is_plugin(folder / f"{m.name}.py")]
    return out


def register() -> str:
    """Register every mcillum plugin for the current Mitsuba variant.

    Idempotent; needed by hand only if the automatic variant callback was
    removed (e.g. by ``mi.detail.clear_variant_callbacks()``). Returns the
    variant. Raises if no variant is set or its LLVM backend is unusable.
    """
    global _registered_for
    variant = mi.variant()
    if variant is None:
        raise RuntimeError(
            "no Mitsuba variant is set: call mi.set_variant('llvm_ad_rgb') "
            "(or 'scalar_rgb', 'cuda_ad_rgb') before mcillum.register()")
    _llvm.check(variant)
    if _registered_for == variant:
        return variant
    for name in (*BASES, *plugin_modules()):
        qualified = f"{__name__}.{name}"
        module = sys.modules.get(qualified)
        # (Re)executing a plugin module rebinds its class to this variant's
        # base types and registers it at its bottom.
        if module is None:
            importlib.import_module(qualified)
        else:
            importlib.reload(module)
    _registered_for = variant
    return variant


def _on_variant_change(old: str | None, new: str | None) -> None:
    if new is not None:
        register()


# ------------------------- The paths before the folders -----------------------

#: Module paths before the folders (``mcillum.integrators.<old>``) → their
#: paths now, relative to this package. Both import until mcillum 0.2; the
#: old one warns (DeprecationWarning) and gives the same module object.
MOVED = {
    "estimator": "core.estimator", "direction_set": "core.direction_set",
    "registry": "core.registry", "scene_checks": "core.scene_checks",
    "passes": "core.passes",
    "uniform_hemisphere": "mc.uniform_hemisphere", "cosine_hemisphere": "mc.cosine_hemisphere",
    "bsdf_sampling": "mc.bsdf_sampling", "emitter_sampling": "mc.emitter_sampling",
    "mis": "mc.mis",
    "fibonacci_hemisphere": "quadrature.fibonacci_hemisphere",
    "bayesian_hemisphere": "quadrature.bayesian_hemisphere",
    "bayesian_importance": "quadrature.bayesian_importance",
    "gp_quadrature": "quadrature.gp_quadrature", "gp_scene": "quadrature.gp_scene",
    "gp_settings": "quadrature.gp_settings",
    "guide": "guiding.guide", "guided_path": "guiding.guided_path",
    "phong": "bsdfs.phong",
}


def _outside_imports() -> int:
    """The stacklevel, as warnings.warn counts it from its caller, of the
    first frame outside the import machinery and this file: the line that
    imported the old path."""
    frame, level = sys._getframe(1), 1
    while frame is not None:
        name = frame.f_code.co_filename
        if name in (__file__, importlib.__file__):
            level += 1
        elif not name.startswith("<frozen importlib._bootstrap"):
            break                 # (warn() skips _bootstrap frames uncounted)
        frame = frame.f_back
    return level


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old path of :data:`MOVED` as the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, old = fullname.rpartition(".")
        if package != __name__ or old not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec):
        new = f"{__name__}.{MOVED[spec.name.rpartition('.')[2]]}"
        warnings.warn(f"{spec.name} is now {new}; the old path goes in mcillum 0.2",
                      DeprecationWarning, stacklevel=_outside_imports())
        module = importlib.import_module(new)
        # The import system stamps this spec on the module it gets;
        # exec_module gives the module its own back (reload() reads it).
        spec.loader_state = module.__spec__
        return module

    def exec_module(self, module):
        module.__spec__ = module.__spec__.loader_state


def __getattr__(name: str):
    """``mcillum.integrators.<old>`` as an attribute (``import mcillum`` then
    ``mcillum.integrators.registry``): imported through :class:`_MovedModules`,
    which warns. Raises AttributeError for any other name."""
    if name in MOVED:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# (appended: a path that exists is always found first, by the usual finders)
if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())

mi.detail.add_variant_callback(_on_variant_change)

if mi.variant() is not None:
    register()
