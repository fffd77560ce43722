"""The energy-normalised modified Phong BSDF (Lafortune & Willems 1994).

    f_r(ω_i, ω_o) = k_d / π + k_s (n + 2) / (2π) · cosⁿ α,

α the angle between ω_o and the mirror direction of ω_i. With k_d + k_s ≤ 1
per channel the albedo never exceeds 1: the specular lobe's (n + 2)/(2π)
normalises ∫ cosⁿα cos θ_o dω_o ≤ 2π/(n + 2) (equality at normal incidence).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

# ----------------------------- Strategy ---------------------------------


def sample_phong_lobe(u: mi.Point2f, exponent) -> mi.Vector3f:
    """Direction around +z with density (n + 1)/(2π) cosⁿ α:
    cos α = u₁^{1/(n+1)}, φ = 2π u₂."""
    cos_a = dr.power(u.x, 1.0 / (exponent + 1.0))
    sin_a = dr.safe_sqrt(1.0 - dr.square(cos_a))
    s, c = dr.sincos(dr.two_pi * u.y)
    return mi.Vector3f(c * sin_a, s * sin_a, cos_a)


def phong_lobe_pdf(v: mi.Vector3f, exponent) -> mi.Float:
    """(n + 1)/(2π) cosⁿ α for v.z = cos α > 0, else 0."""
    return dr.select(v.z > 0, (exponent + 1.0) * dr.inv_two_pi *
                     dr.power(dr.maximum(v.z, 0.0), exponent), 0.0)


def invert_phong_lobe(v: mi.Vector3f, exponent) -> mi.Point2f:
    """Inverse of :func:`sample_phong_lobe` on the upper hemisphere."""
    phi = dr.atan2(v.y, v.x)
    phi = dr.select(phi < 0, phi + dr.two_pi, phi)
    return mi.Point2f(dr.power(dr.maximum(v.z, 0.0), exponent + 1.0), phi * dr.inv_two_pi)


#: Where :func:`covering_exponent` compares a lobe with the Phong lobe of
#: its peak: the angles at which that lobe falls to e^-8 and e^-30 of its
#: peak (the kernel rule of gp_quadrature spans to e^-32).
COVER_LEVELS = (8.0, 30.0)


def covering_exponent(pdf, axis: mi.Vector3f, peak):
    """The exponent n of a Phong lobe about ``axis`` whose tails are no
    lighter than those of the lobe whose density is ``pdf(ω)`` (``peak`` at
    the axis): the peak's own n₀ = 2π·peak − 1, lowered where the lobe,
    four azimuths about the axis at each angle of :data:`COVER_LEVELS`, falls
    slower than cos^{n₀}: n = ln(pdf(ω)/peak) / ln cos α there. Exact (n₀)
    for a Phong lobe; a GGX lobe's power-law tails make it wider, so that
    f/p_n stays bounded where the lobe's mass is."""
    n0 = dr.maximum(dr.two_pi * peak - 1.0, 1.0)
    frame, n, log_peak = mi.Frame3f(axis), n0, dr.log(dr.maximum(peak, 1e-30))
    for level in COVER_LEVELS:
        cos_a = dr.exp(-level / n0)
        sin_a = dr.safe_sqrt(1.0 - dr.square(cos_a))
        for c, s in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
            p = pdf(frame.to_world(mi.Vector3f(c * sin_a, s * sin_a, cos_a)))
            # (a zero density there, below the surface, says nothing of the tail)
            fit = (dr.log(dr.maximum(p, 1e-30)) - log_peak) / dr.log(cos_a)
            n = dr.select((p > 0) & (fit < n), fit, n)
    return dr.maximum(n, 1.0)


def _cosine_sample(u: mi.Point2f) -> mi.Vector3f:
    return mi.warp.square_to_cosine_hemisphere(u)


# ------------------------------ Plugin ----------------------------------


