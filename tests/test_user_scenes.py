"""Validate your own integrator on your own scene.

A user's integrator lives in a file outside the repository (written here
into a temporary folder), registered by ``mi.register_integrator``; their
scene is written as stock Mitsuba scenes are (test_stock_scenes.py:
``<include>``, ``<path>``, textured roughness, the integrator nested in
``moment``). ``mcillum validate scene.xml --plugin my_integrator.py``
compares it with `path` with the scene's own settings, at a reduced film.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import mitsuba as mi

from mcillum import plugins
from mcillum.errors import UsageError
from mcillum.integrators.core import registry
from mcillum.validation import cli, pipeline
from mcillum.validation.plan import profiles, scene_files, scenes, user_scenes
from mcillum.validation.run import renders

from test_stock_scenes import POINT, SKY, write_scene
from user_code import MY_BSDF_DIRECT, MY_INTEGRATOR, MY_QUADRATURE

DIRECT = '<integer name="max_depth" value="2"/>'


@pytest.fixture
def user(tmp_path):
    """(the user's integrator file, their scene file) in folders of their own."""
    plugin = tmp_path / "code" / "my_integrator.py"
    plugin.parent.mkdir()
    plugin.write_text(MY_INTEGRATOR)
    (tmp_path / "scene").mkdir()
    return str(plugin), write_scene(tmp_path / "scene", params=DIRECT)


# ------------------------------- Reading the scene -------------------------------

def test_settings_are_read_through_the_moment_wrapper(tmp_path):
    path = write_scene(tmp_path, params=DIRECT + '<boolean name="hide_emitters" value="true"/>')
    settings, wrappers = scene_files.integrator_settings(path)
    assert settings == {"max_depth": 2, "hide_emitters": True}
    assert wrappers == ["moment"]


def test_settings_take_dollar_parameters_and_a_scene_without_integrator_sets_none(tmp_path):
    path = write_scene(tmp_path, params='<integer name="max_depth" value="$depth"/>')
    text = open(path).read().replace('<default name="res"', '<default name="depth" '
                                     'value="3"/>\n    <default name="res"')
    open(path, "w").write(text)
    assert scene_files.integrator_settings(path)[0] == {"max_depth": 3}
    assert scene_files.integrator_settings(path, {"depth": 5})[0] == {"max_depth": 5}
    bare = tmp_path / "bare.xml"
    bare.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    assert scene_files.integrator_settings(str(bare)) == ({}, [])


def test_film_is_read_and_reduced_with_includes_inlined(llvm, tmp_path):
    """The sensor may sit in an included file; the reduced film keeps the
    aspect, and the scene loads from the edited text with its relative
    files (a <path> folder, an OBJ mesh, a bitmap texture) found."""
    path = write_scene(tmp_path)
    sensor = open(path).read()
    start, end = sensor.index("<sensor"), sensor.index("</sensor>") + len("</sensor>")
    (tmp_path / "fragments" / "camera.xml").write_text(
        '<scene version="3.0.0">' + sensor[start:end].replace("$res", "$width", 1) + "</scene>")
    text = (sensor[:start] + '<include filename="fragments/camera.xml"/>' + sensor[end:])
    text = text.replace('<default name="res" value="8"/>',
                        '<default name="res" value="60"/><default name="width" value="80"/>')
    # a PLY mesh (written from a rectangle) beside the OBJ one, found through <path>
    ply = mi.load_dict({"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
        [0, -1.7, 0]).rotate([1, 0, 0], -90).scale(3)})
    ply.write_ply(str(tmp_path / "common" / "meshes" / "floor.ply"))
    text = text.replace("</scene>", '<shape type="ply"><string name="filename" '
                        'value="meshes/floor.ply"/></shape></scene>')
    open(path, "w").write(text)
    assert scene_files.film_size(path) == (80, 60)
    assert profiles.scaled_film((80, 60), 16) == (16, 12)
    scene = renders.load_resolved(path, {"integrator": "path"}, film=(16, 12))
    assert list(scene.sensors()[0].film().size()) == [16, 12]
    assert len(scene.shapes()) == 3
    image = renders.render(scene, renders.make_integrator("path"), 4).image
    assert image.shape[:2] == (12, 16) and image.mean() > 0


