"""Scenes written the way stock Mitsuba scenes are written (its render tests:
a scene file that ``<include>``s fragments, a ``<path>`` to shared files,
the integrator under test as ``$integrator`` nested in ``moment``, rough
BSDFs whose roughness is a texture with a ``to_uv`` transform, spectra given
as ``wavelength:value`` pairs, OBJ meshes, bitmap textures).

Every estimator on them renders, or refuses with its message: never a crash
(a textured roughness once raised TypeError in the scene check), never a
silently biased image (nested in ``moment`` or ``aov``, which call
``sample()`` without ``render()``, the refusal did not run). Where they
render, they agree with `path`.
"""

from __future__ import annotations

import numpy as np
import pytest

import mitsuba as mi

from mcillum.errors import root_cause
from mcillum.integrators import UnreachableContentError
from mcillum.integrators.core import registry
from mcillum.validation.run import renders
from mcillum.validation.stats import statistics

from conftest import ALL_ESTIMATORS, POINT_SETS, batch

EVERY = [*ALL_ESTIMATORS, *POINT_SETS]

SPHERE = """<scene version="3.0.0">
    <shape type="obj">
        <string name="filename" value="meshes/tetra.obj"/>
        <ref id="surface"/>
    </shape>
    <shape type="sphere">
        <point name="center" value="0, 0, 0"/>
        <float name="radius" value="1"/>
        <ref id="surface"/>
    </shape>
</scene>
"""

#: A tetrahedron below the sphere (OBJ, as stock scenes load meshes).
TETRA = """v -1 -1.6 -1
v 1 -1.6 -1
v 0 -1.6 1
v 0 -1.2 0
f 1 2 4
f 2 3 4
f 3 1 4
"""

SCENE = """<scene version="3.0.0">
    <default name="integrator" value="path"/>
    <default name="spp" value="4"/>
    <default name="res" value="8"/>
    <default name="alpha_low" value="0.1"/>
    <path value="common"/>

    <integrator type="moment">
        <integrator type="$integrator">
            {params}
        </integrator>
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="35"/>
        <transform name="to_world">
            <lookat origin="0, 0.5, 5" target="0, -0.2, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="$res"/>
            <rfilter type="box"/>
        </film>
    </sensor>

    <bsdf type="roughconductor" id="surface">
        <string name="distribution" value="ggx"/>
        <texture type="checkerboard" name="alpha_u">
            <float name="color0" value="$alpha_low"/>
            <float name="color1" value="0.4"/>
            <transform name="to_uv"><scale x="4" y="4"/></transform>
        </texture>
        <texture type="bitmap" name="alpha_v">
            <string name="filename" value="textures/roughness.exr"/>
            <boolean name="raw" value="true"/>
        </texture>
        <spectrum name="eta" value="400:0.2, 500:0.9, 600:1.1, 700:1.3"/>
        <spectrum name="k" value="400:3.9, 500:2.4, 600:3.2, 700:4.0"/>
    </bsdf>

    <include filename="fragments/sphere.xml"/>
    {lights}
</scene>
"""

SKY = '<emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>'
POINT = ('<emitter type="point" id="key_light"><point name="position" value="2, 3, 2"/>'
         '<rgb name="intensity" value="20"/></emitter>')


