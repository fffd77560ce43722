"""The `phong` BSDF: sampling (χ²), energy, reciprocity, refusals, and
agreement between Mitsuba's `path` and our estimators on a Phong scene.

χ²: 10⁶ samples, α = 0.01, pdf integrated with ires = 32 per cell. A cosⁿ
lobe that straddles the pole of mi.chi2's sphere grid (n = 100 at 5–10°) is
mis-integrated at the default ires = 8 (pdf sum 0.9995; rejected at p = 4e-8),
at 16 or 32 it sums to 1 ± 1e-5 and is accepted.
"""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mcillum.validation import renders, statistics

from conftest import ALL_ESTIMATORS, ROOT, batch

ALPHA = 0.01


def chi2(n, theta_deg, plugin="phong", kd=0.3, ks=0.6):
    wi = mi.ScalarVector3f(float(np.sin(np.radians(theta_deg))), 0.0,
                           float(np.cos(np.radians(theta_deg))))
    sample, pdf = mi.chi2.BSDFAdapter(
        plugin, f'<float name="exponent" value="{n}"/>'
                f'<float name="diffuse_reflectance" value="{kd}"/>'
                f'<float name="specular_reflectance" value="{ks}"/>', wi=wi)
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=3, sample_count=1_000_000,
                                 res=101, ires=32)
    return test.run(ALPHA), test


@pytest.mark.parametrize("theta", [10, 50, 80])
@pytest.mark.parametrize("n", [1, 10, 100, 1000])
def test_chi2_sampling_matches_pdf(llvm, n, theta, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # mi.chi2 writes chi2_data.py on rejection
    ok, test = chi2(n, theta)
    assert ok, test.messages


def test_chi2_rejects_a_wrong_pdf(llvm, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    from mcillum.integrators.phong import PhongBSDF

    class WrongPdf(PhongBSDF):
        def pdf(self, ctx, si, wo, active=True):
            return 1.05 * super().pdf(ctx, si, wo, active)

    mi.register_bsdf("phong_wrong_pdf", lambda props: WrongPdf(props))
    ok, _ = chi2(10, 30, plugin="phong_wrong_pdf")
    assert not ok


def make(kd=0.3, ks=0.6, n=10.0):
    return mi.load_dict({"type": "phong", "diffuse_reflectance": kd,
                         "specular_reflectance": ks, "exponent": n})


def interaction(wi):
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = wi
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    return si


def albedo(bsdf, theta_deg, count=1 << 20):
    """E[f cos/p] under the BSDF's own sampling, with its standard error."""
    rng = np.random.default_rng(7)
    u1, u2 = rng.random(count), rng.random((2, count))
    t = np.radians(theta_deg)
    wi = mi.Vector3f(float(np.sin(t)), 0.0, float(np.cos(t)))
    _, w = bsdf.sample(mi.BSDFContext(), interaction(wi), mi.Float(u1),
                       mi.Point2f(u2[0], u2[1]))
    w = np.array(w)[0]
    return w.mean(), w.std() / np.sqrt(count)


@pytest.mark.parametrize("n", [1, 10, 100, 1000])
def test_albedo_at_normal_incidence_is_kd_plus_ks(llvm, n):
    """The (n+2)/(2π) normalisation makes the specular lobe's albedo exactly
    k_s at normal incidence; so k_d + k_s = 1 is a white furnace there."""
    mean, se = albedo(make(0.3, 0.7, n), 0.0)
    assert abs(mean - 1.0) <= 4 * se + 1e-6


@pytest.mark.parametrize("theta", [30, 60, 85])
@pytest.mark.parametrize("n", [1, 10, 100, 1000])
def test_albedo_never_exceeds_one(llvm, n, theta):
    mean, se = albedo(make(0.3, 0.7, n), theta)
    assert mean <= 1.0 + 4 * se


def test_reciprocity(llvm):
    bsdf = make(0.2, 0.5, 20)
    rng = np.random.default_rng(3)
    a = mi.warp.square_to_uniform_hemisphere(mi.Point2f(*rng.random((2, 4096))))
    b = mi.warp.square_to_uniform_hemisphere(mi.Point2f(*rng.random((2, 4096))))
    ctx = mi.BSDFContext()
    f_ab = bsdf.eval(ctx, interaction(a), b) / b.z      # eval includes cos θ_o
    f_ba = bsdf.eval(ctx, interaction(b), a) / a.z
    assert dr.allclose(f_ab, f_ba, rtol=1e-4, atol=1e-6)


def test_one_sided_and_parameters_editable(llvm):
    bsdf = make()
    below = interaction(mi.Vector3f(0, 0, -1))
    assert dr.all(bsdf.eval(mi.BSDFContext(), below, mi.Vector3f(0, 0, 1))[0] == 0)
    params = mi.traverse(bsdf)
    assert "exponent" in params and "diffuse_reflectance.value" in params


@pytest.mark.parametrize("props, message", [
    ({"diffuse_reflectance": 0.6, "specular_reflectance": 0.5}, "exceeds 1"),
    ({"exponent": 0.0}, "exponent must be a number > 0"),
    ({"exponent": -3.0}, "exponent must be a number > 0"),
])
def test_bad_parameters_are_refused(llvm, props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "phong", **props})


def test_white_furnace_sphere(llvm):
    """k_d = 1, k_s = 0 under a constant environment: exactly L everywhere."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 8,
                                                    "height": 8, "rfilter": {"type": "box"}},
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0],
                                                              up=[0, 1, 0]).scale([0.5, 0.5, 1])},
        "ball": {"type": "sphere", "bsdf": {"type": "phong", "diffuse_reflectance": 1.0,
                                            "specular_reflectance": 0.0}},
        "env": {"type": "constant", "radiance": 2.0}})
    image = renders.render(scene, renders.make_integrator("cosine_hemisphere",
                                                          {"max_depth": 2}), 16).image
    np.testing.assert_allclose(image, 2.0, rtol=1e-5)


@pytest.mark.parametrize("name", ALL_ESTIMATORS)
def test_estimators_agree_with_path_on_phong(llvm, name):
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "film": {"type": "hdrfilm", "width": 12, "height": 12,
                            "rfilter": {"type": "box"}},
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 4], target=[0, 0, 0],
                                                              up=[0, 1, 0])},
        "ball": {"type": "sphere", "bsdf": {"type": "phong", "diffuse_reflectance": 0.3,
                                            "specular_reflectance": 0.5, "exponent": 10}},
        "env": {"type": "envmap", "filename": str(ROOT / "envmaps" / "sky_gradient.exr")}})
    est = batch(scene, renders.make_integrator(name, {"max_depth": 3}), 256, 16)
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 3}), 256, 16,
                first_seed=10_000)
    result = statistics.compare(est, ref, ALPHA)
    assert result.passed, result.summary()