def test_a_scene_file_with_a_missing_include_says_which(tmp_path):
    path = tmp_path / "s.xml"
    path.write_text('<scene version="3.0.0"><include filename="gone.xml"/></scene>')
    with pytest.raises(scene_files.SceneFileError, match="gone.xml.*not found"):
        scene_files.film_size(str(path))


def test_the_plan_keeps_the_scene_settings_unless_the_user_overrides(tmp_path):
    path = write_scene(tmp_path, params=DIRECT)
    run, notes = user_scenes.scene_run(profiles.QUICK, path)
    assert (run.max_depth, run.res, run.film, run.own_film) == (2, 8, (8, 8), (8, 8))
    assert any("seen through moment" in n for n in notes)
    run, notes = user_scenes.scene_run(profiles.QUICK, path, settings={"max_depth": 3},
                                       defines={"res": 100}, res=10)
    assert (run.max_depth, run.film, run.display.res) == (3, (10, 10), 100)
    assert any("given by the user: max_depth 3" in n for n in notes)
    assert scenes.info(path).contains is None and not scenes.info(path).bundled


# ------------------------------ A map named by file -------------------------------

#: The sky of a stock-style scene: an included fragment whose envmap emitter
#: names its map as a file (relative: found through the scene's <path>).
SKY_FRAGMENT = ('<scene version="3.0.0"><emitter type="envmap">'
                '<string name="filename" value="textures/city.exr"/></emitter></scene>')


def write_city_scene(root) -> str:
    """A user's glossy scene (test_stock_scenes.py) lit by the city probe, a
    small sun, named as a literal file in an ``<include>``d fragment, with
    the direct-light settings. Returns the scene file's path."""
    import shutil

    from mcillum.envmaps import probes

    path = write_scene(root, lights='<include filename="fragments/sky.xml"/>', params=DIRECT)
    shutil.copy(probes.path("city"), root / "common" / "textures" / "city.exr")
    (root / "fragments" / "sky.xml").write_text(SKY_FRAGMENT)
    return path


#: The included sky's map as another $-parameter, its default in the
#: included file (the values of the file that holds the emitter name it).
SKY_PARAMETER = SKY_FRAGMENT.replace('<emitter', '<default name="sky" value="textures/city.exr"/>'
                                     '<emitter').replace('value="textures/city.exr"/></emitter>',
                                                         'value="$sky"/></emitter>')


@pytest.mark.parametrize("fragment", [SKY_FRAGMENT, SKY_PARAMETER], ids=["file", "parameter"])
def test_a_map_named_in_an_include_is_given_as_envmap(llvm, tmp_path, fragment):
    """The plan finds the file the included emitter names (through the
    scene's <path>), gives it as $envmap and says so; the loaded XML's
    emitter then takes $envmap, so another map replaces it (the sunless
    map of the sun split), and that map keys its own reference."""
    from mcillum.envmaps import sun
    from mcillum.validation.run import references
    path = write_city_scene(tmp_path)
    (tmp_path / "fragments" / "sky.xml").write_text(fragment)
    city = str(tmp_path / "common" / "textures" / "city.exr")
    found = scene_files.environment_map(path)
    assert (found.where, found.file, found.clash) == (
        str(tmp_path / "fragments" / "sky.xml"), city, False)
    run, notes = user_scenes.scene_run(profiles.QUICK, path)
    assert run.defines["envmap"] == city
    assert any("city.exr" in n and "$envmap" in n for n in notes), notes
    other = renders.resolve_defines(path, envmap="gradient")
    text, _ = scene_files.with_film(path, (8, 8), other)
    assert 'name="filename" value="$envmap"' in text
    real = renders.resolve_defines(path, **run.defines)
    suns = [sun.split(renders.environment_texels(renders.load_resolved(path, d, film=(8, 8))))
            [1]["texels"] for d in (real, other)]
    assert suns[0] > 0 and suns[1] == 0           # city's sun; the gradient has none
    keys = {references.cache_key(path, d, {"max_depth": 2}, mi.variant(), film=(8, 8))
            for d in (real, other)}
    assert len(keys) == 2


