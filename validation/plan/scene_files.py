"""A scene file written for stock Mitsuba, read as the comparison needs it.

A user's scene (``mcillum validate my_scene.xml``) carries its own
``<integrator>``, possibly wrapped (``moment``, ``aov``), its film size and
``<include>``/``<path>`` layout. The validation replaces the integrator by
each compared one and by the reference (``mi.render(..., integrator=...)``),
so what it needs from the file is:

* :func:`integrator_settings`: the settings that define the image
  (``max_depth``, ``rr_depth``, ``hide_emitters``) of the innermost
  integrator, seen through wrappers, so that every compared integrator and
  the reference render the same image;
* :func:`with_film`: the scene's XML with another film size (the small-image
  statistics run at a reduced film: plan/profiles.py, ``UserScenes``), its
  includes inlined so that a sensor in an included file is reached too, and
  the folders its relative paths resolve from.

Nothing here loads the scene; run/renders.py does.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from typing import NamedTuple

from . import scenes

#: The integrator settings that define the image, and their XML tags.
SETTINGS = {"max_depth": "integer", "rr_depth": "integer", "hide_emitters": "boolean"}

class SceneFileError(ValueError):
    """The scene file cannot be read as the comparison needs it."""


def _parse(path: str) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as err:
        raise SceneFileError(f"cannot read scene {path}: {err}: fix the XML there") from None
    except OSError as err:
        raise SceneFileError(f"cannot read scene {path}: {err.strerror}") from None


def inlined(path: str, defines: dict | None = None) -> tuple[ET.Element, list[str]]:
    """(the scene's root with every ``<include>`` replaced by the included
    file's children, recursively; the folders its relative paths resolve
    from: the scene's, each included file's, each ``<path>``'s, in order).
    ``$``-parameters in include names are replaced (defaults of each file,
    then ``defines``). Raises :class:`SceneFileError` for a file that is
    not XML or an include that is not found."""
    folders: list[str] = []

    def visit(file: str, params: dict, seen: tuple) -> ET.Element:
        file = os.path.abspath(file)
        if file in seen:
            raise SceneFileError(f"{file} includes itself (through {' > '.join(seen)})")
        root = _parse(file)
        here = os.path.dirname(file)
        if here not in folders:
            folders.append(here)
        local = scenes.parameters(file, params)
        for parent in list(root.iter()):
            for child in list(parent):
                if child.tag == "path":
                    folder = scenes.substitute(child.get("value", ""), local)
                    folder = folder if os.path.isabs(folder) else os.path.join(here, folder)
                    if folder not in folders:
                        folders.append(folder)
                if child.tag != "include":
                    continue
                name = scenes.substitute(child.get("filename", ""), local)
                target = scenes.find(name, [here, *folders])
                if target is None:
                    raise SceneFileError(f"{file}: <include filename=\"{name}\"> not found "
                                         f"(looked in {', '.join([here, *folders])})")
                included = visit(target, local, (*seen, file))
                # (where it stands now: an include before it in this parent
                # has put its own children in its place)
                at = list(parent).index(child)
                parent.remove(child)
                for j, grand in enumerate(list(included)):
                    parent.insert(at + j, grand)
        return root

    root = visit(path, {k: str(v) for k, v in (defines or {}).items()}, ())
    return root, folders


# ------------------------------ Integrator settings ------------------------------

def integrator_settings(path: str, defines: dict | None = None) -> tuple[dict, list[str]]:
    """(the settings of :data:`SETTINGS` the scene's innermost integrator
    sets, as Python values; the wrappers seen through, outermost first,
    e.g. ``['moment']``). A scene without an ``<integrator>`` sets none
    (Mitsuba then renders with ``path``'s defaults)."""
    root, _ = inlined(path, defines)
    values = scenes.parameters(path, defines)
    integrator = root.find("integrator")
    wrappers: list[str] = []
    settings: dict = {}
    while integrator is not None:
        inner = integrator.find("integrator")
        found = _settings_of(integrator, values, path)
        if inner is None or found:
            settings = found
        if inner is None:
            break
        wrappers.append(scenes.substitute(integrator.get("type", "?"), values))
        integrator = inner
    return settings, wrappers


def _settings_of(element, values: dict, path: str) -> dict:
    out = {}
    for child in element:
        name = child.get("name")
        if name not in SETTINGS:
            continue
        text = scenes.substitute(child.get("value", ""), values)
        try:
            out[name] = (text.strip().lower() == "true") if SETTINGS[name] == "boolean" \
                else int(text)
        except ValueError:
            raise SceneFileError(f"{path}: integrator setting {name}='{text}' is not "
                                 f"{'a boolean' if SETTINGS[name] == 'boolean' else 'an integer'}"
                                 f"; give it with -D or fix the scene") from None
    return out


# ---------------------------------- Film size ------------------------------------

#: Mitsuba's hdrfilm size where a scene gives none.
DEFAULT_FILM = (768, 576)


def film_size(path: str, defines: dict | None = None) -> tuple[int, int]:
    """(width, height) of the scene's first sensor's film, ``$``-parameters
    replaced (defaults of the file, then ``defines``); Mitsuba's default
    where it gives none. Raises :class:`SceneFileError` for a size that is
    not a positive integer."""
    root, _ = inlined(path, defines)
    values = scenes.parameters(path, defines)
    film = root.find("sensor/film")
    size = list(DEFAULT_FILM)
    for child in (film if film is not None else []):
        if child.get("name") in ("width", "height"):
            text = scenes.substitute(child.get("value", ""), values)
            try:
                value = int(text)
            except ValueError:
                value = 0
            if value < 1:
                raise SceneFileError(f"{path}: film {child.get('name')} '{text}' is not a "
                                     "positive integer; give its $-parameter with -D")
            size[child.get("name") == "height"] = value
    return size[0], size[1]


class Film(NamedTuple):
    """A film's size, and the window of it rendered (None: all of it).
    One value, so that it passes through run/renders.load_resolved as a
    (width, height) does: that module's source keys every kept render and
    cached reference."""

    width: int
    height: int
    crop: tuple[int, int, int, int] | None = None     # (x, y, width, height)


def with_film(path: str, film: tuple[int, int] | Film, defines: dict | None = None
              ) -> tuple[str, list[str]]:
    """(the scene's XML, includes inlined, with the first sensor's film at
    ``film`` = (width, height), and its crop window a :class:`Film`'s or
    none; the folders its relative paths resolve from). Raises
    :class:`SceneFileError` for a scene without a ``<sensor>``."""
    root, folders = inlined(path, defines)
    sensor = root.find("sensor")
    if sensor is None:
        raise SceneFileError(f"scene {path} has no <sensor> (nor an included file): the "
                             "comparison renders through the scene's first sensor; add one")
    film_element = sensor.find("film")
    if film_element is None:           # Mitsuba's default film, sized here
        film_element = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    for child in list(film_element):
        if child.get("name") in ("width", "height", "crop_width", "crop_height",
                                 "crop_offset_x", "crop_offset_y"):
            film_element.remove(child)
    sizes = dict(zip(("width", "height"), film[:2]))
    crop = getattr(film, "crop", None)
    if crop is not None:
        sizes.update(zip(("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"), crop))
    for name, value in sizes.items():
        ET.SubElement(film_element, "integer", {"name": name, "value": str(int(value))})
    return ET.tostring(root, encoding="unicode"), folders
