"""Profiles as data: the TOML files that hold a profile's records
(plans.py). The bundled profiles (quick.toml, full.toml) ship beside this
module; a user's file is read the same way (:func:`resolve`).

The format (quick.toml is a worked example; SCHEMA lists every key)::

    name = "mine"                   # Profile's settings at the top level
    estimators = ["path", "cosine"] # optional: default every registered one
    plugins = ["my_plugins.py"]     # optional: modules, or files
    [display]                       # the display stage of every scene run
    res = 128
    axis = [0.1, 1, 10, 60]         # optional: the budget axis (stages/budget_axis.py)
    [user_scenes]                   # a scene given by path; display: [display]
    res = 16
    ladder = [4, 16, 64, 256]
    renders = 8
    [[scenes]]                      # one per scene comparison
    scene = "cornell_box"           # a bundled scene's name
    res = 8
    ladder = [32, 128, 512, 2048]
    renders = 16
    display = false                 # none; or {res = 64}: res (always) and the
                                    # keys given, the rest from [display]
    learning = true                 # optional: the learning stage (stages/learning.py)
    [[failures]]                    # one per failure case; for a glossy one:
    sweep = {parameter = "alpha", values = [0.5, 0.1, 0.02]}

Paths (a scene with '/' or ending in .xml, a plugin with '/' or ending in
.py) are relative to the profile file's folder; scene files go in
``scene_files = [...]`` and are compared by ``[user_scenes]``. Why TOML:
``tomllib`` is in the standard library.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import re
import tomllib

from mcillum import files
from mcillum.errors import UsageError

from .plans import Display, FailureCase, Profile, SceneRun, Sequential, UserScenes


# ------------------------------------ The files -------------------------------------

#: The folder of the bundled profile files, and their names (without .toml).
HERE = os.path.dirname(os.path.abspath(__file__))
BUNDLED = tuple(sorted(f[:-5] for f in os.listdir(HERE) if f.endswith(".toml")))

#: The groups a failure case may belong to (stages/cases.py runs each).
FAILURE_GROUPS = ("heavy_tail", "unreachable", "geometry", "numerical", "glossy")

#: What each table of a profile file may hold: key → (kind, required); the
#: kinds are _PLAIN's and those _value() reads as tables.
SCHEMA = {
    "profile": {
        "name": ("text", True), "reference_fraction": ("positive", False),
        "display_reference_fraction": ("positive", False),
        "reference_spp_per_pass": ("count", False), "reference_max_spp": ("count", False),
        "reference_max_seconds": ("positive", False), "estimators": ("names", False),
        "plugins": ("names", False), "scene_files": ("names", False),
        "display": ("display", False),
        "user_scenes": ("user_scenes", False), "scenes": ("scenes", False),
        "failures": ("failures", False), "sequential": ("sequential", False),
    },
    "sequential": {"scene_budget": ("positive", False), "case_budget": ("positive", False),
                   "scene_epsilon": ("positive", False), "case_epsilon": ("positive", False)},
    "display": {"res": ("count", True), "path_spp": ("ladder", False),
                "renders": ("count", False), "repeats": ("count", False),
                "axis": ("seconds", False), "axis_renders": ("spread", False),
                "axis_model_above": ("positive", False), "axis_measured": ("names", False)},
    "user_scenes": {"res": ("count", True), "ladder": ("ladder", True),
                    "renders": ("count", True), "display": ("display", False),
                    "learning": ("flag", False)},
    "scenes": {"scene": ("text", True), "res": ("count", True), "ladder": ("ladder", True),
               "renders": ("count", True), "max_depth": ("depth", False),
               "defines": ("defines", False), "label": ("text", False),
               "display": ("display", False), "learning": ("flag", False)},
    "failures": {"group": ("group", True), "scene": ("text", True), "res": ("count", True),
                 "spp": ("count", True), "seeds": ("count", True),
                 "defines": ("defines", False), "label": ("text", False),
                 "max_depth": ("depth", False), "sweep": ("sweep", False)},
    "sweep": {"parameter": ("text", True), "values": ("numbers", True)},
}


class _Invalid(Exception):
    """What is wrong, from the key path on (the file's name is added)."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)      # TOML true is no count


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _array(v, test) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(test(x) for x in v)


#: The plain kinds of value: (test, what the value must be).
_PLAIN = {
    "text": (lambda v: isinstance(v, str) and v != "", "a non-empty string"),
    "count": (lambda v: _is_int(v) and v >= 1, "an integer ≥ 1"),
    "depth": (lambda v: _is_int(v) and v >= -1, "an integer ≥ -1 (-1: unbounded)"),
    "positive": (lambda v: _is_number(v) and v > 0, "a number > 0"),
    "ladder": (lambda v: _array(v, lambda x: _is_int(x) and x >= 1),
               "an array of integers ≥ 1"),
    "names": (lambda v: _array(v, lambda x: isinstance(x, str) and x != ""),
              "an array of non-empty strings (leave the key out for the default)"),
    "numbers": (lambda v: _array(v, _is_number), "a non-empty array of numbers"),
    "group": (lambda v: v in FAILURE_GROUPS, "one of " + ", ".join(FAILURE_GROUPS)),
    "flag": (lambda v: isinstance(v, bool), "true or false"),
    "seconds": (lambda v: v == [] or _array(v, lambda x: _is_number(x) and x > 0),
                "an array of numbers > 0 (seconds; [] for none)"),
    "spread": (lambda v: _is_int(v) and v >= 2, "an integer ≥ 2 (a spread needs two renders)"),
}


def _show(v) -> str:
    """A value as the file wrote it, with its TOML type."""
    kind = {bool: "a boolean", str: "a string", int: "an integer", float: "a number",
            list: "an array", dict: "a table"}.get(type(v), type(v).__name__)
    return f"{str(v).lower() if isinstance(v, bool) else repr(v)} ({kind})"


def _value(kind: str, v, where: str):
    """``v`` checked as a ``kind`` and converted (arrays to tuples)."""
    if kind in _PLAIN:
        test, what = _PLAIN[kind]
        if not test(v):
            raise _Invalid(f"{where}: {v!r} is not {what}" if kind == "group" else
                           f"{where}: must be {what}, got {_show(v)}")
        if kind in ("ladder", "seconds") and any(b <= a for a, b in itertools.pairwise(v)):
            raise _Invalid(f"{where}: must increase, got {v}")
        if kind == "seconds":
            return tuple(float(x) for x in v)
        return float(v) if kind == "positive" else tuple(v) if isinstance(v, list) else v
    if kind == "display":
        if v is False:                             # no display stage
            return None
        if not isinstance(v, dict):
            raise _Invalid(f"{where}: must be a table or false, got {_show(v)}")
        return _table(v, "display", where)         # (a Display in read(): _display)
    if kind == "defines":
        for k, x in _table(v, None, where).items():
            if isinstance(x, (list, dict)):
                raise _Invalid(f"{where}.{k}: must be a string, number or boolean, "
                               f"got {_show(x)}")
        return dict(v)
    if kind == "sweep":
        t = _table(v, "sweep", where)
        return (t["parameter"], t["values"])
    if kind == "sequential":
        return Sequential(**_table(v, "sequential", where))
    if kind == "user_scenes":                      # its display defaults in read()
        return _table(v, "user_scenes", where)
    if not _array(v, lambda x: isinstance(x, dict)):            # scenes, failures
        raise _Invalid(f"{where}: must be an array of tables ([[{where}]]), got {_show(v)}")
    return [_table(x, kind, f"{where}[{i}]") for i, x in enumerate(v)]


def _table(data, table: str | None, where: str) -> dict:
    """``data`` checked against SCHEMA[table] (None: any keys), each value
    converted by its kind; ``where`` is its key path ("" at the top level)."""
    if not isinstance(data, dict):
        raise _Invalid(f"{where}: must be a table, got {_show(data)}")
    if table is None:
        return data
    schema = SCHEMA[table]
    place = f"in {where}" if where else "at the top level"
    for key in data:
        if key not in schema:
            raise _Invalid(f"unknown key '{key}' {place} (known: {', '.join(schema)})")
    for key, (_, required) in schema.items():
        if required and key not in data:
            raise _Invalid(f"missing required key '{key}' {place}")
    return {k: _value(schema[k][0], v, f"{where}.{k}" if where else k)
            for k, v in data.items()}


def _absolute(entry: str, folder: str) -> str:
    """A file's path in a profile file, made absolute against its ``folder``."""
    return os.path.normpath(os.path.join(folder, os.path.expanduser(entry)))


def _located(entry: str, folder: str, suffix: str) -> str:
    """``entry`` made absolute against ``folder`` where it is a file's path
    (files.names_a_file); a name stays a name."""
    return _absolute(entry, folder) if files.names_a_file(entry, suffix) else entry


def _case_scene(entry: dict, folder: str) -> dict:
    """A failure case's table with its scene made absolute where it is a
    file, labelled by the file's stem unless it has a label: its id names
    checks and folders of the run directory, where a path does not belong."""
    scene = _located(entry["scene"], folder, ".xml")
    if scene == entry["scene"] or entry.get("label"):
        return {**entry, "scene": scene}
    return {**entry, "scene": scene, "label": os.path.splitext(os.path.basename(scene))[0]}


def _unique(items, where: str) -> None:
    seen = {}
    for i, item in enumerate(items):
        if item.id in seen:
            raise _Invalid(f"{where}[{i}]: '{item.id}' is already {where}[{seen[item.id]}]; "
                           f"give one of them its own label")
        seen[item.id] = i


def _load(path: str) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise UsageError(f"{path}: no such profile file") from None
    except OSError as err:
        raise UsageError(f"{path}: cannot be read ({err.strerror})") from None
    except UnicodeDecodeError as err:
        raise UsageError(f"{path}: not UTF-8 text ({err.reason})") from None
    except tomllib.TOMLDecodeError as err:
        m = re.fullmatch(r"(.*) \(at line (\d+), column (\d+)\)", str(err), re.DOTALL)
        where = f"line {m[2]}, column {m[3]}: " if m else ""
        raise UsageError(f"{path}: {where}not valid TOML: {m[1] if m else err}") from None


def read(path) -> Profile:
    """The profile in the TOML file ``path``, with ``source`` its absolute
    path and the scenes and plugins given as paths made absolute (relative
    to the file's folder). Raises UsageError, naming the file and the key,
    for a file that cannot be read, is not TOML or breaks :data:`SCHEMA`."""
    name = os.fspath(path)
    source = os.path.abspath(name)
    folder = os.path.dirname(source)
    try:
        top = _table(_load(name), "profile", "")
        display = _display(top, None)
        user = top.pop("user_scenes", None)
        entries = top.pop("scenes", [])
        for i, e in enumerate(entries):
            if _located(e["scene"], folder, ".xml") != e["scene"]:
                raise _Invalid(f"scenes[{i}].scene: '{e['scene']}' is a file: a scene file "
                               "goes in scene_files = [...], compared by [user_scenes]")
        runs = tuple(SceneRun(display=_display(e, display), **e) for e in entries)
        failures = tuple(FailureCase(**_case_scene(e, folder)) for e in top.pop("failures", []))
        _unique(runs, "scenes")
        _unique(failures, "failures")
    except _Invalid as err:
        raise UsageError(f"{name}: {err}") from None
    if "plugins" in top:
        top["plugins"] = tuple(_located(p, folder, ".py") for p in top["plugins"])
    if "scene_files" in top:
        top["scene_files"] = tuple(_absolute(p, folder) for p in top["scene_files"])
        if user is None:
            raise UsageError(f"{name}: scene_files needs a [user_scenes] table (how a scene "
                             "file is compared: res, ladder, renders)")
    return Profile(**top, runs=runs, failures=failures, source=source,
                   user_scenes=None if user is None else UserScenes(
                       display=_display(user, display), **user))


def _display(table: dict, default: Display | None) -> Display | None:
    """The display stage ``table`` holds, popped from it: none where it says
    ``false``, ``default`` where it has none; its own keys over the
    profile's [display] (``default``), the rest from there (or Display's
    defaults where the profile has none)."""
    if "display" not in table:
        return default
    own = table.pop("display")
    if own is None:
        return None
    return Display(**{**(dataclasses.asdict(default) if default else {}), **own})


def _unknown(name: str) -> UsageError:
    return UsageError(f"unknown profile '{name}': the bundled profiles are "
                      f"{', '.join(BUNDLED)}; a path to a .toml file also works")


def bundled(name: str) -> Profile:
    """The bundled profile ``name`` (one of :data:`BUNDLED`). Raises
    UsageError for another name."""
    if name not in BUNDLED:
        raise _unknown(name)
    return read(os.path.join(HERE, f"{name}.toml"))


def resolve(name_or_path) -> Profile:
    """A bundled profile by name, else the profile file at a path (one that
    ends in .toml or holds a '/'). Raises UsageError for neither, listing the
    bundled names, and as :func:`read` does for a bad file."""
    text = os.fspath(name_or_path)
    if text in BUNDLED:
        return bundled(text)
    if files.names_a_file(text, ".toml"):
        return read(text)
    raise _unknown(text)
