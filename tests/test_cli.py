"""`mcillum render`: outputs, metadata and exit codes."""

import subprocess
import sys

import numpy as np
import pytest

from mcillum import files
from mcillum.validation import cli

from conftest import SCENES

CORNELL = str(SCENES / "cornell_box.xml")


def test_render_writes_exr_with_metadata_and_png(llvm, tmp_path):
    out = tmp_path / "cb.exr"
    code = cli.main(["render", CORNELL, "--integrator", "cosine_hemisphere", "--spp", "4",
                     "--seed", "7", "-p", "max_depth=2", "-D", "res=12",
                     "--variant", "llvm_ad_rgb", "-o", str(out)])
    assert code == 0
    image, meta = files.read_exr(out)
    assert image.shape == (12, 12, 3) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.max() > 0
    assert meta["integrator"] == "cosine_hemisphere" and meta["params"] == "max_depth=2"
    assert meta["spp"] == 4 and meta["seed"] == 7 and meta["variant"] == "llvm_ad_rgb"
    assert meta["mitsuba_version"].startswith("3.9") and meta["drjit_version"].startswith("1.5")
    assert meta["render_seconds"] > 0
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".partial-")]


def test_render_in_scalar_variant(tmp_path):
    out = tmp_path / "s.exr"
    assert cli.main(["render", CORNELL, "-i", "uniform_hemisphere", "--spp", "2",
                     "-D", "res=3", "--variant", "scalar_rgb", "-o", str(out)]) == 0
    assert files.read_exr(out)[1]["variant"] == "scalar_rgb"


@pytest.mark.parametrize("args, message", [
    (["-i", "cosine_hemisphere", "-p", "foo=1"], "foo"),
    (["-i", "no_such_integrator"], "no_such_integrator"),
    (["-i", "cosine_hemisphere", "-p", "max_depth=-5"], "max_depth = -5 is invalid"),
])
def test_integrator_errors_are_usage_errors(llvm, tmp_path, capsys, args, message):
    out = tmp_path / "x.exr"
    with pytest.raises(SystemExit) as info:
        cli.main(["render", CORNELL, *args, "-o", str(out)])
    assert info.value.code == 2 and message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("command", [
    ["render", CORNELL, "-o", "{tmp}/x.exr", "-i"],
    ["bench", CORNELL, "--integrators"],
    ["validate", "--out", "{tmp}/out", "--cache", "{tmp}/cache", "--estimators"],
])
def test_an_unknown_integrator_exits_2_in_every_subcommand(llvm, tmp_path, capsys, command):
    args = [a.replace("{tmp}", str(tmp_path)) for a in command] + ["no_such_integrator"]
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    assert info.value.code == 2
    assert "unknown integrator 'no_such_integrator'" in capsys.readouterr().err


