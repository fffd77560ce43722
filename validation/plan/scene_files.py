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
  the folders its relative paths resolve from;
* :func:`environment_map`: the map file its ``envmap`` emitter loads, which
  :func:`with_film` hands to Mitsuba as ``$envmap`` where a define gives
  one (plan/user_scenes.py: the sun split needs the map as a parameter).

Nothing here loads the scene; run/renders.py does.
"""

from __future__ import annotations

import os
import re
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
    root, folders, _ = _inline(path, defines)
    return root, folders


def _inline(path: str, defines: dict | None = None):
    """:func:`inlined`, and each ``envmap`` emitter of the inlined root with
    the file that holds it and that file's ``$``-parameters (its name is
    resolved as that file's values say)."""
    folders: list[str] = []
    maps: list[tuple[ET.Element, str, dict]] = []

    def visit(file: str, params: dict, seen: tuple) -> ET.Element:
        file = os.path.abspath(file)
        if file in seen:
            raise SceneFileError(f"{file} includes itself (through {' > '.join(seen)})")
        root = _parse(file)
        here = os.path.dirname(file)
        if here not in folders:
            folders.append(here)
        local = scenes.parameters(file, params)
        # (before the includes below are inlined: each file records its own)
        maps.extend((e, file, local) for e in root.iter("emitter")
                    if scenes.substitute(e.get("type", ""), local) == "envmap")
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
    return root, folders, maps


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
    none; the folders its relative paths resolve from). Where ``defines``
    give ``envmap``, the ``envmap`` emitter loads ``$envmap`` whatever file
    it names (:func:`_map_as_parameter`). Raises :class:`SceneFileError`
    for a scene without a ``<sensor>``."""
    root, folders, maps = _inline(path, defines)
    if (defines or {}).get("envmap") is not None and maps:
        _map_as_parameter(root, maps[0][0])
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


# ------------------------------- Environment map ----------------------------------

_USES_ENVMAP = re.compile(r"\$envmap\b")


class EnvironmentMap(NamedTuple):
    """The scene's ``envmap`` emitter as its files give it."""

    where: str              # the XML file that holds the emitter
    written: str            # its filename as written ("" where it names none)
    file: str | None        # the map it loads (absolute); None where not found
    #: The scene declares ``$envmap`` (a ``<default>``) or uses it elsewhere
    #: than as this emitter's filename, while the emitter names another
    #: file: the map cannot be given as ``$envmap`` without changing that use.
    clash: bool = False


def environment_map(path: str, defines: dict | None = None) -> EnvironmentMap | None:
    """The scene's (first) ``envmap`` emitter: where it is, the filename it
    gives and the file that name finds (``$``-parameters replaced as its own
    file's values say; a relative name looked up as the scene is loaded:
    the scene's folder, each included file's, each ``<path>``'s). None for
    a scene without one. Raises :class:`SceneFileError` as :func:`inlined`."""
    root, folders, maps = _inline(path, defines)
    if not maps:
        return None
    emitter, where, local = maps[0]
    element = _filename_element(emitter)
    written = element.get("value", "") if element is not None else ""
    name = scenes.substitute(written, local)
    return EnvironmentMap(where, written, scenes.find(name, folders) if name else None,
                          written != "$envmap" and _has_envmap(root, element))


def _filename_element(emitter: ET.Element) -> ET.Element | None:
    return next((c for c in emitter if c.get("name") == "filename"), None)


def _has_envmap(root: ET.Element, skip: ET.Element | None = None) -> bool:
    """Does the inlined scene declare ``$envmap`` (a ``<default>``) or use
    it anywhere but in ``skip``?"""
    return any(e.tag == "default" and e.get("name") == "envmap" for e in root.iter()) \
        or any(_USES_ENVMAP.search(v) for e in root.iter() if e is not skip
               for v in e.attrib.values())


def _map_as_parameter(root: ET.Element, emitter: ET.Element) -> None:
    """The ``envmap`` emitter's filename made ``$envmap``, so that the map a
    define gives (the sunless map, the widened sun: stages/sun_split.py)
    replaces the one it names. Left as it is where the scene declares or
    uses ``$envmap`` itself (the define then goes where the scene says) or
    the emitter names no file."""
    element = _filename_element(emitter)
    if element is None or _has_envmap(root):
        return
    element.set("value", "$envmap")
