"""Randomized spherical-Fibonacci directions: N low-discrepancy directions per
shading point, each distributed exactly by its pdf (quasi-Monte Carlo)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..core import registry
from ..core.direction_set import DirectionSetEstimator, frac
from ..core.estimator import over_pdf

#: Φ, the golden ratio; 1/Φ = Φ − 1 spreads v_j = frac(j/Φ) evenly.
GOLDEN = (1.0 + 5.0 ** 0.5) / 2.0

# ----------------------------- Strategy ---------------------------------


def fibonacci_point(j, n, shift: mi.Point2f) -> mi.Point2f:
    """Point j of the n-point spherical-Fibonacci set in the unit square,
    shifted (Cranley–Patterson) by ``shift`` ~ U[0,1)²:

        u_j = frac((j + ½)/n + ξ₁),   v_j = frac(j/Φ + ξ₂).

    The shift leaves the set's spacing intact and makes every point uniform
    on the square, so each mapped direction has exactly the mapping's pdf."""
    j = mi.Float(j)
    return mi.Point2f(frac((j + 0.5) / mi.Float(n) + shift.x),
                      frac(j * (GOLDEN - 1.0) + shift.y))


def sample_cosine_polar(u: mi.Point2f) -> mi.Vector3f:
    """Cosine-weighted map of the (u, v) square, area-preserving in polar
    coordinates: cos θ = √(1 − u), φ = 2π v (Malley's method on the disk of
    radius √u), density cos θ / π."""
    cos_t = dr.safe_sqrt(1.0 - u.x)
    sin_t = dr.safe_sqrt(u.x)
    s, c = dr.sincos(dr.two_pi * u.y)
    return mi.Vector3f(c * sin_t, s * sin_t, cos_t)


def cosine_polar_pdf(w: mi.Vector3f) -> mi.Float:
    """p(ω) = cos θ / π for ω.z > 0, else 0."""
    return dr.select(w.z > 0, w.z * dr.inv_pi, 0.0)


def invert_cosine_polar(w: mi.Vector3f) -> mi.Point2f:
    """Inverse of :func:`sample_cosine_polar`: u = 1 − cos²θ, v = φ/2π."""
    phi = dr.atan2(w.y, w.x)
    phi = dr.select(phi < 0, phi + dr.two_pi, phi)
    return mi.Point2f(1.0 - dr.square(w.z), phi * dr.inv_two_pi)


def sample_uniform_polar(u: mi.Point2f) -> mi.Vector3f:
    """Uniform map: cos θ = 1 − u, φ = 2π v, density 1/(2π)."""
    cos_t = 1.0 - u.x
    sin_t = dr.safe_sqrt(1.0 - dr.square(cos_t))
    s, c = dr.sincos(dr.two_pi * u.y)
    return mi.Vector3f(c * sin_t, s * sin_t, cos_t)


def uniform_polar_pdf(w: mi.Vector3f) -> mi.Float:
    """p(ω) = 1/(2π) for ω.z > 0, else 0."""
    return dr.select(w.z > 0, dr.inv_two_pi, 0.0)


def invert_uniform_polar(w: mi.Vector3f) -> mi.Point2f:
    """Inverse of :func:`sample_uniform_polar`."""
    phi = dr.atan2(w.y, w.x)
    phi = dr.select(phi < 0, phi + dr.two_pi, phi)
    return mi.Point2f(1.0 - w.z, phi * dr.inv_two_pi)


#: ``mapping`` → (sample, pdf, inverse) of the diffuse set.
MAPPINGS = {
    "cosine": (sample_cosine_polar, cosine_polar_pdf, invert_cosine_polar),
    "uniform": (sample_uniform_polar, uniform_polar_pdf, invert_uniform_polar),
}


def glossy_context() -> mi.BSDFContext:
    """A BSDF context that enables only glossy lobes (the second set)."""
    ctx = mi.BSDFContext()
    ctx.type_mask = +mi.BSDFFlags.Glossy
    return ctx


# ------------------------------ Plugin ----------------------------------


