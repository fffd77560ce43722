"""What bounds guided_path's learned density on sunlit_room under its hole:
the variance of one indirect bounce, per sample, with the density it learned
against densities that know the answer (oracles) on the same cells.

At the camera's first hit in each pixel (pixel centres), N directions are
drawn by each strategy and the one-bounce integrand is estimated: the
radiance leaving the sunlit patch (grey, albedo 1) towards the point, times
cos θ / π. Strategies:

* ``cosine``: BSDF sampling of a diffuse surface;
* ``learned``: guided_path's mixture (its BSDF share, its pmf) after a
  render of ``--spp`` at max_depth 3, so that its records carry this
  integrand alone;
* ``oracle point``: the same mixture and floor, with a pmf on the R² cells
  of the cosine-warped square made for each point from the integrand itself
  (cell means of J² jittered directions): what the cells allow;
* ``oracle leaf``: the point oracles' pmfs averaged over the points in one
  leaf of the learned tree: what the cells and the tree's leaves allow.

Printed per strategy: the relative variance of one sample (Σ var / Σ mean²
over the pixels) and the share of samples that reach the sunlit patch.

    python benchmarks/guide_bound.py --directional-res 32 64
    python benchmarks/guide_bound.py -p spatial_threshold=5

A script, not part of the installed package: it needs mcillum installed.
"""

from __future__ import annotations

import argparse
import ast

import numpy as np

import mcillum  # noqa: F401  (LLVM set-up before drjit)
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders

SUN = np.array([0.25, -1.0, 0.35]) / np.linalg.norm([0.25, -1.0, 0.35])   # (the scene's)
IRRADIANCE = 500.0


