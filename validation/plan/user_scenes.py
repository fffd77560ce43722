"""The plan of a scene given by path (``mcillum validate my_scene.xml``).

A profile's ``user_scenes`` (plan/profiles.py: ``UserScenes``) says how such
a scene is compared; this module applies it to one file: the statistics at
the reduced film (the scene's aspect, its longest side ``res``), the
equal-time images at the scene's own film up to the display cap, and the
integrator settings that define the image, read off the scene (through
``moment``/``aov`` wrappers) unless the user overrides them. Its
environment map, however the scene names it (a file, a ``$``-parameter, in
an included file), is given to the renders as ``$envmap``
(:func:`map_parameter`), so that the sun split (stages/sun_split.py) can
take a sun off it and widen it.
"""

from __future__ import annotations

import dataclasses
import os

from mcillum import envmaps
from mcillum.errors import UsageError

from . import scene_files, scenes
from .plans import Profile, SceneRun


def scene_run(profile: Profile, path: str, *, defines: dict | None = None,
              settings: dict | None = None, res: int | None = None,
              label: str = "") -> tuple[SceneRun, list[str]]:
    """(the :class:`SceneRun` of scene file ``path`` under ``profile``; what
    it took from where, in sentences for the results' notes). ``settings``
    (``max_depth``, ``rr_depth``, ``hide_emitters``) override the scene's,
    ``res`` the longest side of the statistics film. Raises
    :class:`~mcillum.errors.UsageError` when the profile compares no scenes
    given by path or the file cannot be read as a scene."""
    plan = profile.user_scenes
    if plan is None:
        raise UsageError(f"profile '{profile.name}' compares no scenes given by path (it "
                         "has no [user_scenes] table); use --profile quick or full")
    defines = {k: str(v) for k, v in (defines or {}).items()}
    try:
        found, wrappers = scene_files.integrator_settings(path, defines)
        own = scene_files.film_size(path, defines)
        envmap, said = map_parameter(path, defines)
    except scene_files.SceneFileError as err:
        raise UsageError(str(err)) from None
    # (why a map was not given matters only where it has a sun: sun_split's note)
    told = [said] if said and (envmap is not None or "envmap" in defines) else []
    if envmap is not None:
        defines["envmap"] = envmap
    given = {k: v for k, v in (settings or {}).items() if v is not None}
    chosen = {**found, **given}
    longest = res or plan.res
    if longest < 1:
        raise UsageError(f"--res must be >= 1, got {longest}")
    display = plan.display and dataclasses.replace(
        plan.display, res=min(plan.display.res, max(own)))
    run = SceneRun(scene=os.path.abspath(path), res=min(longest, max(own)),
                   ladder=plan.ladder, renders=plan.renders,
                   max_depth=chosen.pop("max_depth", -1), defines=defines, display=display,
                   label=label or os.path.splitext(os.path.basename(path))[0],
                   own_film=own, settings=chosen, learning=plan.learning)
    return run, _notes(run, found, given, wrappers) + told


def map_parameter(path: str, defines: dict | None = None) -> tuple[str | None, str]:
    """(the map file to give scene ``path`` as ``$envmap``, or None; a
    sentence for the results' notes: what is done, or why not — "" where
    the scene has no ``envmap`` emitter or gives its map as ``$envmap``
    with a default, which the renders resolve as a bundled scene's).
    Where a define gives ``envmap`` (``-D``), that map is used, and the
    sentence says which map it replaces. The map given is checked as
    mcillum's own are (envmaps/safety.py; a map it refuses is left to the
    scene). Raises :class:`~.scene_files.SceneFileError` for a scene file
    that cannot be read."""
    defines = defines or {}
    found = scene_files.environment_map(path, defines)
    if found is None:
        return None, ""
    named = f"the envmap emitter of {found.where}"
    if found.written == "$envmap" and ("envmap" in defines
                                       or "envmap" in scenes.defaults(path)):
        return None, ""
    if found.clash:
        return None, (f"{named} names {found.written!r} while the scene declares or uses "
                      "$envmap for something else: rename that parameter to have mcillum "
                      "give the map as $envmap")
    if "envmap" in defines:
        return None, f"-D envmap={defines['envmap']} replaces the map {named} names"
    if not found.written:
        return None, (f"{named} gives no filename (its map comes another way): mcillum "
                      "gives only a map file as $envmap")
    if found.file is None:
        return None, (f"{named} names {found.written!r}, which mcillum did not find beside "
                      "the scene, its includes or its <path>s: give the file's path")
    try:
        envmaps.resolve(found.file)
    except envmaps.EnvmapError as err:
        return None, f"mcillum's map check refuses the map of {named}: {err}"
    return found.file, (f"the map {found.file} ({named}) is given to the renders as "
                        "$envmap, checked as mcillum's own maps are (negative texels set to "
                        "0), so that a sun on it can be taken off and widened (the sun split)")


def _notes(run: SceneRun, found: dict, given: dict, wrappers: list[str]) -> list[str]:
    through = f" (seen through {' > '.join(wrappers)})" if wrappers else ""
    notes = []
    if found:
        notes.append("settings from the scene's integrator" + through + ": "
                     + ", ".join(f"{k} {v}" for k, v in found.items()))
    elif wrappers:
        notes.append(f"the scene's integrator{through} sets none of max_depth, rr_depth, "
                     "hide_emitters: Mitsuba's defaults")
    if given:
        notes.append("settings given by the user: " + ", ".join(f"{k} {v}"
                                                                 for k, v in given.items()))
    w, h = run.own_film
    fw, fh = run.film
    notes.append(f"statistics at {fw}×{fh} (the scene's film is {w}×{h}; its longest side "
                 f"reduced to {run.res}, the profile's rule)")
    return notes
