"""The scene set: every XML file in scenes/ and what its header declares.

Each scene opens with a comment that says what it tests and lists, on lines
``Estimators: ...`` and (optionally) ``Refused by: ...``, the integrators it is
meant for and those that must refuse it. This module reads those lines so that
tests and sweeps need no second list.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

SCENES_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          "scenes")


@dataclass(frozen=True)
class SceneInfo:
    name: str
    path: str
    summary: str                                  # first paragraph of the comment
    estimators: tuple[str, ...]
    refused_by: tuple[str, ...] = field(default=())


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


def _listed(header: str, label: str) -> tuple[str, ...]:
    m = re.search(rf"^\s*{label}:\s*(.+)$", header, re.M)
    return tuple(m.group(1).split()) if m else ()


def index(directory: str = SCENES_DIR) -> dict[str, SceneInfo]:
    """Scene name → :class:`SceneInfo`, for every ``*.xml`` in ``directory``."""
    out = {}
    for file in sorted(os.listdir(directory)):
        if not file.endswith(".xml"):
            continue
        path = os.path.join(directory, file)
        header = _header(path)
        paragraph = header.strip().split("\n\n")[0]
        lines = [" ".join(l.strip() for l in paragraph.splitlines())]
        estimators = _listed(header, "Estimators")
        if not estimators:
            raise ValueError(f"{path}: header has no 'Estimators:' line")
        out[file[:-4]] = SceneInfo(file[:-4], path, lines[0], estimators,
                                   _listed(header, "Refused by"))
    return out


def path(name: str) -> str:
    scenes = index()
    if name not in scenes:
        raise ValueError(f"unknown scene '{name}'; available: {', '.join(scenes)}")
    return scenes[name].path
