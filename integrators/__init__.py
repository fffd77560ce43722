"""mcillum integrators: Monte Carlo estimators of the illumination integral as
Mitsuba 3 plugins, one per file.

Importing this package (``import mcillum`` does) does three things, in order:

1. points Dr.Jit at the libLLVM of the pinned ``karellen-llvm-core`` wheel
   (unless ``DRJIT_LIBLLVM_PATH`` is set), *before* drjit is first imported;
2. registers every plugin of this folder for the current Mitsuba variant (if
   one is set): every module except the shared ones in :data:`SHARED`, the
   base classes in :data:`BASES` first;
3. registers them again whenever ``mi.set_variant`` switches.

:func:`register` does step 2 by hand; calling it twice is harmless. The
estimators' facts are in :mod:`.registry` (``registry.names()``).
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

from . import _llvm

_llvm.configure()  # must precede the first `import drjit` in the process

import mitsuba as mi  # noqa: E402  (after the LLVM set-up on purpose)

from . import registry  # noqa: E402,F401
from .scene_checks import UnreachableContentError  # noqa: E402,F401  (variant-free)

#: Modules that hold no plugin and do not depend on the variant.
SHARED = ("_llvm", "gp_quadrature", "gp_scene", "gp_settings", "guide", "passes", "registry",
          "scene_checks")
#: Base classes the plugins derive from, (re)loaded in this order before them:
#: every estimator's, then that of the estimators of N directions per point.
BASES = ("estimator", "direction_set")

_registered_for: str | None = None


def plugin_modules() -> list[str]:
    """The plugin modules of this folder (an estimator or a BSDF each)."""
    names = sorted(m.name for m in pkgutil.iter_modules(__path__))
    return [n for n in names if n not in SHARED and n not in BASES]


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


mi.detail.add_variant_callback(_on_variant_change)

if mi.variant() is not None:
    register()
