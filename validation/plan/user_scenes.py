"""The plan of a scene given by path (``mcillum validate my_scene.xml``).

A profile's ``user_scenes`` (plan/profiles.py: ``UserScenes``) says how such
a scene is compared; this module applies it to one file: the statistics at
the reduced film (the scene's aspect, its longest side ``res``), the
equal-time images at the scene's own film up to the display cap, and the
integrator settings that define the image, read off the scene (through
``moment``/``aov`` wrappers) unless the user overrides them.
"""

from __future__ import annotations

import dataclasses
import os

from mcillum.errors import UsageError

from . import scene_files
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
    except scene_files.SceneFileError as err:
        raise UsageError(str(err)) from None
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
    return run, _notes(run, found, given, wrappers)


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