class PhongBSDF(mi.BSDF):
    r"""
    .. _bsdf-phong:

    Modified Phong (:monosp:`phong`)
    --------------------------------

    .. pluginparameters::

     * - diffuse_reflectance
       - |spectrum| or |texture|
       - k_d, the diffuse albedo. (Default: 0.5)
     * - specular_reflectance
       - |spectrum| or |texture|
       - k_s, the specular albedo at normal incidence. (Default: 0.2)
     * - exponent
       - |float|
       - n > 0, the lobe's sharpness. (Default: 30)

    One-sided (black when seen from below, like ``diffuse``). Sampling picks
    the diffuse lobe (cosine-weighted) or the specular lobe (cosⁿ around the
    mirror direction) in proportion to the mean of k_d and k_s; ``pdf`` is the
    mixture. Constant reflectances with k_d + k_s > 1 in some channel are
    refused (they would create energy).

    .. tabs::

        .. code-tab:: xml

            <bsdf type="phong">
                <rgb name="diffuse_reflectance" value="0.3, 0.2, 0.1"/>
                <float name="specular_reflectance" value="0.4"/>
                <float name="exponent" value="100"/>
            </bsdf>
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.kd = props.get_texture("diffuse_reflectance", 0.5)
        self.ks = props.get_texture("specular_reflectance", 0.2)
        exponent = props.get("exponent", 30.0)
        if isinstance(exponent, bool) or not isinstance(exponent, (int, float)) or exponent <= 0:
            raise ValueError(f"phong: exponent must be a number > 0, got {exponent!r}")
        self.exponent = mi.Float(float(exponent))
        self._check_energy()
        diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [diffuse, glossy]
        self.m_flags = diffuse | glossy

    def _check_energy(self):
        """k_d + k_s ≤ 1 per channel, for reflectances that are constant."""
        import numpy as np

        def constant(tex):
            params = mi.traverse(tex)
            keys = [k for k in params.keys() if k.split(".")[-1] == "value"]
            return np.asarray(params[keys[0]], float).ravel() if len(keys) == 1 else None

        kd, ks = constant(self.kd), constant(self.ks)
        if kd is None or ks is None:
            return  # textured: checked per texel by nobody; documented
        total = np.broadcast_to(kd, (max(kd.size, ks.size),)) + ks
        if np.any(total > 1 + 1e-6):
            raise ValueError(
                f"phong: diffuse_reflectance + specular_reflectance = {total.round(4).tolist()} "
                "exceeds 1, which creates energy; lower either so that their sum is <= 1 "
                "in every channel")

    # ------------------------------------------------------------------

    def _weights(self, si, active):
        kd, ks = self.kd.eval(si, active), self.ks.eval(si, active)
        md, ms = dr.mean(mi.unpolarized_spectrum(kd)), dr.mean(mi.unpolarized_spectrum(ks))
        p_spec = dr.select(md + ms > 0, ms / (md + ms), 0.0)
        return kd, ks, p_spec

    def _enabled(self, ctx):
        return (ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0),
                ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1))

    def eval(self, ctx, si, wo, active=True):
        use_d, use_s = self._enabled(ctx)
        kd, ks, _ = self._weights(si, active)
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        valid = active & (cos_i > 0) & (cos_o > 0)
        r = mi.reflect(si.wi)                                   # mirror of ω_i
        cos_a = dr.maximum(dr.dot(r, wo), 0.0)
        f = mi.Spectrum(0.0)
        if use_d:
            f += kd * dr.inv_pi
        if use_s:
            f += ks * (self.exponent + 2.0) * dr.inv_two_pi * dr.power(cos_a, self.exponent)
        return dr.select(valid, f * cos_o, 0.0)                 # eval includes cos θ_o

    def _p_specular(self, ctx, si, active):
        """Probability of sampling the specular lobe (1 or 0 if the context
        enables only one lobe)."""
        use_d, use_s = self._enabled(ctx)
        _, _, p_spec = self._weights(si, active)
        if not use_d:
            p_spec = mi.Float(1.0)
        if not use_s:
            p_spec = mi.Float(0.0)
        return p_spec

    def pdf(self, ctx, si, wo, active=True):
        p_spec = self._p_specular(ctx, si, active)
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        valid = active & (cos_i > 0) & (cos_o > 0)
        local = mi.Frame3f(mi.reflect(si.wi)).to_local(wo)      # lobe frame
        p = (1.0 - p_spec) * cos_o * dr.inv_pi + p_spec * phong_lobe_pdf(local, self.exponent)
        return dr.select(valid, p, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        p_spec = self._p_specular(ctx, si, active)
        pick_spec = sample1 < p_spec
        wo_d = _cosine_sample(sample2)
        wo_s = mi.Frame3f(mi.reflect(si.wi)).to_world(sample_phong_lobe(sample2, self.exponent))
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(pick_spec, wo_s, wo_d)
        bs.eta = 1.0
        bs.sampled_component = dr.select(pick_spec, mi.UInt32(1), mi.UInt32(0))
        bs.sampled_type = dr.select(pick_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        value, bs.pdf = self.eval_pdf(ctx, si, bs.wo, active)
        ok = active & (bs.pdf > 0) & (mi.Frame3f.cos_theta(si.wi) > 0)
        bs.pdf = dr.select(ok, bs.pdf, 0.0)
        return bs, dr.select(ok, value / dr.maximum(bs.pdf, 1e-30), 0.0)

    def traverse(self, cb):
        cb.put("diffuse_reflectance", self.kd, mi.ParamFlags.Differentiable)
        cb.put("specular_reflectance", self.ks, mi.ParamFlags.Differentiable)
        cb.put("exponent", self.exponent, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        self._check_energy()

    def to_string(self):
        return f"PhongBSDF[exponent={self.exponent}]"


mi.register_bsdf("phong", lambda props, cls=PhongBSDF: cls(props))