class FibonacciHemisphereIntegrator(DirectionSetEstimator):
    r"""
    .. _integrator-fibonacci_hemisphere:

    Randomized spherical-Fibonacci estimator (:monosp:`fibonacci_hemisphere`)
    -------------------------------------------------------------------------

    .. pluginparameters::

     * - directions
       - |int|
       - N, directions per shading point. (Default: 64)
     * - mapping
       - |string|
       - How the diffuse set maps the square to the hemisphere: ``cosine``
         (cos θ = √(1 − u)) or ``uniform`` (cos θ = 1 − u). (Default: ``cosine``)
     * - max_depth
       - |int|
       - 2: direct illumination; 1: only emitters seen directly; others are
         refused. (Default: 2)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content this strategy cannot reach instead of refusing the
         scene; the image is then biased and a warning says so. (Default: |false|)

    At the first surface a camera ray hits, traces N directions of a
    spherical-Fibonacci set, u_j = (j + ½)/N, v_j = frac(j/Φ), mapped by
    ``mapping``. One random Cranley–Patterson shift per shading point,
    (u, v) ← frac((u, v) + ξ), makes every direction distributed exactly by
    the mapping's pdf, so the estimate is unbiased while the set keeps its
    even spacing: on smooth lighting the error falls like N⁻¹ rather than
    N^-½. (A rotation about the normal alone would keep every θ_j fixed
    and bias the image.)

    BSDFs with a glossy lobe (``phong``, ``roughplastic``, ...) get two sets:
    N_a = N − ⌊N/2⌋ diffuse directions as above and N_b = ⌊N/2⌋ drawn by the
    BSDF's own sampling of its glossy lobes, fed the shifted points (for
    ``phong``: cos α = u^{1/(n+1)} about the mirror direction). Both are
    combined by the balance heuristic, which is unbiased for any pdfs that
    together cover the hemisphere:

        L_r ≈ Σ_{j ∈ a ∪ b} f_r(ω_j) cos θ_j L_i(ω_j) / (N_a p_a(ω_j) + N_b p_b(ω_j)).

    A bright source that covers little of the hemisphere (a sun, a small
    light) is found by few directions of any set: there the gain over
    ``cosine_hemisphere`` disappears.

    .. tabs::

        .. code-tab:: xml

            <integrator type="fibonacci_hemisphere">
                <integer name="directions" value="64"/>
            </integrator>
    """

    plugin_name = "fibonacci_hemisphere"
    display_name = "randomized spherical Fibonacci (QMC)"
    colour = "#17becf"
    max_direction_pdf = None                   # the glossy set follows the BSDF
    listing_order = 60
    freezable = True                           # (the validation replays its launches)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        mapping = props.get("mapping", "cosine")
        if mapping not in MAPPINGS:
            raise ValueError(f"{self.plugin_name}: mapping must be one of "
                             f"{', '.join(MAPPINGS)}, got {mapping!r}")
        self.mapping = mapping
        self.sample_local, self.pdf_local, self.invert_local = MAPPINGS[mapping]

    def draw_set(self, sampler, si, bsdf, ctx, active):
        # (ξ_a, ξ_b, ξ_c): the shifts of the diffuse and the glossy set, and
        # of the glossy set's lobe choice; N_b directions for the glossy set.
        glossy = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Glossy)
        n_b = dr.select(glossy, mi.UInt32(self.directions // 2), mi.UInt32(0))
        return self.shift(sampler, active), self.shift(sampler, active), \
            sampler.next_1d(active), n_b

    def shift(self, sampler, active) -> mi.Point2f:
        """One Cranley–Patterson shift ξ ~ U[0,1)² of the (u, v) square."""
        return sampler.next_2d(active)

    def direction(self, j, drawn, si, bsdf, ctx, active):
        shift_a, shift_b, shift_c, n_b = drawn
        n_a = self.directions - n_b
        in_a = j < n_a
        index = dr.select(in_a, j, j - n_a)
        size = dr.select(in_a, n_a, n_b)
        u = fibonacci_point(index, size, dr.select(in_a, shift_a, shift_b))

        # Diffuse set, on the side the camera ray came from
        w_up = self.sample_local(u)
        wo_a = mi.Vector3f(w_up.x, w_up.y, dr.mulsign(w_up.z, si.wi.z))
        # Glossy set: the BSDF's own glossy sampling, fed the same kind of point
        ctx_b = glossy_context()
        lobe = frac(shift_c + (mi.Float(index) + 0.5) / dr.maximum(mi.Float(size), 1.0))
        bs, _ = bsdf.sample(ctx_b, si, lobe, u, active & (j >= n_a))
        # (a failed glossy sample adds 0; it is traced along wo_a, a valid
        # direction, so that no lookup sees a zero vector)
        kept = in_a | (bs.pdf > 0)
        wo = dr.select(in_a | (bs.pdf <= 0), wo_a, bs.wo)

        # Balance heuristic over both sets: f cos / (N_a p_a + N_b p_b)
        p_a = self.pdf_local(mi.Vector3f(wo.x, wo.y, dr.mulsign(wo.z, si.wi.z)))
        p_b = dr.select(n_b > 0, bsdf.pdf(ctx_b, si, wo, active & (n_b > 0)), 0.0)
        denom = mi.Float(n_a) * p_a + mi.Float(n_b) * p_b
        f_cos = bsdf.eval(ctx, si, wo, active)             # bsdf.eval includes cos θ
        factor = dr.select(kept, over_pdf(f_cos, denom), 0.0)
        return wo, factor, 1.0

    def to_string(self) -> str:
        return (f"FibonacciHemisphereIntegrator[directions={self.directions}, "
                f"mapping={self.mapping}, max_depth={self.max_depth}]")


registry.register(FibonacciHemisphereIntegrator)
