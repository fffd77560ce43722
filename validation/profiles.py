"""What `mcillum validate` runs: scenes, resolutions, spp ladders, K, and the
cases of the failures group.

``quick`` is for CI and a first look (about 2 minutes on 2 cores with cold
caches); ``full`` is for publication-quality charts. Budgets per scene follow
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


@dataclass(frozen=True)
class Display:
    """The speed-and-images stage of a scene (speed.py): the resolution a
    person judges the images at, and the time budgets, each the time `path`
    needs for one of ``path_spp`` (all scaled by one factor until the
    fixed cost of a render is at most 10 % of the smallest budget)."""


    res: int
    path_spp: tuple[int, ...] = (4, 8, 16)
    renders: int = 4               # K seeds per estimator and budget
    repeats: int = 5               # timed renders per estimator and spp (cost model)


@dataclass(frozen=True)
class SceneRun:
    scene: str
    res: int                       # of the small-image statistics
    ladder: tuple[int, ...]        # spp values, increasing
    renders: int                   # K independent renders per (estimator, spp)
    max_depth: int = -1
    defines: dict = field(default_factory=dict)
    display: Display | None = None
    label: str = ""                # a second run of one scene needs its own

    @property
    def id(self) -> str:
        return self.label or self.scene


@dataclass(frozen=True)
class FailureCase:
    """One case of the ``failures`` group (see pipeline.py and checks.py)."""

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


@dataclass(frozen=True)
class Profile:
    name: str
    runs: tuple[SceneRun, ...]
    reference_fraction: float = 0.1   # reference SE ≤ this × smallest compared RMSE
    #: At the display resolution (speed.py), of `path`'s own RMSE at the largest
    #: budget: 0.25 costs about 16× path's spp there (0.1 of the smallest RMSE
    #: of all cost 100× or more: 30 s per quick scene, beyond the profile's 3
    #: minutes) and adds 6 % to path's relMSE, recorded as ``reference_relmse``.
    display_reference_fraction: float = 0.25
    reference_spp_per_pass: int = 64
    reference_max_spp: int = 1 << 16
    reference_max_seconds: float = 60.0
    failures: tuple[FailureCase, ...] = ()
    #: Integrators compared; None: every registered mcillum estimator, then path.
    estimators: tuple[str, ...] | None = None

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

QUICK = Profile("quick", (
    # silhouette pixels hinge on rare sub-pixel hits: with 680 samples per
    # pixel (16², 1–64 spp × 8) emitter_sampling failed one at p = 2e-8 while
    # 32 × 1024 spp agreed with path; 8² × (4–256 spp) × 8 sees them
    SceneRun("furnace_sphere", 8, (4, 16, 64, 256), 8, max_depth=2, display=Display(128)),
    SceneRun("cap_plane", 8, (4, 16, 64, 256), 12, max_depth=2, display=Display(128)),
    SceneRun("sky_sphere", 24, (4, 16, 64, 128), 12, display=Display(128)),
    SceneRun("probe_spheres", 8, (16, 64, 256, 1024), 16, display=Display(128)),
    SceneRun("cornell_box", 8, (32, 128, 512, 2048), 16, display=Display(128)),
    # the quadrature estimators' own case: no occlusion, diffuse, smooth light
    SceneRun("lone_sphere", 8, (4, 16, 64, 256), 8, max_depth=2, defines={"envmap": "sg"},
             display=Display(128)),
), reference_max_spp=1 << 18, reference_max_seconds=30.0, failures=(
    # small bright sources: 64 seeds each, as the stability suite asks
    FailureCase("heavy_tail", "sun_sky", 8, 16, 64),
    # ... and in direct light, where the estimators of N directions run too
    # (sun_sky's 0.0002 sr sun only in full: at 8² × 16 spp × 64 seeds cosine
    # is expected to hit it about once, and its bound of 4 read "biased")
    FailureCase("heavy_tail", "lone_sphere", 8, 16, 64, {"envmap": "sunrise"}, max_depth=2,
                label="lone_sphere_sunrise"),
    *(FailureCase("heavy_tail", "probe_spheres", 8, 16, 64, {"envmap": probe},
                  label=f"probe_spheres_{probe}") for probe in ("sunrise", "city", "interior")),
    FailureCase("unreachable", "point_light", 8, 16, 16, max_depth=2),
    FailureCase("unreachable", "smooth_glass", 8, 16, 16),
    FailureCase("glossy", "glossy_sphere", 8, 16, 16, label="roughness",
                sweep=("alpha", (0.5, 0.1, 0.02))),
    *(FailureCase("geometry", scene, 8, 16, 64) for scene in GEOMETRY),
    FailureCase("numerical", "edge_light_size", 8, 16, 64, {"radius": 0, "size": 0},
                label="zero_area_emitters"),
))

FULL_DISPLAY = Display(256, (4, 16, 64), renders=6)

FULL = Profile("full", (
    SceneRun("furnace_sphere", 64, (1, 4, 16, 64, 256), 16, max_depth=2, display=FULL_DISPLAY),
    SceneRun("cap_plane", 16, (1, 4, 16, 64, 256, 1024), 16, max_depth=2,
             display=FULL_DISPLAY),
    SceneRun("sky_sphere", 64, (1, 4, 16, 64, 256), 16, display=FULL_DISPLAY),
    SceneRun("probe_spheres", 64, (1, 4, 16, 64, 256, 1024), 16, display=FULL_DISPLAY),
    SceneRun("glossy_sphere", 48, (4, 16, 64, 256, 1024), 16, display=FULL_DISPLAY),
    SceneRun("sun_sky", 48, (4, 16, 64, 256, 1024), 16, display=FULL_DISPLAY),
    SceneRun("cornell_box", 16, (16, 64, 256, 1024, 4096), 16, display=FULL_DISPLAY),
    SceneRun("phong_spheres", 32, (4, 16, 64, 256, 1024), 16, display=FULL_DISPLAY),
    SceneRun("glossy_phong", 32, (4, 16, 64, 256, 1024), 16, display=FULL_DISPLAY),
    SceneRun("probe_spheres", 32, (4, 16, 64, 256), 16, max_depth=2, display=FULL_DISPLAY,
             label="probe_spheres_direct"),
    *(SceneRun("lone_sphere", 32, (4, 16, 64, 256), 16, max_depth=2, defines={"envmap": m},
               display=FULL_DISPLAY, label=f"lone_sphere_{m}")
      for m in ("sg", "gradient", "courtyard", "studio", "forest")),
), reference_max_spp=1 << 20, reference_max_seconds=600.0, failures=(
    FailureCase("heavy_tail", "sun_sky", 32, 16, 128),
    *(FailureCase("heavy_tail", "lone_sphere", 32, 16, 128, {"envmap": m}, max_depth=2,
                  label=f"lone_sphere_{m}") for m in ("sun_sky", "sunrise", "interior")),
    *(FailureCase("heavy_tail", "probe_spheres", 32, 16, 128, {"envmap": probe},
                  label=f"probe_spheres_{probe}") for probe in ("sunrise", "city", "interior")),
    FailureCase("unreachable", "point_light", 16, 64, 32, max_depth=2),
    FailureCase("unreachable", "smooth_glass", 16, 64, 32),
    FailureCase("glossy", "glossy_sphere", 24, 64, 16, label="roughness",
                sweep=("alpha", (0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01))),
    FailureCase("glossy", "glossy_phong", 24, 64, 16, label="phong_exponent",
                sweep=("exponent", (10, 30, 100, 300, 1000, 3000))),
    *(FailureCase("geometry", scene, 16, 64, 64) for scene in GEOMETRY),
    FailureCase("numerical", "edge_light_size", 16, 64, 64, {"radius": 0, "size": 0},
                label="zero_area_emitters"),
))

PROFILES = {p.name: p for p in (QUICK, FULL)}