def test_a_scene_that_uses_envmap_itself_keeps_its_map_and_names_why(tmp_path):
    """A scene that declares $envmap (here for nothing the emitter uses)
    cannot be given its map as $envmap: nothing is rewritten, and the
    sentence the sun split's note gives says why and what to do. A scene
    that gives its map as $envmap with a default is left to the renders."""
    path = write_city_scene(tmp_path)
    text = open(path).read().replace('<default name="res"', '<default name="envmap" '
                                     'value="unused.exr"/>\n    <default name="res"')
    open(path, "w").write(text)
    envmap, why = user_scenes.map_parameter(path)
    assert envmap is None and "rename that parameter" in why
    assert "envmap" not in user_scenes.scene_run(profiles.QUICK, path)[0].defines
    xml, _ = scene_files.with_film(path, (8, 8), {"envmap": "/elsewhere.exr"})
    assert "textures/city.exr" in xml
    (tmp_path / "fragments" / "sky.xml").write_text(
        SKY_FRAGMENT.replace("textures/city.exr", "$envmap"))
    text = text.replace('value="unused.exr"', 'value="common/textures/city.exr"')
    open(path, "w").write(text)
    assert user_scenes.map_parameter(path) == (None, "")


# ---------------------------------- Plugins ---------------------------------------

def test_a_plugin_file_registers_its_integrators_and_their_declared_facts(llvm, user):
    plugin, _ = user
    loaded = plugins.load(plugin, mi.variant())
    assert loaded.module == "my_integrator" and len(loaded.sha256) == 64
    made, taken = renders.make_taking("my_direct", {"max_depth": 2, "hide_emitters": False})
    # (hide_emitters is read by mi.SamplingIntegrator itself)
    assert taken == {"hide_emitters": False} and made is not None
    assert registry.facts("my_direct").display_name == "my direct light"
    assert registry.facts("my_direct").colour is None         # not declared: a spare one
    assert not registry.facts("my_direct").ours


def test_a_plugin_that_fails_to_import_is_a_usage_error_naming_the_file(llvm, tmp_path):
    bad = tmp_path / "bad_plugin.py"
    bad.write_text("import mitsuba as mi\nraise RuntimeError('no GPU here')\n")
    with pytest.raises(UsageError, match=r"bad_plugin.py failed: RuntimeError: no GPU here"):
        plugins.load(str(bad), mi.variant())
    with pytest.raises(UsageError, match="no such file"):
        plugins.load(str(tmp_path / "missing.py"))
    with pytest.raises(UsageError, match="cannot import module 'no_such_module_x'"):
        plugins.load("no_such_module_x")


def test_cli_exits_2_for_a_plugin_that_fails_to_import(llvm, tmp_path, capsys, user):
    bad = tmp_path / "bad_plugin.py"
    bad.write_text("raise ImportError('needs torch')\n")
    _, scene = user
    with pytest.raises(SystemExit) as exit_:
        cli.main(["validate", scene, "--plugin", str(bad), "--out", str(tmp_path / "o")])
    assert exit_.value.code == 2
    assert "needs torch" in capsys.readouterr().err


def test_declared_reachable_kinds_must_be_known(llvm, tmp_path):
    code = tmp_path / "odd.py"
    code.write_text(textwrap.dedent('''
        import mitsuba as mi
        class Odd(mi.SamplingIntegrator):
            reachable = ("delta_emitter", "caustics")
            def sample(self, scene, sampler, ray, medium=None, active=True):
                return mi.Spectrum(0), active, []
        mi.register_integrator("odd_one", lambda props: Odd(props))
    '''))
    plugins.load(str(code), mi.variant())
    with pytest.raises(renders.IntegratorError, match="caustics; the kinds are"):
        renders.make_integrator("odd_one")


