"""Split a render whose wavefront would overflow 32 bits into passes.

A Mitsuba render traces one lane per sample, W·H·spp lanes in one wavefront,
and indexes them with 32-bit integers. Mitsuba 3.9.1 splits larger requests
itself, but only when spp divides evenly into its pass count: 2×2 pixels at
2³¹ spp fail with "[Sampler] sample_count should be a multiple of
samples_per_wavefront". These pure functions plan passes that always work:
every pass holds at most :data:`MAX_WAVEFRONT` lanes and the pass spp differ by
at most one. Passes are averaged with weights spp_i / spp, which is the
single-pass estimator for a box filter and a consistent one for any other.

Nothing here depends on the variant.
"""

from __future__ import annotations

#: Largest number of lanes (W·H·spp, film border included) in one pass.
MAX_WAVEFRONT = 0xFFFFFFFF


def plan_passes(pixels: int, spp: int, max_wavefront: int | None = None) -> list[int]:
    """Samples per pixel of each pass: ``pixels · spp_i ≤ max_wavefront``
    (default :data:`MAX_WAVEFRONT`), ``Σ spp_i = spp``, as few passes as
    possible, as even as possible."""
    max_wavefront = max_wavefront or MAX_WAVEFRONT
    if pixels < 1 or spp < 1:
        raise ValueError(f"need at least one pixel and one sample, got {pixels} pixels, "
                         f"{spp} spp")
    per_pass = max_wavefront // pixels
    if per_pass < 1:
        raise ValueError(
            f"one sample per pixel of {pixels} pixels exceeds the {max_wavefront}-lane "
            "wavefront limit; render the image in crops (film crop_width/crop_height)")
    n = -(-spp // per_pass)                      # ceil(spp / per_pass)
    base, extra = divmod(spp, n)
    return [base + 1] * extra + [base] * (n - extra)


def film_lanes(film) -> int:
    """Lanes per sample per pixel of one pass over a Mitsuba ``film``: its
    crop, plus the reconstruction filter's border where the film samples it."""
    size = film.crop_size()
    border = film.rfilter().border_size() if film.sample_border() else 0
    return (int(size[0]) + 2 * border) * (int(size[1]) + 2 * border)


def render_in_passes(plan: list[int], seed: int, render_pass):
    """Σ_i (spp_i / spp) · ``render_pass(seed_i, spp_i)`` over the passes of
    ``plan``, evaluated after each pass (seed_i from :func:`pass_seed`); one
    pass is returned as rendered."""
    import drjit as dr

    if len(plan) == 1:
        return render_pass(seed, plan[0])
    spp, image = sum(plan), None
    for i, n in enumerate(plan):
        part = render_pass(pass_seed(seed, i), n) * (n / spp)
        image = part if image is None else image + part
        dr.eval(image)
    return image


def pass_seed(seed: int, index: int) -> int:
    """Seed of pass ``index`` of a render with ``seed`` (pass 0 keeps ``seed``,
    so an unsplit render is unchanged). Later passes get a 32-bit mix of both,
    so the passes of seed s do not replay the renders of seeds s+1, s+2, ..."""
    if index == 0:
        return seed
    x = (seed * 0x9E3779B1 + index * 0x85EBCA77) & 0xFFFFFFFF   # splitmix-style
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x846CA68B) & 0xFFFFFFFF
    return x ^ (x >> 16)
