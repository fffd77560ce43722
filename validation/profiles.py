"""What `mcillum validate` runs: scenes, resolutions, spp ladders, K.

``quick`` is for CI and a first look (about 3 minutes on 2 cores with cold
caches); ``full`` is for publication-quality charts. Budgets per scene follow
what its statistics need: the Cornell box's small light must be hit in every
pixel of every render before a per-pixel variance means anything (see
tests/test_against_path.py), so it gets few pixels and many samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class SceneRun:
    scene: str
    res: int
    ladder: tuple[int, ...]        # spp values, increasing
    renders: int                   # K independent renders per (estimator, spp)
    max_depth: int = -1
    defines: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Profile:
    name: str
    runs: tuple[SceneRun, ...]
    estimators: tuple[str, ...] = ("uniform_hemisphere", "cosine_hemisphere", "bsdf_sampling",
                                   "emitter_sampling", "mis", "path")
    reference_fraction: float = 0.1   # reference SE ≤ this × smallest compared RMSE
    reference_spp_per_pass: int = 64
    reference_max_spp: int = 1 << 16
    reference_max_seconds: float = 60.0


QUICK = Profile("quick", (
    # silhouette pixels hinge on rare sub-pixel hits: with 680 samples per
    # pixel (16², 1–64 spp × 8) emitter_sampling failed one at p = 2e-8 while
    # 32 × 1024 spp agreed with path; 8² × (4–256 spp) × 8 sees them
    SceneRun("furnace_sphere", 8, (4, 16, 64, 256), 8, max_depth=2),
    SceneRun("cap_plane", 8, (4, 16, 64, 256), 12, max_depth=2),
    SceneRun("sky_sphere", 24, (4, 16, 64, 128), 12),
    SceneRun("probe_spheres", 8, (16, 64, 256, 1024), 16),
    SceneRun("cornell_box", 8, (32, 128, 512, 2048), 16),
), reference_max_spp=1 << 18, reference_max_seconds=30.0)

FULL = Profile("full", (
    SceneRun("furnace_sphere", 64, (1, 4, 16, 64, 256), 16, max_depth=2),
    SceneRun("cap_plane", 16, (1, 4, 16, 64, 256, 1024), 16, max_depth=2),
    SceneRun("sky_sphere", 64, (1, 4, 16, 64, 256), 16),
    SceneRun("probe_spheres", 64, (1, 4, 16, 64, 256, 1024), 16),
    SceneRun("glossy_sphere", 48, (4, 16, 64, 256, 1024), 16),
    SceneRun("sun_sky", 48, (4, 16, 64, 256, 1024), 16),
    SceneRun("cornell_box", 16, (16, 64, 256, 1024, 4096), 16),
    SceneRun("phong_spheres", 32, (4, 16, 64, 256, 1024), 16),
    SceneRun("glossy_phong", 32, (4, 16, 64, 256, 1024), 16),
), reference_max_spp=1 << 20, reference_max_seconds=600.0)

PROFILES = {p.name: p for p in (QUICK, FULL)}
