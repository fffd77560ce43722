"""Uniform hemisphere sampling: p(ω) = 1/(2π) on the upper hemisphere."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core import registry
from ..core.estimator import IlluminationEstimator

# ----------------------------- Strategy ---------------------------------


def sample_uniform_hemisphere(u: mi.Point2f) -> mi.Vector3f:
    """Area-preserving map [0,1)² → upper hemisphere (z = cos θ uniform in (0,1])."""
    return mi.warp.square_to_uniform_hemisphere(u)


def uniform_hemisphere_pdf(w: mi.Vector3f) -> mi.Float:
    """p(ω) = 1/(2π) for ω.z > 0, else 0 (Mitsuba's own pdf does not mask)."""
    return dr.select(w.z > 0, dr.inv_two_pi, 0)


def invert_uniform_hemisphere(w: mi.Vector3f) -> mi.Point2f:
    """Inverse of :func:`sample_uniform_hemisphere` on the upper hemisphere."""
    return mi.warp.uniform_hemisphere_to_square(w)


# ------------------------------ Plugin ----------------------------------


class UniformHemisphereIntegrator(IlluminationEstimator):
    r"""
    .. _integrator-uniform_hemisphere:

    Uniform hemisphere estimator (:monosp:`uniform_hemisphere`)
    -----------------------------------------------------------

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

    At every vertex draws ω uniformly over the hemisphere, p(ω) = 1/(2π), and
    weights the path by f_r(ω, ω_o) cos θ · 2π. Radiance is gathered only where
    a path hits an area emitter or escapes to the environment; there is no
    emitter sampling. The weight ignores both the cosine and the BSDF shape, so
    variance is high for glossy BSDFs and small bright sources: this is the
    baseline every other estimator is measured against.

    Refuses scenes it would render biased (delta lights, delta BSDF lobes,
    transmission) with an error naming the object.

    .. tabs::

        .. code-tab:: xml

            <integrator type="uniform_hemisphere">
                <integer name="max_depth" value="2"/>
            </integrator>
    """

    plugin_name = "uniform_hemisphere"
    display_name = "uniform hemisphere sampling"
    colour = "#d62728"
    max_direction_pdf = dr.inv_two_pi          # p(ω) = 1/(2π) everywhere
    listing_order = 10
    freezable = True                           # (the validation replays its launches)
    sample_local = staticmethod(sample_uniform_hemisphere)
    pdf_local = staticmethod(uniform_hemisphere_pdf)
    invert_local = staticmethod(invert_uniform_hemisphere)


registry.register(UniformHemisphereIntegrator)
