"""Multiple importance sampling: one BSDF and one emitter sample per vertex,
combined by the power heuristic (Veach 1997), as Mitsuba's `path` does."""

from __future__ import annotations

from ..core import registry
from ..core.estimator import mis_weight  # noqa: F401  (the power heuristic, re-exported)
from .bsdf_sampling import BSDFSamplingIntegrator
from .emitter_sampling import emitter_direction_pdf, sample_emitter_direction

# ----------------------------- Strategy ---------------------------------
# Directions: the BSDF's (bsdf_sampling) and the emitters' (emitter_sampling);
# weights w_s = p_s² / (p_bsdf² + p_emitter²) per technique, delta lobes and
# delta lights weight 1.

# ------------------------------ Plugin ----------------------------------


class MISIntegrator(BSDFSamplingIntegrator):
    r"""
    .. _integrator-mis:

    MIS estimator (:monosp:`mis`)
    -----------------------------

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

    At every vertex: one emitter sample (with shadow ray) and one BSDF sample,
    each weighted by the power heuristic against the other technique's pdf;
    the BSDF sample also continues the path. This is the estimator of
    Mitsuba's ``path`` (same depth convention and Russian roulette), written
    in this package's shared loop: it should match ``path`` statistically and
    in speed. Reaches everything but participating media.

    .. tabs::

        .. code-tab:: xml

            <integrator type="mis">
                <integer name="max_depth" value="8"/>
            </integrator>
    """

    plugin_name = "mis"
    display_name = "multiple importance sampling (as path)"
    colour = "#ff7f0e"
    reachable = frozenset({"delta_bsdf", "transmission", "delta_emitter"})
    max_direction_pdf = None                   # emitter samples find any source
    listing_order = 50
    freezable = True                           # (the validation replays its launches)
    use_nee = True
    use_mis = True
    sample_emitter = staticmethod(sample_emitter_direction)
    emitter_pdf = staticmethod(emitter_direction_pdf)


registry.register(MISIntegrator)