# ------------------------------- One command ----------------------------------

def run_cli(capsys, *args):
    code = cli.main(["validate", *args, "--no-speed", "-D", "res=64"])
    return code, capsys.readouterr()


def test_one_command_from_a_plugin_and_a_scene_to_a_verdict(llvm, tmp_path, capsys, user):
    """The correct integrator passes (exit 0) with JUnit and a report; the
    notes say where the settings came from and what it was not given."""
    plugin, scene = user
    out = tmp_path / "out"
    code, said = run_cli(capsys, scene, "--plugin", plugin, "--estimators", "my_direct",
                         "--out", str(out), "--junit", str(out / "junit.xml"))
    assert code == 0, said.out + said.err
    data = json.loads((out / "results.json").read_text())
    (result,) = data["scenes"]
    assert [e["name"] for e in result["estimators"]] == ["my_direct", "path"]
    assert result["estimators"][0]["params"] == {}
    assert result["estimators"][1]["params"] == {"max_depth": 2}
    notes = " | ".join(result["notes"])
    assert "seen through moment): max_depth 2" in notes
    assert "my_direct takes no max_depth" in notes
    assert data["estimator_facts"]["my_direct"]["display_name"] == "my direct light"
    assert (out / "junit.xml").exists() and (out / "report" / "index.html").exists()


def test_the_broken_twin_exits_1_naming_the_check(llvm, tmp_path, capsys, user):
    plugin, scene = user
    code, said = run_cli(capsys, scene, "--plugin", plugin, "--estimators", "my_direct_broken",
                         "--out", str(tmp_path / "out"))
    assert code == 1
    assert "scene/my_direct_broken/unbiased" in said.out


def test_a_users_quadrature_is_judged_as_ours_and_a_declared_bias_needs_one(llvm, tmp_path,
                                                                           capsys, user):
    """A user's class derived from mcillum's bayesian_hemisphere, every
    direction's weight 5 % low, goes through the quadrature stage as
    mcillum's own does (before, only registered estimators did, and its one
    check was `finite`): its bias does not go to 0, bias_shrinks fails. A
    plain integrator that declares ``unbiased = False`` has nothing to
    measure its bias against N: it is tested as unbiased, and its 5 % dark
    light samples fail that. Beside mcillum's three point sets: four need
    more of the quadrature stage's seed blocks than it had (8)."""
    _, scene = user
    plugin = tmp_path / "code" / "mine.py"
    plugin.write_text(MY_INTEGRATOR + MY_QUADRATURE)
    out = tmp_path / "out"
    # (with mcillum's three point sets: four need more seed blocks than 8)
    code, said = run_cli(capsys, scene, "--plugin", str(plugin), "--res", "8", "--out", str(out),
                         "--estimators", "my_bayes_low", "my_direct_declared_biased",
                         "fibonacci_hemisphere", "bayesian_hemisphere", "bayesian_importance")
    data = json.loads((out / "results.json").read_text())
    outcome = {c["id"].split("/", 1)[1]: c["outcome"] for c in data["checks"]}
    assert outcome["my_bayes_low/bias_shrinks"] == "fail", outcome
    assert "my_bayes_low/unbiased" not in outcome
    assert outcome["my_direct_declared_biased/unbiased"] == "fail", outcome
    for ours in ("fibonacci_hemisphere", "bayesian_importance"):
        assert outcome[f"{ours}/unbiased"] != "fail", outcome
    assert code == 1, said.out
    facts = data["estimator_facts"]
    assert not facts["my_bayes_low"]["unbiased"] and facts["my_direct_declared_biased"]["unbiased"]