def write_scene(root, lights=SKY, params=""):
    """A scene folder as Mitsuba's render tests lay one out: the scene file,
    fragments/ for its parts, common/ (found by ``<path>``) for meshes and
    textures. Returns the scene file's path."""
    for folder in ("fragments", "common/meshes", "common/textures"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    (root / "fragments" / "sphere.xml").write_text(SPHERE)
    (root / "common" / "meshes" / "tetra.obj").write_text(TETRA)
    texels = np.linspace(0.15, 0.5, 16, dtype=np.float32).reshape(4, 4, 1)
    mi.Bitmap(texels).write(str(root / "common" / "textures" / "roughness.exr"))
    path = root / "scene.xml"
    path.write_text(SCENE.format(lights=lights, params=params))
    return str(path)


def render_wrapped(path, integrator, **defines):
    """The scene as written (its own moment-wrapped integrator), by mi.render."""
    scene = mi.load_file(path, integrator=integrator, **{k: str(v) for k, v in defines.items()})
    return mi.render(scene)


def refusal(call):
    """The UnreachableContentError ``call()`` raises (Mitsuba wraps it), or None."""
    try:
        call()
    except Exception as err:  # noqa: BLE001
        cause = root_cause(err)
        if isinstance(cause, UnreachableContentError):
            return cause
        raise
    return None


def direct_params(name):
    """The estimators of N directions define max_depth 2 only."""
    return '<integer name="max_depth" value="2"/>' if name in POINT_SETS else ""


# ------------------------------ Textured roughness ------------------------------

@pytest.mark.parametrize("name", EVERY)
def test_textured_roughness_renders_or_refuses_by_its_smallest_value(llvm, tmp_path, name):
    """A checkerboard roughness with a to_uv transform (and a bitmap one, and
    spectral eta/k): read by its smallest value, 0.1 — every estimator that
    reaches glossy lobes (all of them) renders. At 0.001
    the estimators of the hemisphere refuse the near-specular lobe, naming
    its alpha (by their registry facts, bsdf_sampling, emitter_sampling and mis
    sample such lobes by the BSDF, and render)."""
    path = write_scene(tmp_path, params=direct_params(name))
    err = refusal(lambda: render_wrapped(path, name))
    assert err is None, err
    err = refusal(lambda: render_wrapped(path, name, alpha_low=0.001))
    if registry.facts(name).renders(("delta_bsdf",)):       # it samples the lobe itself
        assert err is None, err
    else:
        assert err is not None and "near-specular lobe (alpha 0.001" in str(err), err


def test_a_roughness_that_cannot_be_read_counts_as_near_specular(llvm):
    """A mesh attribute's traversed number is its scale, not its values: the
    roughness is unreadable, and a hemisphere estimator refuses, saying so."""
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "constant"},
        "ball": {"type": "sphere", "bsdf": {
            "type": "roughconductor",
            "alpha": {"type": "mesh_attribute", "name": "vertex_color"}}}})
    err = refusal(lambda: renders.make_integrator("cosine_hemisphere").check_scene(scene))
    assert err is not None and "cannot be read" in str(err)


@pytest.mark.parametrize("name", ["cosine_hemisphere", "emitter_sampling"])
def test_textured_roughness_agrees_with_path(llvm, tmp_path, name):
    """Rendered alone (no wrapper), the textured, spectral, included scene
    agrees with `path` per pixel (α = 0.01, Šidák)."""
    path = write_scene(tmp_path)
    scene = renders.load_scene(path, res=8)
    est = batch(scene, renders.make_integrator(name, {"max_depth": 3}), 64, 16)
    ref = batch(scene, renders.make_integrator("path", {"max_depth": 3}), 64, 16,
                first_seed=10_000)
    result = statistics.compare(est, ref, statistics.ALPHA)
    assert result.passed, result.summary()


# ----------------------------------- Wrappers -----------------------------------

@pytest.mark.parametrize("name", [n for n in EVERY
                                  if "delta_emitter" not in registry.facts(n).reaches])
def test_refusal_holds_nested_in_moment(llvm, tmp_path, name):
    """`moment` calls the nested integrator's sample() without its render():
    a point light is still refused, with the message the estimator gives
    alone."""
    path = write_scene(tmp_path, lights=SKY + POINT, params=direct_params(name))
    err = refusal(lambda: render_wrapped(path, name))
    assert err is not None and "delta emitter 'key_light'" in str(err), err


