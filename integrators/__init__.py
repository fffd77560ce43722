"""mcillum integrators: Monte Carlo estimators of the illumination integral as
Mitsuba 3 plugins.

``import integrators`` does three things, in this order:

1. points Dr.Jit at the libLLVM of the pinned ``karellen-llvm-core`` wheel
   (unless ``DRJIT_LIBLLVM_PATH`` is set), *before* drjit is first imported;
2. registers every estimator for the current Mitsuba variant (if one is set);
3. re-registers them automatically whenever ``mi.set_variant`` switches.

``integrators.register()`` does step 2 by hand; calling it twice is harmless.
Registered plugin names are listed in :data:`PLUGINS`.
"""

from __future__ import annotations

import importlib
import sys

from . import _llvm

_llvm.configure()  # must precede the first `import drjit` in the process

import mitsuba as mi  # noqa: E402  (after the LLVM set-up on purpose)

from .scene_checks import UnreachableContentError  # noqa: E402,F401  (variant-free)

#: Registered plugin name → module (inside this package) that defines it.
PLUGINS = {
    "uniform_hemisphere": "uniform_hemisphere",
    "cosine_hemisphere": "cosine_hemisphere",
    "bsdf_sampling": "bsdf_sampling",
    "emitter_sampling": "emitter_sampling",
    "mis": "mis",
    "phong": "phong",  # a BSDF, not an integrator
}

#: Modules whose classes derive from a variant's types, in reload order:
#: the shared base first, then the plugins that subclass it.
_VARIANT_MODULES = ("estimator", *dict.fromkeys(PLUGINS.values()))

_registered_for: str | None = None


def register() -> str:
    """Register every mcillum integrator for the current Mitsuba variant.

    Idempotent; needed by hand only if the automatic variant callback was
    removed (e.g. by ``mi.detail.clear_variant_callbacks()``). Returns the
    variant. Raises if no variant is set or its LLVM backend is unusable.
    """
    global _registered_for
    variant = mi.variant()
    if variant is None:
        raise RuntimeError(
            "no Mitsuba variant is set: call mi.set_variant('llvm_ad_rgb') "
            "(or 'scalar_rgb', 'cuda_ad_rgb') before integrators.register()")
    _llvm.check(variant)
    if _registered_for == variant:
        return variant
    for name in _VARIANT_MODULES:
        qualified = f"{__name__}.{name}"
        module = sys.modules.get(qualified)
        # (Re)executing a plugin module rebinds its class to this variant's
        # base types and calls mi.register_integrator at its bottom.
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