def test_estimators_that_cannot_render_a_user_scene_say_why(llvm, tmp_path, capsys):
    """A point light: the hemisphere estimator is not compared, and the
    results say so; emitter sampling is, and agrees."""
    scene = write_scene(tmp_path, lights=SKY + POINT, params=DIRECT)
    code, said = run_cli(capsys, scene, "--estimators", "cosine_hemisphere",
                         "emitter_sampling", "--out", str(tmp_path / "out"))
    assert code == 0, said.out + said.err
    (result,) = json.loads((tmp_path / "out" / "results.json").read_text())["scenes"]
    assert [e["name"] for e in result["estimators"]] == ["emitter_sampling", "path"]
    assert any(n.startswith("cosine_hemisphere does not render this scene: the scene "
                            "holds delta lights") for n in result["notes"])


def test_scene_options_need_a_scene_file_and_a_missing_file_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["validate", "--max-depth", "2", "--out", str(tmp_path)])
    assert exit_.value.code == 2
    with pytest.raises(SystemExit) as exit_:
        cli.main(["validate", str(tmp_path / "nope.xml"), "--out", str(tmp_path)])
    assert exit_.value.code == 2 and "scene file not found" in capsys.readouterr().err


def test_render_and_bench_take_plugins(llvm, tmp_path, capsys, user):
    plugin, scene = user
    out = tmp_path / "r.exr"
    assert cli.main(["render", scene, "--plugin", plugin, "-i", "my_direct", "--spp", "4",
                     "-D", "integrator=path", "-o", str(out)]) == 0
    assert out.exists()
    assert cli.main(["bench", scene, "--plugin", plugin, "--integrators", "my_direct,path",
                     "--spp", "4", "--runs", "2", "-D", "integrator=path"]) == 0
    assert "my_direct" in capsys.readouterr().out


@pytest.mark.ray
@pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                    reason="Ray is not installed: pip install -e '.[ray]'")
def test_ray_imports_the_plugin_on_its_workers_and_renders_the_same(tmp_path, user):
    """The same comparison on Ray (in a subprocess, as test_ray.py says
    why): the workers import the user's file, and the statistical renders
    are bit-identical to the local run's."""
    plugin, scene = user
    for kind in ("local", "ray"):
        args = [sys.executable, "-m", "mcillum.validation.cli", "validate", scene,
                "--plugin", plugin, "--estimators", "my_direct", "--no-speed", "-D", "res=64",
                "--out", str(tmp_path / kind), "--cache", str(tmp_path / f"cache-{kind}")]
        if kind == "ray":
            args += ["--executor", "ray", "--ray-workers", "2"]
        done = subprocess.run(args, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stderr
    stacks = sorted(p.relative_to(tmp_path / "local")
                    for p in (tmp_path / "local" / "renders").rglob("*.npz"))
    assert len(stacks) >= 4                 # the ladder's rungs, both integrators in each
    for rel in stacks:
        with np.load(tmp_path / "local" / rel) as a, np.load(tmp_path / "ray" / rel) as b:
            images = [k for k in a.files if a[k].ndim >= 3]
            assert images, rel
            for k in images:
                assert np.array_equal(a[k], b[k], equal_nan=True), f"{rel} {k}"


def test_a_profile_file_names_the_plugin_the_estimators_and_the_scene(llvm, tmp_path, capsys,
                                                                      user):
    """Everything in one file of the user's: `--profile mine.toml`."""
    (tmp_path / "mine.toml").write_text(textwrap.dedent('''
        name = "mine"
        plugins = ["code/my_integrator.py"]
        estimators = ["my_direct", "path"]
        scene_files = ["scene/scene.xml"]

        [user_scenes]
        res = 12
        ladder = [4, 16, 64, 256]
        renders = 8
    '''))
    code, said = run_cli(capsys, "--profile", str(tmp_path / "mine.toml"),
                         "--out", str(tmp_path / "out"))
    assert code == 0, said.out + said.err
    data = json.loads((tmp_path / "out" / "results.json").read_text())
    assert data["profile"] == "mine" and data["failures"] == []
    (result,) = data["scenes"]
    assert result["name"] == "scene" and result["res"] == 12
    assert [e["name"] for e in result["estimators"]] == ["my_direct", "path"]


def test_validate_accepts_every_estimator_by_name_before_it_runs(llvm, tmp_path, capsys,
                                                                 monkeypatch):
    """Names are checked with each integrator's defaults: the estimators of
    N directions take no max_depth −1, and must still be accepted."""
    def stop(*args, **kwargs):
        raise RuntimeError("reached the pipeline")
    monkeypatch.setattr(pipeline, "validate", stop)
    code = cli.main(["validate", "--estimators", *registry.names(), "--out", str(tmp_path)])
    assert code == 1 and "reached the pipeline" in capsys.readouterr().err


def test_includes_are_inlined_in_order(tmp_path):
    """Two includes in a row: the second one's elements follow the first's
    (a BSDF defined in one and referenced by id in the next must stay
    defined first)."""
    (tmp_path / "a.xml").write_text('<scene version="3.0.0"><bsdf type="diffuse" id="one"/>'
                                    '<bsdf type="diffuse" id="two"/></scene>')
    (tmp_path / "b.xml").write_text('<scene version="3.0.0"><shape type="sphere">'
                                    '<ref id="one"/></shape></scene>')
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><include filename="a.xml"/>'
                     '<include filename="b.xml"/></scene>')
    root, folders = scene_files.inlined(str(scene))
    assert [c.tag for c in root] == ["bsdf", "bsdf", "shape"]
    assert folders == [str(tmp_path)]


