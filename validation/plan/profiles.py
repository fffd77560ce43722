"""What `mcillum validate` runs: scenes, resolutions, spp ladders, K, and the
cases of the failures group.

The profiles are data: ``quick`` (CI and a first look) in quick.toml, ``full``
(publication-quality charts) in full.toml, beside this module; their comments
say why each budget is what it is, and profile_files.py reads them (and a
user's own file) into the dataclasses re-exported here. A profile compares
every registered estimator unless it names its own list.
"""

from __future__ import annotations

from . import profile_files
from .plans import (
    Display,
    FailureCase,
    Profile,
    SceneRun,
    UserScenes,
    scaled_film,
)

__all__ = ["FULL", "GEOMETRY", "GROUPS", "PROFILES", "QUICK", "Display", "FailureCase",
           "Profile", "SceneRun", "UserScenes", "resolve", "scaled_film"]

#: The two groups of a profile: scene comparisons and the failures group.
GROUPS = ("scenes", "failures")

#: Geometry edge cases (grazing views, back faces, shading normals, thin plates).
GEOMETRY = ("edge_grazing", "edge_backface", "edge_shading_normals", "edge_thin")

QUICK = profile_files.bundled("quick")
FULL = profile_files.bundled("full")
#: Accuracy against time from a tenth of a second to a minute (stages/budget_axis.py).
BUDGETS = profile_files.bundled("budgets")

PROFILES = {p.name: p for p in (QUICK, FULL, BUDGETS)}


def resolve(spec) -> Profile:
    """A bundled profile by name (from :data:`PROFILES`, read once), else
    the profile file at path ``spec`` (profile_files.resolve, which raises
    UsageError for neither)."""
    if str(spec) in PROFILES:
        return PROFILES[str(spec)]
    return profile_files.resolve(spec)
