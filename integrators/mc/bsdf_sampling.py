"""BSDF sampling: directions from the BSDF's own ``sample`` (p ∝ its lobes)."""

from __future__ import annotations

import mitsuba as mi

from ..core import registry
from ..core.estimator import IlluminationEstimator

# ----------------------------- Strategy ---------------------------------


def sample_bsdf_direction(bsdf, ctx, si, u1, u2):
    """(ω local, weight f cos/p, p, delta?, η) drawn by the BSDF itself."""
    bs, weight = bsdf.sample(ctx, si, u1, u2)
    return bs.wo, weight, bs.pdf, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), bs.eta


def bsdf_direction_pdf(bsdf, ctx, si, wo):
    """Solid-angle density of :func:`sample_bsdf_direction` (0 for delta lobes).
    (Mitsuba's BSDFs have no inverse of ``sample``.)"""
    return bsdf.pdf(ctx, si, wo)


# ------------------------------ Plugin ----------------------------------


class BSDFSamplingIntegrator(IlluminationEstimator):
    r"""
    .. _integrator-bsdf_sampling:

    BSDF-sampling estimator (:monosp:`bsdf_sampling`)
    -------------------------------------------------

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

    At every vertex draws ω from the BSDF's own sampling routine, so the weight
    f cos/p is near-constant for every lobe it samples well — including delta
    lobes (mirrors, glass) and transmission, which the hemisphere estimators
    refuse. Radiance is gathered only where a path hits an area emitter or the
    environment: no emitter sampling, so small bright lights stay noisy and
    delta lights (point, spot, directional) are unreachable (refused).

    .. tabs::

        .. code-tab:: xml

            <integrator type="bsdf_sampling">
                <integer name="max_depth" value="8"/>
            </integrator>
    """

    plugin_name = "bsdf_sampling"
    display_name = "BSDF sampling"
    colour = "#2ca02c"
    reachable = frozenset({"delta_bsdf", "transmission"})
    max_direction_pdf = None                   # as large as the narrowest lobe makes it
    listing_order = 30
    freezable = True                           # (the validation replays its launches)

    def sample_direction(self, scene, sampler, si, bsdf, ctx):
        return sample_bsdf_direction(bsdf, ctx, si, sampler.next_1d(), sampler.next_2d())


registry.register(BSDFSamplingIntegrator)
