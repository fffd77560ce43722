"""Cosine-weighted hemisphere sampling: p(ω) = cos θ / π on the upper hemisphere."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core import registry
from ..core.estimator import IlluminationEstimator

# ----------------------------- Strategy ---------------------------------


def sample_cosine_hemisphere(u: mi.Point2f) -> mi.Vector3f:
    """Malley's method: a uniform point (x, y) on the unit disk (concentric
    map) lifted to ω = (x, y, √(1 − x² − y²)), which has density cos θ / π."""
    return mi.warp.square_to_cosine_hemisphere(u)


def cosine_hemisphere_pdf(w: mi.Vector3f) -> mi.Float:
    """p(ω) = cos θ / π for ω.z > 0, else 0 (Mitsuba's own pdf goes negative)."""
    return dr.select(w.z > 0, w.z * dr.inv_pi, 0)


def invert_cosine_hemisphere(w: mi.Vector3f) -> mi.Point2f:
    """Inverse of :func:`sample_cosine_hemisphere` on the upper hemisphere."""
    return mi.warp.cosine_hemisphere_to_square(w)


# ------------------------------ Plugin ----------------------------------


class CosineHemisphereIntegrator(IlluminationEstimator):
    r"""
    .. _integrator-cosine_hemisphere:

    Cosine-weighted hemisphere estimator (:monosp:`cosine_hemisphere`)
    ------------------------------------------------------------------

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

    At every vertex draws ω with density p(ω) = cos θ / π, so the weight
    f_r cos θ / p = π f_r: for a Lambertian BSDF (f_r = ρ/π) it is exactly ρ and
    only the incident radiance varies. Radiance is gathered only where a path
    hits an area emitter or escapes to the environment; there is no emitter
    sampling, so small bright sources still cause fireflies.

    Refuses scenes it would render biased (delta lights, delta BSDF lobes,
    transmission) with an error naming the object.

    .. tabs::

        .. code-tab:: xml

            <integrator type="cosine_hemisphere">
                <integer name="max_depth" value="2"/>
            </integrator>
    """

    plugin_name = "cosine_hemisphere"
    display_name = "cosine-weighted hemisphere sampling"
    colour = "#1f77b4"
    max_direction_pdf = dr.inv_pi              # p(ω) = cos θ / π ≤ 1/π
    listing_order = 20
    freezable = True                           # (the validation replays its launches)
    sample_local = staticmethod(sample_cosine_hemisphere)
    pdf_local = staticmethod(cosine_hemisphere_pdf)
    invert_local = staticmethod(invert_cosine_hemisphere)


registry.register(CosineHemisphereIntegrator)