def test_refused_scene_exits_1_naming_the_light(llvm, tmp_path, capsys):
    out = tmp_path / "x.exr"
    code = cli.main(["render", str(SCENES / "point_light.xml"), "-i", "cosine_hemisphere",
                     "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "'key_light' (PointLight)" in err and "'path'" in err
    assert not out.exists() and not list(tmp_path.iterdir())


def test_opt_in_render_is_written_and_marked_biased(llvm, tmp_path, capsys):
    out = tmp_path / "x.exr"
    code = cli.main(["render", str(SCENES / "point_light.xml"), "-i", "cosine_hemisphere",
                     "-p", "allow_unreachable=true", "-D", "res=4", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 0 and "BIASED" in err and "'key_light'" in err
    _, meta = files.read_exr(out)
    assert "'key_light'" in meta["biased"]


@pytest.mark.parametrize("args", [
    ["render", CORNELL, "-i", "cosine_hemisphere", "-o", "x.png"],
    ["render", CORNELL, "-i", "cosine_hemisphere", "--spp", "0", "-o", "x.exr"],
    ["render", CORNELL, "-i", "cosine_hemisphere", "-p", "novalue", "-o", "x.exr"],
    ["render", CORNELL, "-i", "cosine_hemisphere", "-o", "/nonexistent/dir/x.exr"],
    ["render", CORNELL, "-o", "x.exr"],
    ["frobnicate"],
])
def test_usage_errors_exit_2(args):
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    assert info.value.code == 2


@pytest.mark.parametrize("command", [
    ["render", "{scene}", "-i", "cosine_hemisphere", "-o", "{tmp}/x.exr"],
    ["bench", "{scene}"],
    ["validate", "{scene}", "--out", "{tmp}/out"],
])
@pytest.mark.parametrize("scene, said", [
    ("{tmp}/missing.xml", "scene file not found: {tmp}/missing.xml"),
    ("{tmp}", "cannot load scene {tmp}: it is a directory; give an XML file"),
])
def test_a_scene_path_that_names_no_file_is_a_usage_error_in_every_command(
        command, scene, said, tmp_path, capsys):
    """The same mistake, the same exit code (2) and message, whichever
    subcommand is given it; nothing is written."""
    args = [a.replace("{scene}", scene).replace("{tmp}", str(tmp_path)) for a in command]
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    err = capsys.readouterr().err
    assert info.value.code == 2 and said.replace("{tmp}", str(tmp_path)) in err, err
    assert f"mcillum {command[0]}: error:" in err and "Traceback" not in err
    assert not any(tmp_path.iterdir())


def test_console_script_is_installed():
    result = subprocess.run([sys.executable, "-m", "mcillum.validation.cli", "--help"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "render" in result.stdout


def test_committed_sky_matches_its_generator():
    import os

    from mcillum.envmaps import __main__ as generated

    here = os.path.dirname(generated.__file__)
    for name, make in generated.COMMITTED.items():
        stored, _ = files.read_exr(os.path.join(here, name))
        np.testing.assert_array_equal(stored, make())


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 1), (5, 7, 3), (5, 7, 4)])
def test_exr_layers_round_trip_bit_for_bit_with_only_their_own_channels(tmp_path, shape):
    """Every channel group comes back bit for bit, and the file holds exactly
    its channels: one channel given as (H, W, 1) once came out as three,
    two of them read past the array's end (different on every write)."""
    import OpenEXR
    rng = np.random.default_rng(3)
    image, layer = (rng.random(shape, dtype=np.float32) for _ in range(2))
    path = files.write_exr(tmp_path / "x.exr", image, {"k": 1}, layers={"p": layer})
    for name, want in (("", image), ("p", layer)):
        got, meta = files.read_exr(path, name)
        assert meta == {"k": 1}
        assert np.array_equal(got, want.reshape(*shape[:2], -1))
    with OpenEXR.File(path, separate_channels=True) as f:
        stored = sorted(f.channels())
    channels = 1 if len(shape) == 2 else shape[2]
    assert len(stored) == 2 * channels, stored


def test_validate_sets_the_variant_and_imports_plugins_once(llvm, tmp_path, monkeypatch,
                                                            capsys):
    """The CLI sets the variant and imports the plugins (it checks the
    estimators' names with them), and the pipeline takes them as set: a
    second set-up would import each plugin again."""
    from user_code import MY_INTEGRATOR

    from mcillum import plugins
    from mcillum.validation import pipeline
    from mcillum.validation.run import renders

    plugin = tmp_path / "mine.py"
    plugin.write_text(MY_INTEGRATOR)
    calls = {"variant": 0, "plugin": 0}

    def counted(key, real):
        def call(*args, **kwargs):
            calls[key] += 1
            return real(*args, **kwargs)
        return call

    def stop(*args, **kwargs):
        raise RuntimeError("reached the renders")

    monkeypatch.setattr(renders, "set_variant", counted("variant", renders.set_variant))
    monkeypatch.setattr(plugins, "load", counted("plugin", plugins.load))
    monkeypatch.setattr(pipeline, "start_executor", stop)
    code = cli.main(["validate", "--plugin", str(plugin), "--estimators", "my_direct",
                     "--scenes", "cornell_box", "--out", str(tmp_path / "out")])
    assert code == cli.EXIT_FAILED and "reached the renders" in capsys.readouterr().err
    assert calls == {"variant": 1, "plugin": 1}