def pixel_centres(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Film coordinates (x, y) of the res² pixel centres, row major."""
    x, y = np.meshgrid((np.arange(res) + 0.5) / res, (np.arange(res) + 0.5) / res)
    return x.ravel(), y.ravel()


def first_hits(scene, x: np.ndarray, y: np.ndarray, n: int):
    """The camera's first hits at film points (x, y), ``n`` lanes per point
    (point major)."""
    import mitsuba as mi
    pos = mi.Point2f(np.repeat(x, n), np.repeat(y, n))
    ray, _ = scene.sensors()[0].sample_ray(0, 0.5, pos, mi.Point2f(0.5))
    return scene.ray_intersect(ray)


def patch_radiance(scene, si, w):
    """Radiance leaving the sunlit patch towards ``si`` along -``w`` (0 where
    the ray from ``si`` along ``w`` meets no sunlit surface)."""
    import drjit as dr
    import mitsuba as mi
    ray = si.spawn_ray(w)
    hit = scene.ray_intersect(ray)
    lit = dr.maximum(dr.dot(hit.sh_frame.n, mi.Vector3f(-SUN)), 0)
    lit = dr.select(dr.dot(hit.n, -ray.d) > 0, lit, 0)
    seen = ~scene.ray_test(hit.spawn_ray(mi.Vector3f(-SUN)))
    return dr.select(hit.is_valid() & seen, IRRADIANCE * lit / dr.pi, 0.0)


def oracle_pmfs(scene, res: int, R: int, jitter: int, chunk: int = 64) -> np.ndarray:
    """Per pixel, the integrand's mean over each of the R² cells (pixels, R²)."""
    import mitsuba as mi
    from mcillum.integrators.guiding import guided_path as gp
    cells = R * R
    per = cells * jitter * jitter
    c = np.repeat(np.arange(cells), jitter * jitter)
    j = (np.arange(jitter) + 0.5) / jitter
    jx, jy = np.tile(np.repeat(j, jitter), cells), np.tile(np.tile(j, jitter), cells)
    u = ((c % R) + jx) / R, ((c // R) + jy) / R
    out = np.zeros((res * res, cells))
    x, y = pixel_centres(res)
    for p0 in range(0, res * res, chunk):
        px, py = x[p0:p0 + chunk], y[p0:p0 + chunk]
        si = first_hits(scene, px, py, per)
        square = mi.Point2f(np.tile(u[0], len(px)), np.tile(u[1], len(px)))
        w = gp.from_guide(si, mi.warp.square_to_cosine_hemisphere(square))
        L = np.array(patch_radiance(scene, si, w))
        out[p0:p0 + chunk] = L.reshape(len(px), cells, jitter * jitter).mean(axis=2)
    return out


def evaluate(scene, res: int, n: int, R: int, pmf: np.ndarray, alpha: np.ndarray,
             seed: int, anchor=None) -> tuple[float, float]:
    """(relative variance of one sample, share reaching the patch) of the
    mixture α·cosine + (1 − α)·pmf (per pixel: ``pmf`` (pixels, R²), ``alpha``
    (pixels,)); ``anchor`` (per pixel its anchor (pixels, 3) and learned
    distance (pixels,)) draws the pmf's cells as seen from the anchor, as
    guided_path does (None: from the point)."""
    import drjit as dr
    import mitsuba as mi
    from mcillum.integrators.guiding import guided_path as gp
    rng = np.random.default_rng(seed)
    pixels = res * res
    cdf = np.cumsum(pmf, axis=1)
    cdf /= cdf[:, -1:]
    cell = np.stack([np.searchsorted(cdf[i], rng.random(n)) for i in range(pixels)])
    cell = cell.clip(0, R * R - 1)
    bsdf = (rng.random((pixels, n)) < alpha[:, None]).ravel()
    ux = np.where(bsdf, rng.random(pixels * n), ((cell.ravel() % R) + rng.random(pixels * n)) / R)
    uy = np.where(bsdf, rng.random(pixels * n), ((cell.ravel() // R) + rng.random(pixels * n)) / R)
    si = first_hits(scene, *pixel_centres(res), n)
    centre = np.zeros((pixels, 3)) if anchor is None else anchor[0]
    distance = np.zeros(pixels) if anchor is None else anchor[1]
    c = mi.Point3f(*[np.repeat(centre[:, k], n) for k in range(3)])
    d = mi.Float(np.repeat(distance, n))
    drawn = gp.from_guide(si, mi.warp.square_to_cosine_hemisphere(mi.Point2f(ux, uy)))
    w = dr.select(mi.Bool(bsdf), drawn, gp.from_anchor(si.p, drawn, c, d))
    w_c, jacobian = gp.to_anchor(si.p, w, c, d)
    local = gp.to_guide(si, w_c)
    at = np.array(gp.square_cell(mi.warp.cosine_hemisphere_to_square(local), R))
    pmf_at = pmf.ravel()[np.repeat(np.arange(pixels), n) * R * R + at]
    cos_x = np.maximum(np.array(gp.to_guide(si, w).z), 0)
    p_guide = pmf_at * R * R * np.maximum(np.array(local.z), 0) * np.array(jacobian)
    a = np.repeat(alpha, n)
    p = a * cos_x + (1 - a) * p_guide                 # (both over 1/π)
    L = np.array(patch_radiance(scene, si, w))
    x = np.where(p > 0, L * cos_x / np.maximum(p, 1e-30), 0).reshape(pixels, n)
    L = L.reshape(pixels, n)
    valid = np.array(si.is_valid()).reshape(pixels, n)[:, 0]
    mean, var = x.mean(axis=1)[valid], x.var(axis=1)[valid]
    return float(var.sum() / np.sum(mean ** 2)), float(np.mean(L[valid] > 0))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--res", type=int, default=64)
    parser.add_argument("--spp", type=int, default=1024, help="guided_path's training render")
    parser.add_argument("--samples", type=int, default=512, help="directions per pixel")
    parser.add_argument("--directional-res", type=int, nargs="+", default=[32],
                        help="the oracles' R")
    parser.add_argument("--jitter", type=int, default=2)
    parser.add_argument("-p", dest="params", action="append", default=[],
                        help="guided_path property, key=value (repeatable)")
    args = parser.parse_args(argv)
    renders.set_variant("llvm_ad_rgb")
    from mcillum.integrators.guiding import directional, guide as guide_mod, spatial

    scene = renders.load_scene(scenes.path("sunlit_room"), res=args.res, gap="hole",
                               sun=IRRADIANCE)
    learned = {}
    learn = guide_mod.Guide.learn.__func__

    def keep(cls, *a, **k):             # (the render's last guide, for the table)
        learned["guide"] = learn(cls, *a, **k)
        return learned["guide"]

    guide_mod.Guide.learn = classmethod(keep)
    params = {"max_depth": 3, **{k: ast.literal_eval(v) for k, v in
                                 (p.split("=", 1) for p in args.params)}}
    integrator = renders.make_integrator("guided_path", params)
    renders.render(scene, integrator, args.spp, seed=1)
    guide_mod.Guide.learn = classmethod(learn)
    g, share = learned["guide"], integrator.bsdf_fraction
    pixels = args.res * args.res
    grid = spatial.grid_of(scene.bbox())
    hits = first_hits(scene, *pixel_centres(args.res), 1)
    node = g.voxel_node[np.array(spatial.voxel_of(hits.p, grid))]
    # (what the plugin samples from: each leaf's BSDF share, quantized pmf
    # and learned distance)
    tables = {k: np.array(v) for k, v in g.device(share).items()}
    row = tables["leaf"][np.array(spatial.voxel_of(hits.p, grid))]
    alpha = tables["alpha"][row]
    quantized = tables["pmf"].reshape(-1, g.res * g.res)[row]
    from mcillum.integrators.guiding import guided_path as gp
    at = spatial.on_plane(spatial.anchor_of(hits.p, grid), hits.p, gp.guide_frame(hits).n)
    centre = np.array(at).T.reshape(pixels, 3)
    anchors = (centre, tables["distance"][row])
    rows = [("cosine", 1, np.full((pixels, 1), 1.0), np.ones(pixels), None),
            (f"learned ({g.leaves} leaves)", g.res, quantized, alpha, anchors)]
    for R in args.directional_res:
        means = oracle_pmfs(scene, args.res, R, args.jitter)
        norm = means / np.maximum(means.sum(axis=1, keepdims=True), 1e-30)
        by_leaf = np.zeros((g.child.size, R * R))
        np.add.at(by_leaf, node, norm)
        for name, m in (("oracle point", means), ("oracle leaf", by_leaf[node])):
            total = m.sum(axis=1, keepdims=True)
            pmf = np.where(total > 0, (1 - directional.FLOOR) * m / np.maximum(total, 1e-30)
                           + directional.FLOOR / (R * R), 1.0 / (R * R))
            rows.append((f"{name}, R = {R}", R, pmf, np.full(pixels, share), None))
    print("| strategy | cells | relative variance of one sample | share reaching the patch |")
    print("|---|---|---|---|")
    for name, R, pmf, a, anchor in rows:
        rel, reach = evaluate(scene, args.res, args.samples, R, pmf, a, seed=7, anchor=anchor)
        print(f"| {name} | {R}² | {rel:.1f} | {reach:.4f} |", flush=True)


if __name__ == "__main__":
    main()
