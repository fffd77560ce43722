"""Emitter sampling: direct light from one emitter sample per vertex."""

from __future__ import annotations

from ..core import registry
from .bsdf_sampling import BSDFSamplingIntegrator

# ----------------------------- Strategy ---------------------------------


def sample_emitter_direction(scene, si, u, active=True):
    """(DirectionSample, L_e/p) towards a scene emitter (importance-sampled
    envmap, area lights by area, delta lights exactly), visibility tested."""
    return scene.sample_emitter_direction(si, u, True, active)


def emitter_direction_pdf(scene, ref, ds, active=True):
    """Solid-angle density of :func:`sample_emitter_direction` for ``ds``
    seen from ``ref`` (0 for delta lights)."""
    return scene.pdf_emitter_direction(ref, ds, active)


# ------------------------------ Plugin ----------------------------------


class EmitterSamplingIntegrator(BSDFSamplingIntegrator):
    r"""
    .. _integrator-emitter_sampling:

    Emitter-sampling estimator (:monosp:`emitter_sampling`)
    -------------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: unbounded; 1: emitters seen directly; 2: direct
         illumination). (Default: -1)
     * - rr_depth
       - |int|
       - Depth at which Russian roulette starts, as in ``path``. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content this strategy cannot reach instead of refusing the
         scene; the image is then biased and a warning says so. (Default: |false|)

    Direct light comes *only* from emitter samples: at every vertex with a
    smooth BSDF one direction is drawn from the scene's emitters
    (``scene.sample_emitter_direction``: the importance-sampled envmap, area
    lights, and point/spot/directional lights exactly) and weighted by
    f cos · L_e / p_e after a shadow ray. The path continues by BSDF sampling
    for indirect light; emitters it hits count only where an emitter sample
    could not have found them (seen directly, or after a delta bounce).

    What it cannot reach: light that arrives *through* a non-delta transmissive
    surface (rough glass, ``mask``): the shadow ray is blocked and the
    continuation's hit is not counted, so such scenes are refused (use
    ``mis``). Glossy surfaces lit by large lights or an envmap stay noisy:
    the emitter pdf ignores the BSDF lobe.

    .. tabs::

        .. code-tab:: xml

            <integrator type="emitter_sampling"/>
    """

    plugin_name = "emitter_sampling"
    display_name = "emitter sampling (next-event estimation)"
    colour = "#9467bd"
    reachable = frozenset({"delta_bsdf", "delta_emitter"})
    max_direction_pdf = None                   # emitter samples find any source
    listing_order = 40
    freezable = True                           # (the validation replays its launches)
    use_nee = True
    sample_emitter = staticmethod(sample_emitter_direction)
    emitter_pdf = staticmethod(emitter_direction_pdf)


registry.register(EmitterSamplingIntegrator)
