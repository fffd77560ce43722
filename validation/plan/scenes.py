"""The scene set: every XML file in scenes/ and what its header declares.

Each scene opens with a comment that says what it tests (first paragraph:
``<name>: <summary>``) and, on a line ``Contains: ...``, the kinds of content
(:data:`~mcillum.integrators.core.scene_checks.KINDS`) that a continuous hemisphere
pdf cannot reach: delta lights, delta lobes, transmission. Which estimators
render a scene follows from that line and each estimator's registry facts
(``registry.facts(name).renders(info.contains)``); those that cannot must
refuse it. A scene without the line holds none of them.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

from mcillum import files
from mcillum.integrators.core.scene_checks import KINDS

#: scenes/ beside the package's subfolders (in a checkout and when installed):
#: three folders up from validation/plan/.
SCENES_DIR = os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "scenes")


@dataclass(frozen=True)
class SceneInfo:
    name: str
    path: str
    summary: str                                  # first paragraph of the comment
    #: Kinds of content a hemisphere pdf cannot reach (its ``Contains:``
    #: line); None for a user's scene, whose content is read off the loaded
    #: scene (stages/common.py).
    contains: tuple[str, ...] | None = field(default=())
    bundled: bool = True


def _header(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        text = f.read()
    m = re.search(r"<!--(.*?)-->", text, re.S)
    if not m:
        raise ValueError(f"{path}: scene has no header comment saying what it tests")
    return m.group(1)


_DEFAULT = re.compile(r'<default\s+name="([^"]+)"\s+value="([^"]*)"')


def defaults(path: str) -> dict[str, str]:
    """The ``<default name=... value=...>`` $-parameters declared in an XML file."""
    with open(path, encoding="utf-8") as f:
        return dict(_DEFAULT.findall(f.read()))


_PLACEHOLDER = re.compile(r"\$([A-Za-z_]\w*)")


def parameters(path: str, defines: dict | None = None) -> dict[str, str]:
    """The $-parameters of the XML file ``path`` as it is loaded: its
    defaults, then ``defines``, as strings."""
    return {**defaults(path), **{k: str(v) for k, v in (defines or {}).items()}}


def substitute(text: str, values: dict) -> str:
    """``text`` with each ``$name`` that ``values`` holds replaced by its
    value (others are left as they are)."""
    return _PLACEHOLDER.sub(lambda m: str(values.get(m.group(1), m.group(0))), text)


def expand(path: str, text: str, defines: dict) -> str:
    """``text`` (a scene's summary) with each ``$name`` replaced by the value
    it is rendered with: ``defines``, else the file's default. A map given as
    a file shows as its name (``sunrise``, not a cache path)."""
    values = parameters(path, defines)
    if "envmap" in values:
        values["envmap"] = os.path.splitext(os.path.basename(values["envmap"]))[0]
    return substitute(text, values)


def _contains(header: str, path: str) -> tuple[str, ...]:
    m = re.search(r"^\s*Contains:\s*(.+)$", header, re.M)
    kinds = tuple(m.group(1).split()) if m else ()
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f"{path}: 'Contains:' names {', '.join(unknown)}; the kinds are "
                         f"{', '.join(KINDS)}")
    return kinds


def index(directory: str = SCENES_DIR) -> dict[str, SceneInfo]:
    """Scene name → :class:`SceneInfo`, for every ``*.xml`` in ``directory``."""
    out = {}
    for file in sorted(os.listdir(directory)):
        if not file.endswith(".xml"):
            continue
        path = os.path.join(directory, file)
        header = _header(path)
        paragraph = header.strip().split("\n\n")[0]
        summary = " ".join(line.strip() for line in paragraph.splitlines())
        out[file[:-4]] = SceneInfo(file[:-4], path, summary, _contains(header, path))
    return out


def is_path(name: str) -> bool:
    """Does ``name`` (a command-line scene) name a file rather than a bundled
    scene? An XML file name or anything with a folder in it does."""
    return files.names_a_file(name, ".xml")


def info(name: str) -> SceneInfo:
    """The :class:`SceneInfo` of a bundled scene's name or of a scene file's
    path (a user's: its header comment, if any, is its summary; its content
    is read when it is loaded). Raises ValueError for an unknown name or a
    file that is not there."""
    if not is_path(name):
        scenes = index()
        if name not in scenes:
            raise ValueError(f"unknown scene '{name}'; available: {', '.join(scenes)} "
                             "(or give a scene file's path)")
        return scenes[name]
    full = os.path.abspath(name)
    if not os.path.isfile(full):
        raise ValueError(f"scene file not found: {name}")
    try:
        paragraph = _header(full).strip().split("\n\n")[0]
        summary = " ".join(line.strip() for line in paragraph.splitlines())
    except (ValueError, UnicodeDecodeError):
        summary = ""
    return SceneInfo(os.path.splitext(os.path.basename(full))[0], full,
                     summary or f"{os.path.basename(full)}, a scene given by path.", None,
                     bundled=False)


def path(name: str) -> str:
    scenes = index()
    if name not in scenes:
        raise ValueError(f"unknown scene '{name}'; available: {', '.join(scenes)}")
    return scenes[name].path


# ------------------------------ Referenced files --------------------------------

_FILE_REF = re.compile(r'(?:name="filename"\s+value|<include\s+filename)="([^"]*)"')
_PATH_REF = re.compile(r'<path\s+value="([^"]*)"')


def find(name: str, folders) -> str | None:
    """The file ``name`` refers to: itself if absolute, else the first of
    ``folders`` that holds it; None where none does."""
    if os.path.isabs(name):
        return name if os.path.isfile(name) else None
    return next((os.path.join(f, name) for f in folders
                 if os.path.isfile(os.path.join(f, name))), None)


def referenced_files(scene_path: str, defines: dict) -> list[str]:
    """The scene file and every file it references, recursively, after
    substituting ``$``-parameters (defaults from the file, then ``defines``).
    A relative reference is found as Mitsuba finds it: beside the file that
    makes it, else in a folder a ``<path>`` added (stock scenes keep their
    meshes and textures in a shared folder found that way). The map an
    ``envmap`` define names is one too, where the scene names another file
    in its place (a user's scene that mcillum gives its map as ``$envmap``,
    plan/scene_files.py: the sunless map must key its own reference)."""
    seen: list[str] = []

    def visit(path: str, params: dict, folders: list[str]):
        path = os.path.abspath(path)
        if path in seen:
            return
        seen.append(path)
        if not path.endswith(".xml"):
            return
        with open(path, encoding="utf-8") as f:
            text = f.read()
        local = parameters(path, params)
        here = os.path.dirname(path)
        folders = [here, *folders, *(os.path.join(here, substitute(p, local))
                                     for p in _PATH_REF.findall(text))]
        for ref in _FILE_REF.findall(text):
            target = find(substitute(ref, local), folders)
            if target is not None:
                visit(target, local, folders)

    visit(scene_path, {k: str(v) for k, v in defines.items()}, [])
    given = defines.get("envmap")
    if given is not None and os.path.isfile(str(given)) \
            and os.path.abspath(str(given)) not in seen:
        seen.append(os.path.abspath(str(given)))
    return seen
