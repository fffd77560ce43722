"""Bayesian cubature of direct illumination on an importance-sampled lattice:
N directions per shading point, drawn from randomly shifted rank-1 lattices
through the environment map's and the BSDF's own sampling, and weighted as
Bayesian cubature with a shift-invariant kernel weights a lattice (equally)."""

from __future__ import annotations

import functools
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..core import registry
from ..core.direction_set import DirectionSetEstimator, frac
from ..core.estimator import over_pdf

# ----------------------------- Strategy ---------------------------------
# The integral is taken in the unit square of each strategy's own sampling
# (the "primary sample space"): with ω = T(u) and density p,
#
#     ∫ f_r L_i cos θ dω = ∫_[0,1)² h(u) du,   h(u) = f_r L_i cos θ / p̄ at T(u),
#
# and p̄ the mixture density of both sets (balance heuristic). Where T is
# the light's sampling, a sun is mapped onto a share of the square equal to
# its share of the map's power: it is sampled, not waited for.
#
# On the square the prior is a Gaussian process with a shift-invariant
# kernel k(u, v) = K(frac(u − v)) and a constant mean fitted with the data.
# On a rank-1 lattice the Gram matrix is then circulant (the lattice is a
# group under addition mod 1), the kernel mean ∫k(u, v)dv is the same at
# every node, and the Bayesian weights are exactly 1/n: the posterior mean is
# the lattice average (Jagadeeswaran & Hickernell, "Fast automatic Bayesian
# cubature using lattice sampling", Stat. Comput. 2019). One random shift
# per shading point keeps every node uniform on the square, so the estimate
# is unbiased for any kernel, while the lattice keeps its spacing.


