"""Profiles as data (validation/plan/profile_files.py): the bundled TOML files
read into what profiles.QUICK and FULL hold, a user's file has its paths made
absolute, and every kind of mistake in a file is a UsageError that names the
file and the key. No renders: every test only reads files."""

from __future__ import annotations

import dataclasses
import json
import os

import pytest
import tomllib
from mcillum.validation.plan import profile_files, profiles
from mcillum.validation.plan.plans import Sequential
from mcillum.validation.plan.profiles import (
    Display,
    FailureCase,
    Profile,
    SceneRun,
    UserScenes,
)

from mcillum.errors import UsageError

# ------------------------------ The bundled files -----------------------------------


def bundled_path(name: str) -> str:
    return os.path.join(os.path.dirname(profile_files.__file__), f"{name}.toml")


def test_the_bundled_profiles_are_the_files():
    assert profile_files.BUNDLED == ("budgets", "full", "quick")
    assert sorted(profiles.PROFILES) == ["budgets", "full", "quick"]
    for name, profile in profiles.PROFILES.items():
        assert profile.name == name                    # the file's name is its profile's
        assert profile.source == bundled_path(name)
        assert profile_files.bundled(name) == profile
        assert profile_files.resolve(name) == profile
    assert profiles.QUICK is profiles.PROFILES["quick"]
    assert profiles.FULL is profiles.PROFILES["full"]


def _as_read(value):
    """A raw TOML value as a profile holds it: arrays as tuples."""
    return tuple(value) if isinstance(value, list) else value


@pytest.mark.parametrize("name", ["quick", "full"])
def test_every_field_of_a_bundled_profile_is_what_its_file_says(name):
    """Field by field against the raw TOML (tomllib alone): a key the reader
    dropped, misplaced or defaulted wrongly shows here."""
    with open(bundled_path(name), "rb") as f:
        raw = tomllib.load(f)
    profile = profiles.PROFILES[name]
    default = Display(**{k: _as_read(v) for k, v in raw["display"].items()})
    for key, value in raw.items():
        if key not in ("display", "user_scenes", "scenes", "failures", "sequential"):
            assert getattr(profile, key) == _as_read(value), key
    assert profile.sequential == Sequential(**raw["sequential"])
    assert profile.estimators is None and profile.plugins == ()
    assert profile.user_scenes == UserScenes(
        display=default, **{k: _as_read(v) for k, v in raw["user_scenes"].items()})
    assert len(profile.runs) == len(raw["scenes"])
    for run, entry in zip(profile.runs, raw["scenes"]):
        fields = {k: _as_read(v) for k, v in entry.items()}
        if isinstance(fields.get("display"), dict):      # its own keys over [display]'s
            fields["display"] = dataclasses.replace(
                default, **{k: _as_read(v) for k, v in fields["display"].items()})
        assert run == SceneRun(**{"display": default, **fields}), entry
    assert len(profile.failures) == len(raw["failures"])
    for case, entry in zip(profile.failures, raw["failures"]):
        fields = {k: _as_read(v) for k, v in entry.items() if k != "sweep"}
        sweep = entry.get("sweep")
        if sweep is not None:
            fields["sweep"] = (sweep["parameter"], tuple(sweep["values"]))
        assert case == FailureCase(**fields), entry


@pytest.mark.parametrize("name", ["quick", "full"])
def test_the_geometry_cases_are_the_geometry_scenes(name):
    cases = [c.scene for c in profiles.PROFILES[name].failures if c.group == "geometry"]
    assert tuple(cases) == profiles.GEOMETRY


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, str)):
        return json.dumps(value)                   # TOML's numbers and basic strings
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    if dataclasses.is_dataclass(value):
        return _toml(dataclasses.asdict(value))
    assert value is None
    return "false"                                 # display = false: none


