"""Each estimator's direction sampling matches the pdf it reports.

Hemisphere strategies (a pure ``sample_local`` / ``pdf_local`` /
``invert_local`` trio on the class): χ² goodness of fit with mi.chi2, 10⁶
directions on a 101×202 sphere grid, α = 0.01 (mi.chi2 corrects for the cells
it pools); a pdf scaled by 1.05 or 1/1.05 must be rejected by the same test.
The pdf is zero below the horizon (Mitsuba's warp pdfs are not), and the
inverse undoes the sampler. BSDF and emitter sampling: each strategy file's pdf
function returns the density its sampler reported, for the same directions
(so MIS weights use the right numbers).
"""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mcillum.integrators.mc.bsdf_sampling import bsdf_direction_pdf, sample_bsdf_direction
from mcillum.integrators.mc.emitter_sampling import emitter_direction_pdf, sample_emitter_direction
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders

from conftest import HEMISPHERE
from twins import plugin_class

ALPHA = 0.01


def trio(name):
    cls = plugin_class(name)
    return cls.sample_local, cls.pdf_local, cls.invert_local


def chi2(sample, pdf):
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=2, sample_count=1_000_000,
                                 res=101, ires=4)
    return test.run(ALPHA), test


@pytest.mark.parametrize("name", HEMISPHERE)
def test_chi2_accepts_strategy(llvm, name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # mi.chi2 writes chi2_data.py on rejection
    sample, pdf, _ = trio(name)
    ok, test = chi2(sample, pdf)
    assert ok, test.messages


@pytest.mark.parametrize("factor", [1.05, 1 / 1.05])
@pytest.mark.parametrize("name", HEMISPHERE)
def test_chi2_rejects_wrong_pdf(llvm, name, factor, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    sample, pdf, _ = trio(name)
    ok, test = chi2(sample, lambda w: factor * pdf(w))
    assert not ok, f"a pdf scaled by {factor} passed χ²:\n{test.messages}"


@pytest.mark.parametrize("name", HEMISPHERE)
def test_pdf_is_zero_below_the_horizon(variant, name):
    _, pdf, _ = trio(name)
    for z in (-1.0, -1e-3, 0.0):
        w = dr.normalize(mi.Vector3f(0.3, 0.2, z))
        assert dr.all(pdf(w) == 0), f"{name} pdf nonzero at z={z}"
    assert dr.all(pdf(mi.Vector3f(0, 0, 1)) > 0)


@pytest.mark.parametrize("name", HEMISPHERE)
def test_sample_is_on_upper_hemisphere_and_inverts(llvm, name):
    sample, pdf, invert = trio(name)
    rng = np.random.default_rng(1)
    u = mi.Point2f(*(rng.uniform(0.001, 0.999, (2, 4096))))
    w = sample(u)
    assert dr.all((w.z > 0) & (dr.abs(dr.norm(w) - 1) < 1e-5))
    back = invert(w)
    assert dr.max(dr.abs(back.x - u.x)) < 1e-4 and dr.max(dr.abs(back.y - u.y)) < 1e-4


def test_pdfs_are_the_closed_forms(llvm):
    """p(ω) = cos θ / π and 1/2π exactly, not just in shape (the closed forms
    are written here, not read from the code under test)."""
    w = dr.normalize(mi.Vector3f(0.6, -0.2, 0.7))
    assert dr.allclose(trio("cosine_hemisphere")[1](w), w.z / dr.pi)
    assert dr.allclose(trio("uniform_hemisphere")[1](w), 1 / (2 * dr.pi))


def test_bsdf_and_emitter_pdfs_match_their_samplers(llvm):
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
