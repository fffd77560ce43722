"""Broken twins: deliberately wrong estimators, in one place.

A statistical test earns trust by rejecting answers known to be wrong. Each
twin below plays one bug a real estimator could have; a test parametrises over
``cases(names, kinds)`` and asserts that it rejects every twin that applies, so
a new estimator gets its twins by declaring its strategy, not by new tests.

=====================  ====================================================  ==========================
twin                   the bug                                               applies to
=====================  ====================================================  ==========================
``pdf_high``           pdf 5 % too high (``pdf_local`` × 1.05)               hemisphere pairs
``bsdf_weight_low``    BSDF-sample weight f cos/p × 0.95 (its pdf 5 % high)  direct light from BSDF hits
``emitter_weight_low`` emitter-sample weight L_e/p × 0.95                    next-event estimators
``set_weight_low``     each direction's weight of a set × 0.95               estimators of N directions
``unshifted_set``      the point set never shifted (the same N directions)   shifted point sets
``glossy_dropped``     the glossy lobe left out of every BSDF call           all (glossy scenes only)
``region_dark``        radiance × 0.7 in one block of the image              all (a local error)
``black``              renders zeros                                         all
=====================  ====================================================  ==========================

Every class binds to the *current* variant (call after ``renders.set_variant``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mcillum  # noqa: F401  (LLVM set-up before drjit; registers the plugins)
import drjit as dr
import mitsuba as mi
import numpy as np

from mcillum.integrators.core import registry
from mcillum.validation.run import renders


def plugin_class(name: str):
    """The plugin class of registered estimator ``name`` (current variant)."""
    return type(mi.load_dict({"type": name}))


def has_pdf_pair(cls) -> bool:
    """Is ``cls`` a hemisphere estimator (its own ``sample_local``/``pdf_local``)?"""
    base = next(c for c in cls.__mro__ if c.__name__ == "IlluminationEstimator")
    return cls.pdf_local is not base.pdf_local


def is_direction_set(cls) -> bool:
    """Does ``cls`` trace a set of N directions per shading point?"""
    return registry.is_point_set_class(cls)


# ------------------------------- The twins ---------------------------------

def wrong_pdf_class(base: str = "cosine_hemisphere", factor: float = 1.05):
    """``base`` with its pdf scaled by ``factor`` (sampling unchanged)."""
    cls = plugin_class(base)
    pdf = cls.pdf_local

    class WrongPdf(cls):
        plugin_name = f"{base}_pdf_x{factor}"
        pdf_local = staticmethod(lambda w: factor * pdf(w))

    return WrongPdf


def bsdf_weight_class(base: str, factor: float = 0.95):
    """``base`` whose sampled direction's weight f cos/p is scaled by
    ``factor`` (as if the BSDF reported a pdf 1/factor too high to the
    weight but not to the MIS weights)."""
    cls = plugin_class(base)

    class BsdfWeight(cls):
        plugin_name = f"{base}_bsdf_weight_x{factor}"

        def sample_direction(self, scene, sampler, si, bsdf, ctx):
            wo, weight, pdf, delta, eta = super().sample_direction(scene, sampler, si, bsdf, ctx)
            return wo, weight * factor, pdf, delta, eta

    return BsdfWeight


def emitter_weight_class(base: str, factor: float = 0.95):
    """``base`` whose emitter sample's contribution f cos · L_e/p is scaled by
    ``factor`` (an emitter pdf 1/factor too high)."""
    cls = plugin_class(base)

    class EmitterWeight(cls):
        plugin_name = f"{base}_emitter_weight_x{factor}"

        def emitter_sample(self, scene, sampler, si, bsdf, ctx):
            return factor * super().emitter_sample(scene, sampler, si, bsdf, ctx)

    return EmitterWeight


def set_weight_class(base: str, factor: float = 0.95):
    """``base`` (N directions per point) with every direction's factor
    f cos/p scaled by ``factor``."""
    cls = plugin_class(base)

    class SetWeight(cls):
        plugin_name = f"{base}_set_weight_x{factor}"

        def direction(self, j, drawn, si, bsdf, ctx, active):
            wo, f, a = super().direction(j, drawn, si, bsdf, ctx, active)
            return wo, f * factor, a

    return SetWeight


def unshifted_set_class(base: str = "fibonacci_hemisphere"):
    """``base`` whose point set is never shifted: the same N directions at
    every shading point, a deterministic quadrature (biased)."""
    cls = plugin_class(base)

    class Unshifted(cls):
        plugin_name = f"{base}_unshifted"

        def shift(self, sampler, active):
            return mi.Point2f(0.0, 0.0)

    return Unshifted


def lobes_only(flags) -> mi.BSDFContext:
    """A BSDF context that enables only the lobes of ``flags``."""
    ctx = mi.BSDFContext()
    ctx.type_mask = +flags
    return ctx


def glossy_dropped_class(base: str):
    """``base`` that evaluates, samples and weights only the diffuse lobes:
    every BSDF call gets a context without glossy reflection (the bug of a
    renderer that forgets one lobe of a layered material)."""
    cls = plugin_class(base)

    class GlossyDropped(cls):
        plugin_name = f"{base}_glossy_dropped"

        def sample_direction(self, scene, sampler, si, bsdf, ctx):
            return super().sample_direction(scene, sampler, si, bsdf,
                                            lobes_only(mi.BSDFFlags.DiffuseReflection))

        def emitter_sample(self, scene, sampler, si, bsdf, ctx):
            return super().emitter_sample(scene, sampler, si, bsdf,
                                          lobes_only(mi.BSDFFlags.DiffuseReflection))

        def direction(self, j, drawn, si, bsdf, ctx, active):
            return super().direction(j, drawn, si, bsdf,
                                     lobes_only(mi.BSDFFlags.DiffuseReflection), active)

    return GlossyDropped


def _pixel(scene, ray, active, width: int, height: int):
    """(x, y) film pixel of each camera ray: where the sensor sees a point on
    it (``Sensor.sample_direction`` returns film coordinates in ``uv``)."""
    it = dr.zeros(mi.Interaction3f)
    it.p = ray.o + ray.d
    ds, _ = scene.sensors()[0].sample_direction(it, mi.Point2f(0.5), active)
    return (mi.UInt32(dr.clip(dr.floor(ds.uv.x), 0, width - 1)),
            mi.UInt32(dr.clip(dr.floor(ds.uv.y), 0, height - 1)))


#: The block ``region_dark`` darkens, as fractions of the film [x0, x1) × [y0, y1).
REGION = (0.375, 0.625, 0.375, 0.625)


def region_dark_class(base: str, factor: float = 0.7, region=REGION):
    """``base`` with its radiance scaled by ``factor`` in one block of the
    image: a local error the image mean dilutes (a quarter-by-quarter block is
    1/16 of the film), which only a per-pixel test can find."""
    cls = plugin_class(base)

    class RegionDark(cls):
        plugin_name = f"{base}_region_x{factor}"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, aovs = super().sample(scene, sampler, ray, medium, active)
            w, h = scene.sensors()[0].film().crop_size()
            x, y = _pixel(scene, ray, active, int(w), int(h))
            inside = ((x >= int(region[0] * w)) & (x < int(region[1] * w)) &
                      (y >= int(region[2] * h)) & (y < int(region[3] * h)))
            return dr.select(inside, factor * L, L), valid, aovs

    return RegionDark


def region_mask(height: int, width: int, region=REGION) -> np.ndarray:
    """(H, W) True in the block :func:`region_dark_class` darkens."""
    mask = np.zeros((height, width), bool)
    mask[int(region[2] * height):int(region[3] * height),
         int(region[0] * width):int(region[1] * width)] = True
    return mask


def black_class(base: str):
    """``base`` replaced by a stub that renders zeros (valid everywhere)."""
    cls = plugin_class(base)

    class Black(cls):
        plugin_name = f"{base}_black"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return mi.Spectrum(0), mi.Bool(active), [mi.Float(0)] * len(self.aov_names())

    return Black


def clamped_class(reference: np.ndarray, base: str = "cosine_hemisphere",
                  factor: float = 10.0):
    """``base`` with every sample's radiance clamped per channel at
    ``factor`` × the ``reference`` (H, W, 3) at its pixel (the firefly clamp
    renderers offer, and users forget is a bias)."""
    cls = plugin_class(base)
    h, w = reference.shape[:2]
    limit = (factor * np.asarray(reference[..., :3], np.float32)).reshape(-1)

    class Clamped(cls):
        plugin_name = f"{base}_clamped_{factor:g}x"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, aovs = super().sample(scene, sampler, ray, medium, active)
            x, y = _pixel(scene, ray, active, w, h)
            i = 3 * (y * w + x)
            cap = mi.Color3f(*(dr.gather(mi.Float, mi.Float(limit), i + c) for c in range(3)))
            return dr.minimum(L, cap), valid, aovs

    return Clamped


def radiance_clamp_class(limit: float, base: str = "cosine_hemisphere"):
    """``base`` with every sample's radiance clamped per channel at ``limit``
    (a renderer's fixed firefly clamp): above the firefly threshold it
    leaves fireflies, and it darkens wherever the sun is hit."""
    cls = plugin_class(base)

    class RadianceClamp(cls):
        plugin_name = f"{base}_clamp_{limit:g}"

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, aovs = super().sample(scene, sampler, ray, medium, active)
            return dr.minimum(L, mi.Color3f(limit)), valid, aovs

    return RadianceClamp


def path_at_depth_class(depth: int = 2):
    """A biased reference: Mitsuba's ``path`` at ``max_depth`` ``depth``
    whatever the validation asks for (it reads and ignores the max_depth it is
    given)."""

    class PathAtDepth(mi.SamplingIntegrator):
        plugin_name = f"path_max_depth_{depth}"
        display_name, colour, listing_order = plugin_name, None, 400
        reachable = frozenset({"delta_emitter", "delta_bsdf", "transmission"})   # path's
        max_direction_pdf = None

        def __init__(self, props):
            super().__init__(props)
            props.get("max_depth", -1)         # (the validation's: ignored on purpose)
            self.inner = mi.load_dict({"type": "path", "max_depth": depth})

        def sample(self, scene, sampler, ray, medium=None, active=True):
            return self.inner.sample(scene, sampler, ray, medium, active)

    return PathAtDepth


# ------------------------------- Registry ----------------------------------

@dataclass(frozen=True)
class Twin:
    name: str
    bug: str
    applies: Callable[[type], bool]
    make: Callable[[str], type]


def _direct_from_bsdf_hits(cls) -> bool:
    # the BSDF-sampled direction carries direct light unless NEE alone does
    return (not has_pdf_pair(cls) and not is_direction_set(cls)
            and (not cls.use_nee or cls.use_mis))


TWINS = {t.name: t for t in (
    Twin("pdf_high", "pdf 5 % too high", has_pdf_pair, wrong_pdf_class),
    Twin("bsdf_weight_low", "BSDF-sample weight 5 % low", _direct_from_bsdf_hits,
         bsdf_weight_class),
    Twin("emitter_weight_low", "emitter-sample weight 5 % low", lambda c: bool(c.use_nee),
         emitter_weight_class),
    Twin("set_weight_low", "set-direction weight 5 % low", is_direction_set,
         set_weight_class),
    Twin("unshifted_set", "point set not shifted", lambda c: hasattr(c, "shift"),
         unshifted_set_class),
    Twin("glossy_dropped", "glossy lobe left out", lambda c: True, glossy_dropped_class),
    Twin("region_dark", "30 % dark in one block of the image", lambda c: True,
         region_dark_class),
    Twin("black", "renders zeros", lambda c: True, black_class),
)}

#: The twins that play a global error in how one sample is weighted.
WEIGHT_TWINS = ("pdf_high", "bsdf_weight_low", "emitter_weight_low", "set_weight_low")


def cases(names, kinds=WEIGHT_TWINS) -> list[tuple[str, str]]:
    """(estimator, twin) for every twin of ``kinds`` that applies to each of
    ``names``; every estimator has at least one."""
    out = [(n, k) for n in names for k in kinds if TWINS[k].applies(plugin_class(n))]
    missing = set(names) - {n for n, _ in out}
    assert not missing, f"no broken twin of kinds {kinds} applies to {sorted(missing)}"
    return out


def integrator(kind: str, base: str, params: dict | None = None, **options) -> mi.Integrator:
    """An instance of twin ``kind`` of estimator ``base`` with properties
    ``params`` (registered with Mitsuba as '<base>__<kind>' in this variant);
    ``options`` go to the twin's class factory (e.g. ``factor``)."""
    cls = TWINS[kind].make(base, **options)
    name = f"{base}__{kind}"
    mi.register_integrator(name, lambda props, cls=cls: cls(props))
    return renders.make_integrator(name, params)
