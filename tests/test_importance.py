"""bsdf_sampling, emitter_sampling and mis against Mitsuba's `path` (same
batch-means test and budgets as tests/test_against_path.py, α = 0.01), and
what each reaches or refuses."""

import numpy as np
import pytest

from mcillum.validation import renders, scenes, statistics

from conftest import batch, wrong_pdf_integrator

ALPHA = 0.01
NEW = ["bsdf_sampling", "emitter_sampling", "mis"]
# scene: (res, spp, renders per side) — the Cornell light needs many samples
BUDGET = {"cornell_box": (8, 2048, 16), "probe_spheres": (8, 512, 16),
          "smooth_glass": (8, 256, 16), "point_light": (8, 64, 16)}


def compare(scene_name, integrator, max_depth, reference="path"):
    res, spp, k = BUDGET[scene_name]
    scene = renders.load_scene(scenes.path(scene_name), res=res)
    if isinstance(integrator, str):
        integrator = renders.make_integrator(integrator, {"max_depth": max_depth})
    est = batch(scene, integrator, spp, k)
    ref = batch(scene, renders.make_integrator(reference, {"max_depth": max_depth}), spp, k,
                first_seed=10_000)
    return statistics.compare(est, ref, ALPHA), est, ref


@pytest.mark.parametrize("max_depth", [2, -1])
@pytest.mark.parametrize("scene", ["cornell_box", "probe_spheres"])
@pytest.mark.parametrize("name", NEW)
def test_agrees_with_path(llvm, name, scene, max_depth):
    result, _, _ = compare(scene, name, max_depth)
    assert result.passed, result.summary()


@pytest.mark.parametrize("name", ["bsdf_sampling", "mis"])
def test_delta_bsdfs_and_transmission_are_reached(llvm, name):
    result, _, _ = compare("smooth_glass", name, -1)
    assert result.passed, result.summary()


@pytest.mark.parametrize("name", ["emitter_sampling", "mis"])
def test_delta_emitters_are_reached(llvm, name):
    result, _, _ = compare("point_light", name, 2)
    assert result.passed, result.summary()


def test_wrong_pdf_is_rejected_in_the_new_loop(llvm):
    """The emitter-sampling loop with its BSDF continuation still rejects a
    hemisphere estimator whose pdf is 5% off (NEE paths change the loop)."""
    result, _, _ = compare("probe_spheres", wrong_pdf_integrator("cosine_hemisphere"), -1)
    assert not result.passed


@pytest.mark.parametrize("scene, name", [
    ("point_light", "bsdf_sampling"), ("smooth_glass", "emitter_sampling"),
])
def test_unreachable_content_is_refused(llvm, scene, name):
    from mcillum.integrators import UnreachableContentError

    loaded = renders.load_scene(scenes.path(scene), res=2)
    with pytest.raises(Exception) as info:
        renders.render(loaded, renders.make_integrator(name), 1)
    assert isinstance(renders.root_cause(info.value), UnreachableContentError)


def test_strategy_pdfs_match_their_samplers(llvm):
    """Each file's pdf function returns the density its sampler reported, for
    the same directions (so MIS weights use the right numbers)."""
    import drjit as dr
    import mitsuba as mi

    from mcillum.integrators.bsdf_sampling import bsdf_direction_pdf, sample_bsdf_direction
    from mcillum.integrators.emitter_sampling import emitter_direction_pdf, sample_emitter_direction

    rng = np.random.default_rng(11)
    n = 4096
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = dr.normalize(mi.Vector3f(0.3, -0.2, 0.9))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    ctx = mi.BSDFContext()
    for bsdf in (mi.load_dict({"type": "phong", "exponent": 50.0}),
                 mi.load_dict({"type": "roughconductor", "alpha": 0.2})):
        wo, _, pdf, delta, _ = sample_bsdf_direction(
            bsdf, ctx, si, mi.Float(rng.random(n)), mi.Point2f(*rng.random((2, n))))
        ok = (pdf > 0) & ~delta
        assert dr.count(ok) > n // 2
        assert dr.allclose(dr.select(ok, bsdf_direction_pdf(bsdf, ctx, si, wo), 0),
                           dr.select(ok, pdf, 0), rtol=1e-3)

    scene = renders.load_scene(scenes.path("sky_sphere"), res=2)
    it = dr.zeros(mi.SurfaceInteraction3f, n)
    it.p = mi.Point3f(0, 3, 0)                      # above the sphere, sees the sky
    ds, _ = sample_emitter_direction(scene, it, mi.Point2f(*rng.random((2, n))))
    ok = ds.pdf > 0
    assert dr.count(ok) > n // 2
    assert dr.allclose(dr.select(ok, emitter_direction_pdf(scene, it, ds), 0),
                       dr.select(ok, ds.pdf, 0), rtol=1e-3)
