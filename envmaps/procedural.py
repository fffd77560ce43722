"""Deterministic procedural environment maps (float32 RGB, Mitsuba latlong).

Each generator returns an ``(height, width, 3)`` float32 array in Mitsuba's
``envmap`` convention: y up, direction (sinφ sinθ, cosθ, −cosφ sinθ). Mitsuba
3.9 interpolates bilinearly between *nodes*: column j sits at φ = 2π(j + ½)/W
(pixel centres) but row i at θ = π·i/(H − 1), so the first and last rows are
the poles (envmap.cpp, eval_spectrum). A value is the box filter of the
radiance over its node's cell, averaged from ``supersample``² directions, so
hard edges (cap, checker) keep their solid angle. The closed forms in the
docstrings hold for the continuous map; :func:`irradiance` measures how far a
discrete map is from them.
"""

from __future__ import annotations

import numpy as np

#: Default resolution of generated maps (Mitsuba envmaps are 2:1).
WIDTH, HEIGHT = 512, 256

# Parameter types of the generators (``envmaps.catalog.generate`` checks them):
# a Colour is one number or an RGB triple; a Vector three numbers; Lobes a
# sequence of (axis Vector, sharpness, amplitude Colour).
Colour = "float | tuple[float, float, float]"
Vector = "tuple[float, float, float]"
Lobes = "tuple[tuple[Vector, float, Colour], ...]"


def directions(width: int, height: int, supersample: int = 1) -> np.ndarray:
    """Unit directions (height, width, s², 3): ``s × s`` sub-pixel samples per
    pixel (s = ``supersample``), stratified; y up, Mitsuba's latlong mapping."""
    return _band(width, height, 0, height, supersample)


def bake(radiance, width: int = WIDTH, height: int = HEIGHT,
         supersample: int = 4) -> np.ndarray:
    """Box-filter ``radiance(d: (..., 3)) -> (..., 3)`` over each pixel
    (in bands of rows, so memory stays bounded at high ``supersample``)."""
    out = np.empty((height, width, 3), np.float32)
    band = max(1, 2 ** 22 // (width * supersample * supersample))
    for top in range(0, height, band):
        rows = min(band, height - top)
        d = _band(width, height, top, rows, supersample)
        out[top:top + rows] = np.asarray(radiance(d), np.float64).mean(axis=2)
    return out


def cell_directions(width: int, height: int, y: int, x: int, supersample: int) -> np.ndarray:
    """The ``supersample``² directions of node (y, x)'s cell, shape (s², 3)."""
    s = supersample
    o = (np.arange(s) + 0.5) / s
    phi = (x + o) / width * 2 * np.pi
    theta = np.clip((y + o - 0.5) / (height - 1), 0.0, 1.0) * np.pi
    theta, phi = (a.ravel() for a in np.meshgrid(theta, phi, indexing="ij"))
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta),
                     -np.cos(phi) * np.sin(theta)], axis=-1)


def _band(width, height, top, rows, supersample):
    """Sub-pixel directions of rows [top, top + rows) (see :func:`directions`)."""
    s = supersample
    offsets = (np.arange(s) + 0.5) / s
    u = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1) / width
    # row i covers θ ∈ [i − ½, i + ½]·π/(H − 1), clipped to [0, π] at the poles
    v = (np.arange(top, top + rows)[:, None] + offsets[None, :] - 0.5).reshape(-1)
    v = np.clip(v / (height - 1), 0.0, 1.0)
    phi, theta = np.meshgrid(u * 2 * np.pi, v * np.pi)
    d = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta),
                  -np.cos(phi) * np.sin(theta)], axis=-1)
    d = d.reshape(rows, s, width, s, 3).transpose(0, 2, 1, 3, 4)
    return d.reshape(rows, width, s * s, 3)


def _rgb(value) -> np.ndarray:
    return np.broadcast_to(np.asarray(value, np.float64), (3,)).copy()


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError(f"direction must be non-zero, got {v.tolist()}")
    return v / n


def constant(radiance: Colour = 1.0, width: int = 8, height: int = 4) -> np.ndarray:
    """Uniform radiance L everywhere (a furnace).

    Closed forms: irradiance on any plane E = π·L; total ∫ L dω = 4π·L; a
    convex diffuse object of albedo ρ has exitant radiance ρ·L everywhere.
    """
    return np.broadcast_to(_rgb(radiance), (height, width, 3)).astype(np.float32)


def cap(radiance: Colour = 10.0, alpha_deg: float = 20.0, direction: Vector = (0, 1, 0),
        width: int = WIDTH, height: int = HEIGHT, supersample: int = 16) -> np.ndarray:
    """Radiance L inside a cone of half-angle α around ``direction``, 0 outside.

    Closed forms: solid angle 2π(1 − cos α); irradiance on a plane facing the
    cone's axis E = π·L·sin²α (so a facing diffuse surface of albedo ρ has
    radiance ρ·L·sin²α).
    """
    if not 0 < alpha_deg <= 90:
        raise ValueError(f"alpha_deg must be in (0, 90], got {alpha_deg}")
    axis, L, cos_a = _unit(direction), _rgb(radiance), np.cos(np.radians(alpha_deg))
    return bake(lambda d: ((d @ axis) >= cos_a)[..., None] * L,
                width, height, supersample)