def test_files_found_through_path_belong_to_the_scene(llvm, tmp_path):
    """A texture and a mesh found through the scene's <path> folder are the
    scene's files: they travel to Ray workers, and a changed texture makes a
    new reference cache key (the reference is rendered again)."""
    from mcillum.validation.run import references
    path = write_scene(tmp_path, params=DIRECT)
    found = scenes.referenced_files(path, {})
    assert str(tmp_path / "common" / "textures" / "roughness.exr") in found
    assert str(tmp_path / "common" / "meshes" / "tetra.obj") in found
    before = references.cache_key(path, {}, {"max_depth": 2}, mi.variant(), film=(8, 8))
    mi.Bitmap(np.full((4, 4, 1), 0.3, np.float32)).write(
        str(tmp_path / "common" / "textures" / "roughness.exr"))
    assert references.cache_key(path, {}, {"max_depth": 2}, mi.variant(),
                                film=(8, 8)) != before


# --------------------------- A scene with no signal -----------------------------

def dark_scene(folder, emitter: str = "", target: str = "0, 0, 0") -> str:
    """A stock Mitsuba scene: a sensor at z = 4 looking at ``target``, a
    diffuse sphere at the origin, and ``emitter`` (none by default)."""
    path = folder / "dark.xml"
    path.write_text(textwrap.dedent(f"""\
        <scene version="3.0.0">
            <integrator type="path"><integer name="max_depth" value="3"/></integrator>
            <sensor type="perspective">
                <float name="fov" value="40"/>
                <transform name="to_world">
                    <lookat origin="0, 0, 4" target="{target}" up="0, 1, 0"/>
                </transform>
                <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
                <film type="hdrfilm">
                    <integer name="width" value="32"/><integer name="height" value="32"/>
                </film>
            </sensor>
            <shape type="sphere"><bsdf type="diffuse"/></shape>
            {emitter}
        </scene>
        """))
    return str(path)


#: A point light between the camera and the sphere, lighting its front.
LIGHT = ('<emitter type="point"><point name="position" x="0" y="2" z="2"/>'
         '<rgb name="intensity" value="10"/></emitter>')


