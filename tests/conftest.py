"""Shared fixtures: variants, scene paths, batches of independent renders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mcillum  # noqa: F401  (LLVM set-up before drjit; registers the plugins)
import mitsuba as mi

from mcillum.validation import renders

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"

#: Variants every rendering test runs in (scalar with tiny images).
VARIANTS = ["scalar_rgb", "llvm_ad_rgb"]

#: The hemisphere estimators (the foundation issue's pair).
ESTIMATORS = ["uniform_hemisphere", "cosine_hemisphere"]

#: Every estimator of this package.
ALL_ESTIMATORS = ESTIMATORS + ["bsdf_sampling", "emitter_sampling", "mis"]


@pytest.fixture(params=VARIANTS)
def variant(request):
    """Switch Mitsuba to each test variant in turn."""
    return renders.set_variant(request.param)


@pytest.fixture
def llvm():
    return renders.set_variant("llvm_ad_rgb")


def small(variant: str, scalar: int, vectorized: int) -> int:
    """Pick a size: scalar variants run Python per sample, so keep them tiny."""
    return scalar if variant.startswith("scalar") else vectorized


def batch(scene, integrator, spp: int, k: int, first_seed: int = 0) -> np.ndarray:
    """K independent renders (seeds first_seed … first_seed+k-1), (K, H, W, C)."""
    return np.stack([renders.render(scene, integrator, spp, seed).image
                     for seed in range(first_seed, first_seed + k)])


def wrong_pdf_integrator(base: str = "cosine_hemisphere", factor: float = 1.05,
                         props: "mi.Properties | None" = None):
    """A deliberately biased estimator: ``base`` with its pdf scaled by ``factor``.

    The class is built for the current variant (plugin classes bind to it).
    """
    return wrong_pdf_class(base, factor)(props or mi.Properties())


def wrong_pdf_class(base: str = "cosine_hemisphere", factor: float = 1.05):
    """The class of :func:`wrong_pdf_integrator` (for mi.register_integrator)."""
    import importlib

    module = importlib.import_module(f"mcillum.integrators.{base}")
    cls = next(c for c in vars(module).values()
               if isinstance(c, type) and getattr(c, "plugin_name", None) == base)
    pdf = cls.pdf_local

    class WrongPdf(cls):
        plugin_name = f"{base}_pdf_x{factor}"
        pdf_local = staticmethod(lambda w: factor * pdf(w))

    return WrongPdf