def gradient(zenith: Colour = (0.25, 0.45, 1.0), horizon: Colour = (1.0, 0.95, 0.85),
             ground: Colour = (0.2, 0.17, 0.15), width: int = 128,
             height: int = 64) -> np.ndarray:
    """Smooth sky: L(θ) = zenith·cosθ + horizon·(1 − cosθ) above the horizon
    (y = cosθ > 0) and a uniform ``ground`` below. Low frequency everywhere.

    Closed form: irradiance on an upward-facing plane
    E = 2π (zenith/3 + horizon/6).
    """
    z, h, g = _rgb(zenith), _rgb(horizon), _rgb(ground)

    def radiance(d):
        y = d[..., 1:2]
        return np.where(y > 0, z * y + h * (1 - y), g)

    return bake(radiance, width, height, supersample=1)


def checker(low: Colour = 0.1, high: Colour = 1.0, squares: int = 16,
            width: int = WIDTH, height: int = HEIGHT, supersample: int = 4) -> np.ndarray:
    """High-frequency checkerboard in (φ, θ): ``2·squares`` columns in φ and
    ``squares`` rows in θ, alternating ``low`` and ``high``.

    Closed form: every θ band holds equal φ-lengths of ``low`` and ``high``,
    so the irradiance on a plane facing ±y is E = π·(low + high)/2, like a
    constant map of the mean radiance.
    """
    if squares < 1:
        raise ValueError(f"squares must be >= 1, got {squares}")
    lo, hi = _rgb(low), _rgb(high)

    def radiance(d):
        theta = np.arccos(np.clip(d[..., 1], -1, 1))
        phi = np.mod(np.arctan2(d[..., 0], -d[..., 2]), 2 * np.pi)
        i = np.floor(phi / (2 * np.pi) * 2 * squares).astype(int)
        j = np.minimum(np.floor(theta / np.pi * squares).astype(int), squares - 1)
        return np.where(((i + j) % 2 == 0)[..., None], hi, lo)

    return bake(radiance, width, height, supersample)


#: Default lobes of :func:`sg`: (axis, sharpness λ, amplitude a). Both point
#: at the zenith, so the closed form for an upward plane applies exactly.
SG_LOBES = (((0, 1, 0), 4.0, (1.0, 0.9, 0.8)), ((0, 1, 0), 32.0, (4.0, 4.0, 4.0)))


def sg(lobes: Lobes = SG_LOBES, width: int = WIDTH, height: int = HEIGHT,
       supersample: int = 2) -> np.ndarray:
    """Sum of spherical Gaussians G(v) = a·exp(λ(μ·v − 1)).

    Closed forms, per lobe:

    * total ∫_{S²} G dω = 2π·a·(1 − e^{−2λ})/λ;
    * irradiance on a plane whose normal is the lobe axis μ,
      ∫_{H} G (μ·v) dω = 2π·a·(λ − 1 + e^{−λ})/λ²;
    * against a Phong lobe cosⁿ around μ: 2π·a·∫₀¹ tⁿ e^{λ(t−1)} dt
      (a lower incomplete gamma function).
    """
    parsed = [(_unit(mu), float(lam), _rgb(a)) for mu, lam, a in lobes]
    if any(lam <= 0 for _, lam, _ in parsed):
        raise ValueError("sharpness λ must be > 0")

    def radiance(d):
        return sum(a * np.exp(lam * (d @ mu - 1))[..., None] for mu, lam, a in parsed)

    return bake(radiance, width, height, supersample)


def irradiance(rgb: np.ndarray, normal=(0, 1, 0)) -> np.ndarray:
    """Irradiance ∫ L(v) max(0, n·v) dω of a discrete map (pixel quadrature).

    Each value is treated as constant over its node's cell, of solid angle
    Δφ·(cos θ₀ − cos θ₁) with θ₀,₁ = (i ∓ ½)·π/(H − 1) clipped to [0, π]; this
    is the number a renderer sees up to Mitsuba's bilinear interpolation, so
    comparing it with a closed form measures the map's discretisation error.
    """
    h, w, _ = rgb.shape
    n = _unit(normal)
    d = directions(w, h, 4)                                   # (h, w, 16, 3)
    cos = np.clip(d @ n, 0, None).mean(axis=2)                # mean cosine in cell
    return np.einsum("hwc,hw->c", rgb.astype(np.float64), cos * cell_solid_angles(h, w))


def cell_solid_angles(height: int, width: int) -> np.ndarray:
    """(H, W) solid angle Δφ·(cos θ₀ − cos θ₁) of each texel's cell, with
    θ₀,₁ = (i ∓ ½)·π/(H − 1) clipped to [0, π] (Mitsuba's row convention)."""
    bounds = np.clip((np.arange(height + 1) - 0.5) / (height - 1), 0, 1) * np.pi
    edges = np.cos(bounds)
    return np.repeat(((edges[:-1] - edges[1:]) * (2 * np.pi / width))[:, None], width, axis=1)