def dump(profile: Profile) -> str:
    """``profile`` as a file that spells out every field (each run's display
    inline): the reader must bring every one of them back."""
    top = {f.name: getattr(profile, f.name) for f in dataclasses.fields(Profile)
           if f.name not in ("runs", "failures", "user_scenes", "source")}
    lines = [f"{k} = {_toml(v)}" for k, v in top.items() if v not in (None, ())]
    if profile.user_scenes is not None:
        lines += ["[user_scenes]", *(f"{k} = {_toml(v)}" for k, v in
                                     dataclasses.asdict(profile.user_scenes).items())]
    for run in profile.runs:
        lines += ["[[scenes]]", *(f"{k} = {_toml(getattr(run, k))}" for k in
                                  ("scene", "res", "ladder", "renders", "max_depth",
                                   "defines", "display", "learning"))]
        lines += [f"label = {_toml(run.label)}"] if run.label else []
    for case in profile.failures:
        lines += ["[[failures]]", *(f"{k} = {_toml(getattr(case, k))}" for k in
                                    ("group", "scene", "res", "spp", "seeds", "defines",
                                     "max_depth"))]
        lines += [f"label = {_toml(case.label)}"] if case.label else []
        if case.sweep:
            lines.append(f"sweep = {{parameter = {_toml(case.sweep[0])}, "
                         f"values = {_toml(case.sweep[1])}}}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("name", ["quick", "full"])
def test_a_bundled_profile_round_trips_through_a_file(name, tmp_path):
    profile = dataclasses.replace(profiles.PROFILES[name], estimators=("path", "cosine"),
                                  plugins=("some.module",), reference_fraction=0.05)
    path = tmp_path / f"{name}.toml"
    path.write_text(dump(profile), encoding="utf-8")
    assert profile_files.read(path) == dataclasses.replace(profile, source=str(path))


# --------------------------------- A user's file ------------------------------------

USER = """
name = "mine"
reference_max_seconds = 5          # an integer where a float is meant: fine
estimators = ["path", "cosine"]
plugins = ["plugins/mine.py", "mymodule.plugins", "extra.py", "/opt/abs.py"]
scene_files = ["../shared/room.xml", "kitchen.xml"]

[display]
res = 64

[user_scenes]
res = 16
ladder = [4, 16]
renders = 4

[[scenes]]
scene = "furnace_sphere"
res = 8
ladder = [4, 16]
renders = 4
display = false

[[scenes]]
scene = "cornell_box"
res = 8
ladder = [32, 128]
renders = 16
max_depth = 3
defines = { envmap = "sg", radius = 0.5 }
label = "cornell_deep"
display = { res = 32, path_spp = [2, 4], renders = 2 }

[[failures]]
group = "glossy"
scene = "sub/glossy.xml"
res = 8
spp = 16
seeds = 8
sweep = { parameter = "alpha", values = [0.5, 0.1] }
"""


def test_a_users_file_has_its_paths_made_absolute(tmp_path, monkeypatch):
    folder = tmp_path / "profiles"
    folder.mkdir()
    (folder / "mine.toml").write_text(USER, encoding="utf-8")
    monkeypatch.chdir(tmp_path)                    # a path relative to the working folder
    profile = profile_files.resolve("profiles/mine.toml")
    assert profile.source == str(folder / "mine.toml")
    assert profile.name == "mine" and profile.estimators == ("path", "cosine")
    assert profile.reference_max_seconds == 5.0
    assert profile.reference_max_spp == Profile.reference_max_spp    # the default
    assert profile.plugins == (str(folder / "plugins" / "mine.py"), "mymodule.plugins",
                               str(folder / "extra.py"), "/opt/abs.py")
    assert profile.scene_files == (str(tmp_path / "shared" / "room.xml"),
                                   str(folder / "kitchen.xml"))
    furnace, cornell = profile.runs
    assert furnace.scene == "furnace_sphere" and furnace.display is None
    assert cornell == SceneRun(scene="cornell_box", res=8, ladder=(32, 128), renders=16,
                               max_depth=3, defines={"envmap": "sg", "radius": 0.5},
                               label="cornell_deep",
                               display=Display(res=32, path_spp=(2, 4), renders=2))
    assert profile.user_scenes == UserScenes(res=16, ladder=(4, 16), renders=4,
                                             display=Display(res=64))
    (case,) = profile.failures
    assert case.scene == str(folder / "sub" / "glossy.xml")
    assert case.id == "failures.glossy.glossy"      # a file's stem names it, not its path
    assert case.sweep == ("alpha", (0.5, 0.1))
    assert profile_files.read(folder / "mine.toml") == profile


def test_a_scenes_display_table_takes_what_it_leaves_out_from_the_profiles(tmp_path):
    """``display = {res = 64}`` changes the resolution only: the budgets,
    renders and pilot are the profile's [display]'s (the quick profile's
    cap_plane relies on it); without a [display], Display's defaults."""
    path = tmp_path / "m.toml"
    path.write_text('name = "m"\n[display]\nres = 128\npath_spp = [4, 16]\nrenders = 3\n'
                    'repeats = 2\n[user_scenes]\nres = 16\nladder = [4]\nrenders = 2\n'
                    'display = { renders = 5, res = 32 }\n'
                    + scene(extra="display = { res = 64 }") + scene("cap_plane")
                    + scene("sky_sphere", extra="display = false"))
    own, inherited, none = profile_files.read(path).runs
    assert own.display == Display(res=64, path_spp=(4, 16), renders=3, repeats=2)
    assert inherited.display == Display(res=128, path_spp=(4, 16), renders=3, repeats=2)
    assert none.display is None
    assert profile_files.read(path).user_scenes.display == Display(
        res=32, path_spp=(4, 16), renders=5, repeats=2)
    path.write_text('name = "m"\n' + scene(extra="display = { res = 64 }"))
    assert profile_files.read(path).runs[0].display == Display(res=64)


def test_a_scene_file_belongs_in_scene_files_and_needs_user_scenes(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[[scenes]]\nscene = "room.xml"\nres = 8\nladder = [4]\n'
                   'renders = 2\n')
    with pytest.raises(UsageError, match=r"bad.toml: scenes\[0\].scene: 'room.xml' is a file: "
                                         r"a scene file goes in scene_files"):
        profile_files.read(bad)
    bad.write_text('name = "x"\nscene_files = ["room.xml"]\n')
    with pytest.raises(UsageError, match=r"bad.toml: scene_files needs a \[user_scenes\]"):
        profile_files.read(bad)


def test_an_unknown_profile_name_lists_the_bundled_ones():
    with pytest.raises(UsageError) as err:
        profile_files.resolve("quik")
    assert "unknown profile 'quik'" in str(err.value)
    assert "full, quick" in str(err.value) and "path to a .toml file" in str(err.value)
    with pytest.raises(UsageError, match="unknown profile 'quik'"):
        profile_files.bundled("quik")


def test_a_missing_file_is_named(tmp_path):
    path = tmp_path / "nope.toml"
    with pytest.raises(UsageError, match="nope.toml: no such profile file"):
        profile_files.resolve(str(path))


# ------------------------------ Mistakes in a file ----------------------------------

def scene(name="cornell_box", ladder="[4, 16]", extra=""):
    return f'[[scenes]]\nscene = "{name}"\nres = 8\nladder = {ladder}\nrenders = 4\n{extra}\n'


FAILURE = '[[failures]]\ngroup = "heavy_tail"\nscene = "sun_sky"\nres = 8\nspp = 16\nseeds = 8\n'

MISTAKES = {
    "unknown key": (
        'name = "m"\n' + scene() + scene("sky_sphere", extra="ladders = [4]"),
        ("unknown key 'ladders' in scenes[1] (known: scene, res, ladder, renders, "
         "max_depth, defines, label, display, learning)")),
    "unknown top-level key": (
        'name = "m"\nreference_max_sp = 4\n' + scene(),
        "unknown key 'reference_max_sp' at the top level (known: name, "),
    "wrong type": (
        'name = "m"\n' + scene().replace("res = 8", 'res = "8"'),
        "scenes[0].res: must be an integer ≥ 1, got '8' (a string)"),
    "wrong type in a nested table": (
        'name = "m"\n[display]\nres = 128\npath_spp = 8\n' + scene(),
        "display.path_spp: must be an array of integers ≥ 1, got 8 (an integer)"),
    "a boolean for a depth": (
        'name = "m"\n' + scene(extra="max_depth = true"),
        "scenes[0].max_depth: must be an integer ≥ -1 (-1: unbounded), got true (a boolean)"),
    "missing required key": (
        'name = "m"\n' + FAILURE.replace("seeds = 8\n", ""),
        "missing required key 'seeds' in failures[0]"),
    "missing name": (
        scene(),
        "missing required key 'name' at the top level"),
    "missing key of a sweep": (
        'name = "m"\n' + FAILURE + 'sweep = { parameter = "alpha" }\n',
        "missing required key 'values' in failures[0].sweep"),
    "bad group": (
        'name = "m"\n' + FAILURE.replace("heavy_tail", "heavy"),
        ("failures[0].group: 'heavy' is not one of heavy_tail, unreachable, geometry, "
         "numerical, glossy")),
    "non-increasing ladder": (
        'name = "m"\n' + scene() + scene("sky_sphere") + scene("cap_plane", "[16, 4]"),
        "scenes[2].ladder: must increase, got [16, 4]"),
    "a run twice without a label": (
        'name = "m"\n' + scene() + scene(),
        "scenes[1]: 'cornell_box' is already scenes[0]; give one of them its own label"),
    "a display that is neither": (
        'name = "m"\n' + scene(extra="display = true"),
        "scenes[0].display: must be a table or false, got true (a boolean)"),
    "a learning flag that is a string": (
        'name = "m"\n' + scene(extra='learning = "yes"'),
        "scenes[0].learning: must be true or false, got 'yes' (a string)"),
    "a sequential budget that is not positive": (
        'name = "m"\n[sequential]\ncase_budget = 0\n' + scene(),
        "sequential.case_budget: must be"),
    "an unknown key of [sequential]": (
        'name = "m"\n[sequential]\nepsilon = 0.01\n' + scene(),
        "unknown key 'epsilon' in sequential"),
}


@pytest.mark.parametrize("kind", MISTAKES)
def test_a_mistake_names_the_file_and_the_key(kind, tmp_path):
    text, expected = MISTAKES[kind]
    path = tmp_path / "my.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(UsageError) as err:
        profile_files.read(str(path))
    assert str(err.value).startswith(f"{path}: {expected}"), str(err.value)
    assert err.value.usage                         # exit code 2 in the CLI


def test_a_toml_syntax_error_names_the_file_and_line(tmp_path):
    path = tmp_path / "my.toml"
    path.write_text('name = "m"\n\nreference_max_spp = = 4\n' + scene(), encoding="utf-8")
    with pytest.raises(UsageError) as err:
        profile_files.resolve(str(path))
    message = str(err.value)
    assert message.startswith(f"{path}: line 3, column "), message
    assert "not valid TOML" in message


def test_a_bundled_name_resolves_to_the_profile_the_run_holds(monkeypatch, tmp_path):
    """`--profile quick` is profiles.PROFILES["quick"] (read once; a test or
    a driver may replace it), a path is read as a file."""
    tiny = dataclasses.replace(profiles.QUICK, reference_max_seconds=1.0)
    monkeypatch.setitem(profiles.PROFILES, "quick", tiny)
    assert profiles.resolve("quick") is tiny
    (tmp_path / "mine.toml").write_text('name = "mine"\n')
    assert profiles.resolve(str(tmp_path / "mine.toml")).name == "mine"
