"""The records of the quadrature stage (stages/quadrature.py): equal rays
against a Monte Carlo baseline, bias against N, calibration."""

from __future__ import annotations

from dataclasses import dataclass

from .common import optional


@dataclass(kw_only=True)
class EqualRays:
    """A point-set estimator against ``baseline`` at the same number of traced
    directions per pixel (stages/quadrature.py)."""

    baseline: str
    baseline_spp: int            # N · spp
    relmse: float                # each less the reference's relative variance
    baseline_relmse: float
    ratio: float                 # relmse / baseline_relmse (< 1: the set wins)
    ratio_low: float             # 95 % interval
    ratio_high: float
    seconds: float               # median per render
    baseline_seconds: float
    # the spp the baseline's error was read at: N · spp where rendered there,
    # the ladder's spp where scaled to N · spp by 1/N (independent samples)
    baseline_read_at: int | None = optional()


@dataclass(kw_only=True)
class BiasAtN:
    directions: int
    rms_bias: float              # noise-corrected rms over pixels, / rms of the reference
    rms_bias_se: float
    mean_bias: float             # signed, image mean, / the reference's image mean
    renders: int | None = None   # K renders the bias was read from (minor 17; None: the record's)


@dataclass(kw_only=True)
class Calibration:
    """Measured RMSE over predicted posterior std, per pixel."""

    median: float
    q25: float
    q75: float
    pixels: int
    verdict: str                 # calibrated | over-confident | under-confident | exact …
    spp: int | None = None       # the ladder rung it was read at (minor 17; None: the record's)


@dataclass(kw_only=True)
class SettingScore:
    """One candidate's held-out error (integrators/quadrature/gp_settings.py)."""

    mapping: str
    noise: float
    length_scale: float
    relmse: float                # at the render's spp; inf where it could not be solved


@dataclass(kw_only=True)
class GlossySettings:
    """bayesian_hemisphere's two sets at a glossy shading point: the diffuse
    set's settings for its N − N_b nodes, and the lobe set's."""

    lobe_directions: int         # N_b
    diffuse_mapping: str
    diffuse_noise: float
    diffuse_length_scale: float
    lobe_length_scale: float     # in lobe widths √(2/(n + 1))
    lobe_noise: float
    lobe_calibration: float      # what the lobe set's posterior variance is scaled by
    #: the exponent the lobe's candidates were scored at (None: not scored, defaults)
    lobe_exponent: float | None = None


@dataclass(kw_only=True)
class Settings:
    """How an estimator chose its settings for the scene (bayesian_hemisphere's
    ``auto``): what it chose, how, and every candidate's score."""

    source: str
    mapping: str
    noise: float
    length_scale: float
    spp: int                     # the pixel's sample count they were chosen for
    #: what the posterior variance is scaled by (held-out calibration; 1: none)
    calibration: float = 1.0
    candidates: list[SettingScore] | None = optional()
    #: where the scene has glossy lobes (minor version 13)
    glossy: GlossySettings | None = optional()


@dataclass(kw_only=True)
class Quadrature:
    """What the quadrature stage measured of one estimator of N directions."""

    name: str
    directions: int
    spp: int
    renders: int
    equal_rays: EqualRays | None = optional()
    bias: list[BiasAtN] | None = optional()
    calibration: Calibration | None = optional()
    settings: Settings | None = optional()      # minor version 10