def test_a_scene_without_an_emitter_is_refused_with_exit_2_naming_it(llvm, tmp_path,
                                                                     capsys):
    """A sensor and a sphere, no emitter: path's reference is black, every
    check would pass against it (it did: "PASSED: pass 21 of 21"). The
    run is refused, exit 2, naming the file and what to add."""
    scene = dark_scene(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["validate", scene, "--estimators", "cosine_hemisphere", "--no-speed",
                  "--res", "8", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2, err
    assert f"{scene}: nothing to validate" in err and "black in every pixel" in err
    assert "the scene has no emitter" in err and "add an emitter" in err


def test_an_emitter_behind_a_camera_that_looks_away_is_refused(llvm, tmp_path):
    """The light and the sphere behind the camera: the scene has an emitter,
    but the image is black; compare() raises NoSignal naming the sensor's
    direction to check, and no check is reported."""
    from mcillum.errors import NoSignal
    from mcillum.testing import compare

    scene = dark_scene(tmp_path, LIGHT, target="0, 0, 8")
    with pytest.raises(NoSignal, match="its 1 emitter lights nothing the sensor sees") as err:
        compare(scene, "emitter_sampling", res=8, out_dir=tmp_path / "out",
                cache_dir=tmp_path / "cache")
    assert "lookat" in str(err.value) and str(err.value).startswith(scene)
    assert NoSignal.usage                  # (the CLI's exit 2)


def test_the_same_scene_lit_still_validates(llvm, tmp_path):
    """The negative control: the camera turned to the sphere the light
    lights; the run goes on and passes."""
    from mcillum.testing import assert_passes, compare

    c = compare(dark_scene(tmp_path, LIGHT), "emitter_sampling", res=8,
                out_dir=tmp_path / "out", cache_dir=tmp_path / "cache")
    assert c.results.scenes[0].reference.spp > 0
    assert_passes(c)


def test_a_bundled_scene_with_a_black_reference_is_an_internal_error():
    """The profile's own scenes are all lit: a black reference there is a
    bug (RuntimeError), not the user's mistake (NoSignal, exit 2)."""
    from types import SimpleNamespace

    from mcillum.errors import NoSignal
    from mcillum.validation.stages import common

    ref = SimpleNamespace(mean=np.zeros((4, 4, 3)), spp=64)
    ctx = SimpleNamespace(reference=ref, id="lone_sphere", defines={"envmap": "sg"},
                          info=SimpleNamespace(bundled=True, path="scenes/lone_sphere.xml"),
                          scene=None, max_depth=2)
    with pytest.raises(RuntimeError, match="internal error: bundled scene 'lone_sphere'"):
        common.require_signal(ctx)
    ctx.info.bundled = False
    with pytest.raises(NoSignal, match="scenes/lone_sphere.xml: nothing to validate"):
        common.require_signal(ctx)
    ref.mean[2, 3, 1] = 1e-6               # one dim pixel channel is signal
    common.require_signal(ctx)


def test_a_sun_named_by_file_in_an_include_is_split(llvm, tmp_path, capsys):
    """A user's direct light from BSDF samples only (a file outside the
    repository) on their glossy scene under the city probe, the map named
    as a file in an included fragment. Before mcillum gave such a map as
    $envmap, its sun was not split and the tail excused the twin whose
    weights are 5 % low (inconclusive here, exit 0). Now the twin fails
    without the sun, the correct one does not fail, and the notes say the
    map was given."""
    plugin = tmp_path / "code" / "my_bsdf.py"
    plugin.parent.mkdir()
    plugin.write_text(MY_BSDF_DIRECT)
    (tmp_path / "scene").mkdir()
    scene = write_city_scene(tmp_path / "scene")
    out = tmp_path / "out"
    code, said = run_cli(capsys, scene, "--plugin", str(plugin), "--out", str(out),
                         "--estimators", "my_bsdf_direct", "my_bsdf_direct_low")
    data = json.loads((out / "results.json").read_text())
    (result,) = data["scenes"]
    unbiased = {c["id"].split("/")[1]: c for c in data["checks"]
                if c["id"].endswith("/unbiased")}
    assert unbiased["my_bsdf_direct_low"]["outcome"] == "fail", unbiased
    assert unbiased["my_bsdf_direct"]["outcome"] != "fail", unbiased
    split = {e["name"]: e["unbiasedness"].get("sun") for e in result["estimators"]}
    assert split["my_bsdf_direct_low"] is not None, split
    assert split["my_bsdf_direct_low"]["sunless_outcome"] == "fail", split
    notes = " | ".join(result["notes"])
    assert "city.exr" in notes and "$envmap" in notes, notes
    assert code == 1, said.out + said.err