@functools.lru_cache(maxsize=64)
def lattice_generator(n: int) -> int:
    """The g of the n-point rank-1 lattice {(j/n, frac(j g/n))} whose
    nearest two points lie furthest apart on the torus (g coprime to n; for
    n = 13, 34, 89 the Fibonacci lattice's, for 55 and 144 a wider one).
    1 for n < 3."""
    if n < 3:
        return 1
    j = np.arange(1, n)
    x = np.minimum(j, n - j) / n
    best, best_gap = 1, -1.0
    for g in range(1, n // 2 + 1):                 # (g and n − g mirror each other)
        if math.gcd(g, n) != 1:
            continue
        y = (j * g) % n
        gap = float(np.min(np.square(x) + np.square(np.minimum(y, n - y) / n)))
        if gap > best_gap * (1 + 1e-12):
            best, best_gap = g, gap
    return best


#: The largest n whose j·g (both < n) fits in 32 bits.
MAX_DIRECTIONS = 65535


def lattice_point(j, n, g, shift: mi.Point2f) -> mi.Point2f:
    """Node j of the n-point lattice with generator g, shifted (Cranley–
    Patterson) by ``shift`` ~ U[0,1)²: u_j = frac((j, j g mod n)/n + ξ)."""
    jg = (mi.UInt32(j) * mi.UInt32(g)) % mi.UInt32(n) if dr.is_jit_v(mi.Float) \
        else (int(j) * int(g)) % int(n)
    return mi.Point2f(frac(mi.Float(j) / mi.Float(n) + shift.x),
                      frac(mi.Float(jg) / mi.Float(n) + shift.y))


def mixture_pdf(n_light, p_light, n_bsdf, p_bsdf):
    """Σ_s n_s p_s(ω): the density of the whole set at ω, the balance
    heuristic's divisor (each node then weighs f_r L_i cos θ / this)."""
    return n_light * p_light + n_bsdf * p_bsdf


def split(n: int, light_fraction: float, has_light: bool) -> tuple[int, int]:
    """(N_light, N_bsdf): the light's share of N, at least one of each for a
    share strictly between 0 and 1; all N to the BSDF without an environment
    map."""
    if not has_light:
        return 0, n
    n_light = int(round(light_fraction * n))
    if 0.0 < light_fraction < 1.0 and n >= 2:
        n_light = min(max(n_light, 1), n - 1)
    return n_light, n - n_light


# ------------------------------ Plugin ----------------------------------


class BayesianImportanceIntegrator(DirectionSetEstimator):
    r"""
    .. _integrator-bayesian_importance:

    Bayesian cubature on an importance-sampled lattice (:monosp:`bayesian_importance`)
    ---------------------------------------------------------------------------------

    .. pluginparameters::

     * - directions
       - |int|
       - N, directions per shading point. (Default: 64)
     * - light_fraction
       - |float|
       - Share of N drawn by the environment map's importance sampling; the
         rest is drawn by the BSDF's own sampling (all of N where the scene
         has no environment map). (Default: 0.5)
     * - max_depth
       - |int|
       - 2: direct illumination; 1: only emitters seen directly; others are
         refused. (Default: 2)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)
     * - allow_unreachable
       - |bool|
       - Render content this strategy cannot reach (delta lights and lobes)
         instead of refusing the scene; the image is then biased and a
         warning says so. (Default: |false|)

    At the first surface a camera ray hits, traces two sets of directions:
    N_l drawn by the environment map's ``sample_direction`` (its luminance:
    a sun gets its share of the power, not of the solid angle) and N_b by
    the BSDF's ``sample`` (its lobe), each from an n-point rank-1 lattice of
    the unit square, u_j = frac((j, j g mod n)/n + ξ), with its own random
    shift ξ per shading point. Every direction found is weighted by the
    balance heuristic over both sets,

        L_r ≈ Σ_j f_r(ω_j) cos θ_j L_i(ω_j) / (N_l p_l(ω_j) + N_b p_b(ω_j)),

    which is what Bayesian cubature with a shift-invariant kernel on each
    lattice gives (equal weights; see the module's notes). The random shift
    makes every direction distributed exactly by its strategy's pdf: the
    estimate is unbiased, with the lattice's even spacing on each square.
    Area lights are found by the BSDF's set.

    .. tabs::

        .. code-tab:: xml

            <integrator type="bayesian_importance">
                <integer name="directions" value="16"/>
            </integrator>
    """

    plugin_name = "bayesian_importance"
    display_name = "Bayesian cubature, importance-sampled lattice"
    colour = "#393b79"
    max_direction_pdf = None                   # the light's set finds a sun
    listing_order = 75
    freezable = True                           # (the validation replays its launches)
    equal_rays_baseline = "emitter_sampling"   # (both sample the light)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        share = props.get("light_fraction", 0.5)
        if isinstance(share, bool) or not isinstance(share, (int, float)) \
                or not 0.0 <= share <= 1.0:
            raise ValueError(f"{self.plugin_name}: light_fraction must be a number in [0, 1] "
                             f"(<float name=\"light_fraction\" value=\"0.5\"/>), got {share!r}")
        self.light_fraction = float(share)
        if self.directions > MAX_DIRECTIONS:
            raise ValueError(f"{self.plugin_name}: directions = {self.directions} is more than "
                             f"{MAX_DIRECTIONS}, the largest lattice whose j·g fits 32 bits; "
                             "use fewer directions and more samples per pixel")
        self._use_split(True)

    def _use_split(self, has_light: bool) -> None:
        self.n_light, self.n_bsdf = split(self.directions, self.light_fraction, has_light)
        self.g_light = lattice_generator(max(self.n_light, 1))
        self.g_bsdf = lattice_generator(max(self.n_bsdf, 1))

    def check_scene(self, scene) -> None:
        super().check_scene(scene)
        self._use_split(scene.environment() is not None)
        if self.n_bsdf == 0 and any(not mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)
                                    for e in scene.emitters()):
            raise ValueError(
                f"{self.plugin_name}: light_fraction = 1 draws every direction from the "
                "environment map, but the scene has other emitters (area lights), which "
                "only the BSDF's set finds; use a light_fraction below 1 (default 0.5)")

    # ----------------------------- The set -------------------------------

    def draw_set(self, sampler, si, bsdf, ctx, active):
        # one shift per lattice, and one for the BSDF's lobe choice
        return self.shift(sampler, active), self.shift(sampler, active), \
            sampler.next_1d(active)

    def shift(self, sampler, active) -> mi.Point2f:
        """One Cranley–Patterson shift ξ ~ U[0,1)² of a lattice."""
        return sampler.next_2d(active)

    def direction(self, j, drawn, si, bsdf, ctx, active):
        shift_l, shift_b, shift_lobe = drawn
        n_l, n_b = self.n_light, self.n_bsdf
        in_l = j < n_l
        index = dr.select(in_l, j, j - n_l)
        size = dr.select(in_l, max(n_l, 1), max(n_b, 1))
        u = lattice_point(index, size, dr.select(in_l, self.g_light, self.g_bsdf),
                          dr.select(in_l, shift_l, shift_b))

        # --------------- The light's set: the map's own sampling ----------
        env = self.environment
        wo_l, ok_l = mi.Vector3f(0, 0, 1), mi.Bool(False)
        if env is not None:
            ds, _ = env.sample_direction(si, u, active & in_l)
            wo_l, ok_l = si.to_local(ds.d), ds.pdf > 0

        # --------------- The BSDF's set: its own sampling -----------------
        lobe = frac(shift_lobe + (mi.Float(index) + 0.5) / mi.Float(size))
        bs, _ = bsdf.sample(ctx, si, lobe, u, active & (j >= n_l))
        # (a failed sample adds 0; it is traced along the normal, since an
        # inactive lane's direction may be anything, NaN included)
        drawn_ok = dr.select(in_l, ok_l, bs.pdf > 0)
        wo = dr.select(drawn_ok, dr.select(in_l, wo_l, bs.wo), mi.Vector3f(0, 0, 1))

        # --------------- Balance heuristic over both sets ------------------
        p_l = mi.Float(0)
        if env is not None:
            ds_any = mi.DirectionSample3f()           # (the map's pdf reads only d)
            ds_any.d = si.to_world(wo)
            p_l = env.pdf_direction(si, ds_any, active)
        p_b = bsdf.pdf(ctx, si, wo, active) if n_b > 0 else mi.Float(0)
        denom = mixture_pdf(mi.Float(n_l), p_l, mi.Float(n_b), p_b)
        f_cos = bsdf.eval(ctx, si, wo, active)             # bsdf.eval includes cos θ
        factor = dr.select(drawn_ok, over_pdf(f_cos, denom), 0.0)
        return wo, factor, 1.0

    def sample(self, scene, sampler, ray, medium=None, active=True):
        # direction() reads the map from here while the kernel is traced; it is
        # let go after: an integrator that kept it would keep the scene's
        # emitter in Dr.Jit's registry, in every later kernel's virtual calls
        self.environment = scene.environment()
        try:
            return super().sample(scene, sampler, ray, medium, active)
        finally:
            self.environment = None

    def to_string(self) -> str:
        return (f"BayesianImportanceIntegrator[directions={self.directions}, "
                f"light_fraction={self.light_fraction:g} ({self.n_light} + {self.n_bsdf}), "
                f"max_depth={self.max_depth}]")


registry.register(BayesianImportanceIntegrator)
