"""χ² goodness-of-fit of the direction-sampling strategies (mi.chi2).

Each test draws 10^6 directions and compares their histogram on a 101×202
sphere grid with the integrated pdf; significance α = 0.01 (mi.chi2 applies
its own correction for the number of cells it pools). A pdf off by 5% either
way must be rejected by the same test.
"""

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

ALPHA = 0.01


def strategies():
    from mcillum.integrators import cosine_hemisphere as c, uniform_hemisphere as u

    return {
        "uniform": (u.sample_uniform_hemisphere, u.uniform_hemisphere_pdf,
                    u.invert_uniform_hemisphere),
        "cosine": (c.sample_cosine_hemisphere, c.cosine_hemisphere_pdf,
                   c.invert_cosine_hemisphere),
    }


def chi2(sample, pdf):
    test = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=2, sample_count=1_000_000,
                                 res=101, ires=4)
    return test.run(ALPHA), test


@pytest.mark.parametrize("name", ["uniform", "cosine"])
def test_chi2_accepts_strategy(llvm, name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # mi.chi2 writes chi2_data.py on rejection
    sample, pdf, _ = strategies()[name]
    ok, test = chi2(sample, pdf)
    assert ok, test.messages


@pytest.mark.parametrize("factor", [1.05, 1 / 1.05])
@pytest.mark.parametrize("name", ["uniform", "cosine"])
def test_chi2_rejects_wrong_pdf(llvm, name, factor, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    sample, pdf, _ = strategies()[name]
    ok, test = chi2(sample, lambda w: factor * pdf(w))
    assert not ok, f"a pdf scaled by {factor} passed χ²:\n{test.messages}"


@pytest.mark.parametrize("name", ["uniform", "cosine"])
def test_pdf_is_zero_below_the_horizon(variant, name):
    _, pdf, _ = strategies()[name]
    for z in (-1.0, -1e-3, 0.0):
        w = dr.normalize(mi.Vector3f(0.3, 0.2, z))
        assert dr.all(pdf(w) == 0), f"{name} pdf nonzero at z={z}"
    assert dr.all(pdf(mi.Vector3f(0, 0, 1)) > 0)


@pytest.mark.parametrize("name", ["uniform", "cosine"])
def test_sample_is_on_upper_hemisphere_and_inverts(llvm, name):
    sample, pdf, invert = strategies()[name]
    rng = np.random.default_rng(1)
    u = mi.Point2f(*(rng.uniform(0.001, 0.999, (2, 4096))))
    w = sample(u)
    assert dr.all((w.z > 0) & (dr.abs(dr.norm(w) - 1) < 1e-5))
    back = invert(w)
    assert dr.max(dr.abs(back.x - u.x)) < 1e-4 and dr.max(dr.abs(back.y - u.y)) < 1e-4


def test_cosine_pdf_matches_lambert(llvm):
    """p(ω) = cos θ / π exactly (and 1/2π for uniform), not just in shape."""
    s = strategies()
    w = dr.normalize(mi.Vector3f(0.6, -0.2, 0.7))
    assert dr.allclose(s["cosine"][1](w), w.z / dr.pi)
    assert dr.allclose(s["uniform"][1](w), 1 / (2 * dr.pi))
