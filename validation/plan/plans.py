"""The records a profile is made of: a scene comparison (:class:`SceneRun`),
its speed-and-images stage (:class:`Display`), a failure case
(:class:`FailureCase`), how a scene given by path is compared
(:class:`UserScenes`), and the profile itself (:class:`Profile`). Files
hold them (profile_files.py); profiles.py has the bundled ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mcillum.errors import UsageError
from mcillum.integrators.core import registry


@dataclass(frozen=True, kw_only=True)
class Display:
    """The speed-and-images stage of a scene (stages/speed.py): the
    resolution a person judges the images at, and the time budgets, each the
    time `path` needs for one of ``path_spp`` (all scaled by one factor
    until the fixed cost of a render is at most 10 % of the largest
    budget, where efficiency is read)."""

    res: int
    path_spp: tuple[int, ...] = (4, 8, 16)
    renders: int = 4               # K seeds per estimator and budget
    repeats: int = 5               # pilot renders per estimator at 1 and 16 spp
    #: The budget axis (stages/budget_axis.py): seconds per render,
    #: increasing; () leaves it out.
    axis: tuple[float, ...] = ()
    axis_renders: int = 2          # K per estimator and measured budget (≥ 2: a spread)
    #: Fixed-pdf estimators are measured up to this many seconds and at the
    #: next budget, which checks the model drawn beyond it; the estimators
    #: of ``axis_measured`` and every learner are measured at every budget.
    axis_model_above: float = 3.0
    axis_measured: tuple[str, ...] = ("path", "mis")


@dataclass(frozen=True, kw_only=True)
class SceneRun:
    """One scene comparison: the small-image statistics over an spp ladder,
    and (``display``) its speed-and-images stage."""

    scene: str
    res: int                       # of the small-image statistics
    ladder: tuple[int, ...]        # spp values, increasing
    renders: int                   # K independent renders per (estimator, spp)
    max_depth: int = -1
    defines: dict = field(default_factory=dict)
    display: Display | None = None
    label: str = ""                # a second run of one scene needs its own
    #: A scene given by path (:meth:`Profile.user_run`): its film's own
    #: (width, height); ``res`` is then the longest side it is rendered at
    #: (the aspect kept). None: a bundled scene, which takes ``res`` as $res.
    own_film: tuple[int, int] | None = None
    #: Integrator settings that define its image besides ``max_depth``
    #: (``rr_depth``, ``hide_emitters``: read off a user's scene).
    settings: dict = field(default_factory=dict)
    #: Run the learning stage (stages/learning.py) for the estimators that
    #: learn their pdf: their error against training passes.
    learning: bool = False

    @property
    def id(self) -> str:
        return self.label or self.scene

    @property
    def film(self) -> tuple[int, int] | None:
        """(width, height) at ``res`` for a scene given by path; None for a
        bundled one (see :func:`scaled_film`)."""
        return None if self.own_film is None else scaled_film(self.own_film, self.res)

    @property
    def integrator_settings(self) -> dict:
        """What every compared integrator and the reference are given (those
        an integrator does not take are left out for it: run/jobs.py)."""
        return {"max_depth": self.max_depth, **self.settings}


def scaled_film(own: tuple[int, int], longest: int) -> tuple[int, int]:
    """A film of aspect ``own`` whose longest side is ``longest`` (each side
    at least 1 pixel); ``own`` itself where it is no larger."""
    w, h = own
    if max(w, h) <= longest:
        return (w, h)
    f = longest / max(w, h)
    return (max(1, round(w * f)), max(1, round(h * f)))


@dataclass(frozen=True, kw_only=True)
class UserScenes:
    """How a profile compares a scene given by path (``mcillum validate
    my_scene.xml``): the reduced-film rule. The small-image statistics run
    at a film whose longest side is ``res`` (the scene's aspect kept): every
    pixel is a test of its own (K renders per rung), so a few hundred pixels
    give the per-pixel tests and the image mean as much power as the bundled
    scenes' 8²–24² films, at a cost that does not grow with the scene's
    film. The equal-time images run at the scene's own film, its longest
    side capped at ``display.res``."""

    res: int                       # longest side of the statistics film
    ladder: tuple[int, ...]
    renders: int
    display: Display | None = None
    learning: bool = False         # the learning stage on every such scene


@dataclass(frozen=True, kw_only=True)
class FailureCase:
    """One case of the ``failures`` group (pipeline.py, stages/cases.py,
    checks/cases.py)."""

    group: str          # heavy_tail | unreachable | geometry | numerical | glossy
    scene: str
    res: int
    spp: int
    seeds: int                     # K independent renders per estimator
    defines: dict = field(default_factory=dict)
    label: str = ""
    sweep: tuple = ()              # glossy: (parameter, values from wide to narrow)
    max_depth: int = -1

    @property
    def id(self) -> str:
        return f"failures.{self.group}.{self.label or self.scene}"


@dataclass(frozen=True, kw_only=True)
class Sequential:
    """How far a sequential test may go (stages/sequential.py): the samples
    per pixel one check may reach before it says inconclusive, as a multiple
    of its first look's (a scene's ladder, a case's K seeds), and the ε of a
    pass ("unbiased within ±ε": the interval on the image mean's relative
    bias lies inside ±ε), for scene runs and failure cases."""

    scene_budget: float = 16.0
    case_budget: float = 1024.0
    scene_epsilon: float = 0.02
    case_epsilon: float = 0.05


@dataclass(frozen=True, kw_only=True)
class Profile:
    """What one ``--profile`` runs, and how precise its references are."""

    name: str
    runs: tuple[SceneRun, ...]
    reference_fraction: float = 0.1   # reference SE ≤ this × smallest compared RMSE
    #: At the display resolution (stages/speed.py), of `path`'s own RMSE at
    #: the largest budget: 0.25 costs about 16× path's spp there (0.1 of the
    #: smallest RMSE of all costs 100× or more) and adds 6 % to path's relMSE,
    #: recorded as ``reference_relmse``.
    display_reference_fraction: float = 0.25
    #: The smallest pass: small images get larger ones (run/references.pass_spp).
    reference_spp_per_pass: int = 64
    reference_max_spp: int = 1 << 16
    reference_max_seconds: float = 60.0
    failures: tuple[FailureCase, ...] = ()
    #: Integrators compared; None: every registered mcillum estimator, then path.
    estimators: tuple[str, ...] | None = None
    #: How a scene given by path is compared (None: the profile takes none).
    user_scenes: UserScenes | None = None
    #: Modules or files that register integrators (mcillum/plugins.py),
    #: imported before anything runs, on the driver and every worker.
    plugins: tuple[str, ...] = ()
    #: Scene files compared by the ``user_scenes`` rule when the command
    #: line names no scenes (absolute paths).
    scene_files: tuple[str, ...] = ()
    #: Budgets and ε of the sequential tests.
    sequential: Sequential = Sequential()
    #: The file the profile was read from ("" for one built in Python).
    source: str = ""

    def estimator_names(self) -> list[str]:
        if self.estimators is not None:
            return list(self.estimators)
        return [*registry.names(), registry.REFERENCE]

    def check_scenes(self, names) -> None:
        """Raise UsageError for a scene name (or label) the profile does not run."""
        known = ({r.scene for r in self.runs} | {r.label for r in self.runs if r.label}
                 | {c.scene for c in self.failures} | {c.label for c in self.failures if c.label})
        for name in names:
            if name not in known:
                raise UsageError(f"scene '{name}' is not in profile '{self.name}' "
                                 f"({', '.join(sorted(known))})")