def test_the_moment_test_sees_a_missing_check(llvm, tmp_path, monkeypatch):
    """Negative control: without the check in sample(), the same render
    returns an image, silently biased (what happened before)."""
    # (the class registered now: a variant switch re-imports the plugin modules)
    registered = type(renders.make_integrator("cosine_hemisphere"))
    monkeypatch.setattr(registered, "check_wrapped", lambda self, scene: None)
    path = write_scene(tmp_path, lights=SKY + POINT)
    assert refusal(lambda: render_wrapped(path, "cosine_hemisphere")) is None


def test_allow_unreachable_nested_in_moment_renders_and_records(llvm):
    """With allow_unreachable, nested in moment: the image renders and the
    nested estimator records what it lacks, as alone."""
    inner = renders.make_integrator("cosine_hemisphere", {"allow_unreachable": True})
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "constant"},
        "key_light": {"type": "point", "position": [2, 3, 2]},
        "ball": {"type": "sphere"},
        "integrator": {"type": "moment", "inner": inner},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4,
                                                   "height": 4}}})
    image = mi.render(scene, spp=2)
    assert np.isfinite(np.array(image)).all()
    assert [p.kind for p in inner.unreachable] == ["delta_emitter"]


def test_refusal_holds_nested_in_aov(llvm):
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "constant"},
        "key_light": {"type": "point", "position": [2, 3, 2]},
        "ball": {"type": "sphere"},
        "integrator": {"type": "aov", "aovs": "nn:sh_normal",
                       "inner": {"type": "cosine_hemisphere"}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4,
                                                   "height": 4}}})
    err = refusal(lambda: mi.render(scene, spp=2))
    assert err is not None and "delta emitter 'key_light'" in str(err)


def test_refusal_holds_in_a_users_own_wrapper(llvm):
    """A wrapper written in Python, as a user would, that calls the nested
    integrator's sample() and halves it."""
    class Half(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            self.inner = props["inner"]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            L, valid, aovs = self.inner.sample(scene, sampler, ray, medium, active)
            return 0.5 * L, valid, aovs

    mi.register_integrator("half_wrapper_test", lambda props: Half(props))
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "constant"},
        "key_light": {"type": "point", "position": [2, 3, 2]},
        "ball": {"type": "sphere"},
        "integrator": {"type": "half_wrapper_test", "inner": {"type": "uniform_hemisphere"}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4,
                                                   "height": 4}}})
    err = refusal(lambda: mi.render(scene, spp=2))
    assert err is not None and "uniform_hemisphere" in str(err)


@pytest.mark.parametrize("variant_name", ["scalar_rgb", "llvm_ad_spectral"])
def test_refusal_in_moment_in_other_variants(use_variant, tmp_path, variant_name):
    """scalar_rgb calls sample() once per sample: the check runs once per
    scene; a spectral variant reads the spectra as spectra."""
    use_variant(variant_name)
    path = write_scene(tmp_path, lights=SKY + POINT)
    err = refusal(lambda: render_wrapped(path, "cosine_hemisphere", res=2, spp=1))
    assert err is not None and "delta emitter 'key_light'" in str(err)


def test_bayesian_fits_its_length_scale_nested_in_moment(llvm, tmp_path):
    """The scene check also fits bayesian_hemisphere's length scale to the
    scene's map: nested in moment it gets the one it gets alone."""
    nested = renders.make_integrator("bayesian_hemisphere", {"max_depth": 2})
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "envmap", "filename": str(_gradient(tmp_path))},
        "ball": {"type": "sphere"},
        "integrator": {"type": "moment", "inner": nested},
        "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4,
                                                    "height": 4}}})
    mi.render(scene, spp=1)
    alone = renders.make_integrator("bayesian_hemisphere", {"max_depth": 2})
    alone.check_scene(scene)
    assert nested.source == alone.source != "given"
    assert nested.length_scale == alone.length_scale


def _gradient(tmp_path):
    h, w = 16, 32
    rows = np.linspace(2.0, 0.2, h, dtype=np.float32)[:, None, None]
    image = np.broadcast_to(rows, (h, w, 3)).copy()
    path = tmp_path / "gradient.exr"
    mi.Bitmap(image).write(str(path))
    return path
