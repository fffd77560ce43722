"""Shared fixtures: variants, scene paths, the estimators under test (read from
the registry), batches of independent renders, and broken twins."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

import mcillum  # noqa: F401  (LLVM set-up before drjit; registers the plugins)
import drjit as dr
import mitsuba as mi

from mcillum.integrators import registry
from mcillum.validation import renders

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"

#: Variants every rendering test runs in (scalar with tiny images).
VARIANTS = ["scalar_rgb", "llvm_ad_rgb"]

renders.set_variant("llvm_ad_rgb")      # the registry fills when a variant is set


def _base():
    return importlib.import_module("mcillum.integrators.estimator").IlluminationEstimator


def plugin_class(name: str):
    """The plugin class of registered estimator ``name`` (current variant)."""
    return type(mi.load_dict({"type": name}))


def estimators() -> list[str]:
    """Every registered mcillum estimator (registry order)."""
    return registry.names()


def hemisphere_estimators() -> list[str]:
    """Estimators defined by a pure direction pair ``sample_local`` /
    ``pdf_local`` on the hemisphere (they get a wrong-pdf twin)."""
    return [n for n in estimators() if plugin_class(n).pdf_local is not _base().pdf_local]


#: Fixed at collection time (parametrize needs lists).
ALL_ESTIMATORS = estimators()
HEMISPHERE = hemisphere_estimators()


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


def tiny_scene(**items):
    """A 2x2 camera looking down at whatever ``items`` add."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=[0, 3, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 2, "height": 2,
                            "rfilter": {"type": "box"}}},
        **items,
    })


def disk(bsdf):
    return {"type": "disk", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),
            "bsdf": bsdf}


def render(scene, name, **params):
    """One 2-spp render of ``scene`` with integrator ``name``."""
    return renders.render(scene, renders.make_integrator(name, params), spp=2)


def batch(scene, integrator, spp: int, k: int, first_seed: int = 0) -> np.ndarray:
    """K independent renders (seeds first_seed … first_seed+k-1), (K, H, W, C)."""
    return np.stack([renders.render(scene, integrator, spp, seed).image
                     for seed in range(first_seed, first_seed + k)])


def wrong_pdf_class(base: str = "cosine_hemisphere", factor: float = 1.05):
    """A deliberately biased estimator: ``base`` with its pdf scaled by
    ``factor`` (the class binds to the current variant)."""
    cls = plugin_class(base)
    pdf = cls.pdf_local

    class WrongPdf(cls):
        plugin_name = f"{base}_pdf_x{factor}"
        pdf_local = staticmethod(lambda w: factor * pdf(w))

    return WrongPdf


def wrong_pdf_integrator(base: str = "cosine_hemisphere", factor: float = 1.05,
                         props: "mi.Properties | None" = None):
    """An instance of :func:`wrong_pdf_class`."""
    return wrong_pdf_class(base, factor)(props or mi.Properties())


def clamped_class(reference: np.ndarray, base: str = "cosine_hemisphere",
                  factor: float = 10.0):
    """A deliberately biased estimator: ``base`` with every sample's radiance
    clamped per channel at ``factor`` × the ``reference`` (H, W, 3) at its
    pixel (the firefly clamp renderers offer, and users forget is a bias).
    The pixel of a camera ray is where the sensor sees a point on it
    (``Sensor.sample_direction`` gives film coordinates)."""
    cls = plugin_class(base)
    h, w = reference.shape[:2]
    limit = (factor * np.asarray(reference[..., :3], np.float32)).reshape(-1)

    class Clamped(cls):
        plugin_name = f"{base}_clamped_{factor:g}x"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, aovs = super().sample(scene, sampler, ray, medium, active)
            it = dr.zeros(mi.Interaction3f)
            it.p = ray.o + ray.d
            ds, _ = scene.sensors()[0].sample_direction(it, mi.Point2f(0.5), active)
            x = mi.UInt32(dr.clip(dr.floor(ds.uv.x), 0, w - 1))
            y = mi.UInt32(dr.clip(dr.floor(ds.uv.y), 0, h - 1))
            i = 3 * (y * w + x)
            cap = mi.Color3f(*(dr.gather(mi.Float, mi.Float(limit), i + c) for c in range(3)))
            return dr.minimum(L, cap), valid, aovs

    return Clamped


def path_at_depth_class(depth: int = 2):
    """A deliberately biased reference: Mitsuba's ``path`` at ``max_depth``
    ``depth`` whatever the validation asks for (it reads and ignores the
    max_depth it is given)."""

    class PathAtDepth(mi.SamplingIntegrator):
        plugin_name = f"path_max_depth_{depth}"
        display_name, colour, reachable, listing_order = plugin_name, None, frozenset(), 400
        max_direction_pdf = None

        def __init__(self, props):
            super().__init__(props)
            props.get("max_depth", -1)         # (the validation's: ignored on purpose)
            self.inner = mi.load_dict({"type": "path", "max_depth": depth})

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return self.inner.sample(scene, sampler, ray, medium, active)

    return PathAtDepth
