"""What `mcillum validate` runs: scenes, resolutions, spp ladders, K, and the
cases of the failures group.

``quick`` is for CI and a first look; ``full`` is for publication-quality
charts (docs/measurements.md says what each costs). Budgets per scene follow
what its statistics need: the Cornell box's small light must be hit in every
pixel of every render before a per-pixel variance means anything (see
tests/test_agreement.py), so it gets few pixels and many samples. A profile
compares every registered estimator unless it names its own list.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mcillum.errors import UsageError
from mcillum.integrators import registry

#: The two groups of a profile: scene comparisons and the failures group.
GROUPS = ("scenes", "failures")


@dataclass(frozen=True, kw_only=True)
class Display:
    """The speed-and-images stage of a scene (stages/speed.py): the
    resolution a person judges the images at, and the time budgets, each the
    time `path` needs for one of ``path_spp`` (all scaled by one factor
    until the fixed cost of a render is at most 10 % of the smallest
    budget)."""

    res: int
    path_spp: tuple[int, ...] = (4, 8, 16)
    renders: int = 4               # K seeds per estimator and budget
    repeats: int = 5               # timed renders per estimator and spp (cost model)


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
    #: The file the profile was read from ("" for one built in Python).
    source: str = ""

    def estimator_names(self) -> list[str]:
        if self.estimators is not None:
            return list(self.estimators)
        return [*registry.names(), registry.REFERENCE]

    def check_scenes(self, names) -> None:
        """Raise UsageError for a scene name the profile does not run."""
        known = {r.scene for r in self.runs} | {c.scene for c in self.failures}
        for name in names:
            if name not in known:
                raise UsageError(f"scene '{name}' is not in profile '{self.name}' "
                                 f"({', '.join(sorted(known))})")


#: Geometry edge cases (grazing views, back faces, shading normals, thin plates).
GEOMETRY = ("edge_grazing", "edge_backface", "edge_shading_normals", "edge_thin")

#: The display stage of the quick profile: 128² (stages/speed.py).
QUICK_DISPLAY = Display(res=128)

QUICK = Profile(name="quick", runs=(
    # silhouette pixels hinge on rare sub-pixel hits: with 680 samples per
    # pixel (16², 1–64 spp × 8) emitter_sampling failed one at p = 2e-8 while
    # 32 × 1024 spp agreed with path; 8² × (4–256 spp) × 8 sees them
    SceneRun(scene="furnace_sphere", res=8, ladder=(4, 16, 64, 256), renders=8, max_depth=2,
             display=QUICK_DISPLAY),
    SceneRun(scene="cap_plane", res=8, ladder=(4, 16, 64, 256), renders=12, max_depth=2,
             display=QUICK_DISPLAY),
    SceneRun(scene="sky_sphere", res=24, ladder=(4, 16, 64, 128), renders=12,
             display=QUICK_DISPLAY),
    SceneRun(scene="probe_spheres", res=8, ladder=(16, 64, 256, 1024), renders=16,
             display=QUICK_DISPLAY),
    SceneRun(scene="cornell_box", res=8, ladder=(32, 128, 512, 2048), renders=16,
             display=QUICK_DISPLAY),
    # the quadrature estimators' own case: no occlusion, diffuse, smooth light
    SceneRun(scene="lone_sphere", res=8, ladder=(4, 16, 64, 256), renders=8, max_depth=2,
             defines={"envmap": "sg"}, display=QUICK_DISPLAY),
), reference_max_spp=1 << 18, reference_max_seconds=30.0,
    user_scenes=UserScenes(res=16, ladder=(4, 16, 64, 256), renders=8, display=QUICK_DISPLAY),
    failures=(
    # small bright sources: 64 seeds each, as the stability suite asks
    FailureCase(group="heavy_tail", scene="sun_sky", res=8, spp=16, seeds=64),
    # ... and in direct light, where the estimators of N directions run too
    # (sun_sky's 0.0002 sr sun only in full: at 8² × 16 spp × 64 seeds cosine
    # is expected to hit it about once, and its bound of 4 read "biased")
    FailureCase(group="heavy_tail", scene="lone_sphere", res=8, spp=16, seeds=64,
                defines={"envmap": "sunrise"}, max_depth=2, label="lone_sphere_sunrise"),
    *(FailureCase(group="heavy_tail", scene="probe_spheres", res=8, spp=16, seeds=64,
                  defines={"envmap": probe}, label=f"probe_spheres_{probe}")
      for probe in ("sunrise", "city", "interior")),
    FailureCase(group="unreachable", scene="point_light", res=8, spp=16, seeds=16, max_depth=2),
    FailureCase(group="unreachable", scene="smooth_glass", res=8, spp=16, seeds=16),
    FailureCase(group="glossy", scene="glossy_sphere", res=8, spp=16, seeds=16, label="roughness",
                sweep=("alpha", (0.5, 0.1, 0.02))),
    *(FailureCase(group="geometry", scene=scene, res=8, spp=16, seeds=64) for scene in GEOMETRY),
    FailureCase(group="numerical", scene="edge_light_size", res=8, spp=16, seeds=64,
                defines={"radius": 0, "size": 0}, label="zero_area_emitters"),
))

#: The display stage of the full profile: 256², larger budgets, K = 6.
FULL_DISPLAY = Display(res=256, path_spp=(4, 16, 64), renders=6)

FULL = Profile(name="full", runs=(
    SceneRun(scene="furnace_sphere", res=64, ladder=(1, 4, 16, 64, 256), renders=16, max_depth=2,
             display=FULL_DISPLAY),
    SceneRun(scene="cap_plane", res=16, ladder=(1, 4, 16, 64, 256, 1024), renders=16,
             max_depth=2, display=FULL_DISPLAY),
    SceneRun(scene="sky_sphere", res=64, ladder=(1, 4, 16, 64, 256), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="probe_spheres", res=64, ladder=(1, 4, 16, 64, 256, 1024), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="glossy_sphere", res=48, ladder=(4, 16, 64, 256, 1024), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="sun_sky", res=48, ladder=(4, 16, 64, 256, 1024), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="cornell_box", res=16, ladder=(16, 64, 256, 1024, 4096), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="phong_spheres", res=32, ladder=(4, 16, 64, 256, 1024), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="glossy_phong", res=32, ladder=(4, 16, 64, 256, 1024), renders=16,
             display=FULL_DISPLAY),
    SceneRun(scene="probe_spheres", res=32, ladder=(4, 16, 64, 256), renders=16, max_depth=2,
             display=FULL_DISPLAY, label="probe_spheres_direct"),
    *(SceneRun(scene="lone_sphere", res=32, ladder=(4, 16, 64, 256), renders=16, max_depth=2,
               defines={"envmap": m}, display=FULL_DISPLAY, label=f"lone_sphere_{m}")
      for m in ("sg", "gradient", "courtyard", "studio", "forest")),
), reference_max_spp=1 << 20, reference_max_seconds=600.0,
    user_scenes=UserScenes(res=32, ladder=(4, 16, 64, 256, 1024), renders=16,
                           display=FULL_DISPLAY),
    failures=(
    FailureCase(group="heavy_tail", scene="sun_sky", res=32, spp=16, seeds=128),
    *(FailureCase(group="heavy_tail", scene="lone_sphere", res=32, spp=16, seeds=128,
                  defines={"envmap": m}, max_depth=2, label=f"lone_sphere_{m}")
      for m in ("sun_sky", "sunrise", "interior")),
    *(FailureCase(group="heavy_tail", scene="probe_spheres", res=32, spp=16, seeds=128,
                  defines={"envmap": probe}, label=f"probe_spheres_{probe}")
      for probe in ("sunrise", "city", "interior")),
    FailureCase(group="unreachable", scene="point_light", res=16, spp=64, seeds=32, max_depth=2),
    FailureCase(group="unreachable", scene="smooth_glass", res=16, spp=64, seeds=32),
    FailureCase(group="glossy", scene="glossy_sphere", res=24, spp=64, seeds=16, label="roughness",
                sweep=("alpha", (0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01))),
    FailureCase(group="glossy", scene="glossy_phong", res=24, spp=64, seeds=16,
                label="phong_exponent", sweep=("exponent", (10, 30, 100, 300, 1000, 3000))),
    *(FailureCase(group="geometry", scene=scene, res=16, spp=64, seeds=64) for scene in GEOMETRY),
    FailureCase(group="numerical", scene="edge_light_size", res=16, spp=64, seeds=64,
                defines={"radius": 0, "size": 0}, label="zero_area_emitters"),
))

PROFILES = {p.name: p for p in (QUICK, FULL)}
