"""The records of the failures group: per case and estimator, how its error
spreads over seeds, its batch-means test, the sun split, its verdict; the
rows of a parameter sweep."""

from __future__ import annotations

from dataclasses import dataclass, field

from .common import Outcome, flat, optional


@dataclass(kw_only=True)
class Percentiles:
    mean: float
    median: float
    p90: float
    p99: float
    max: float


@dataclass(kw_only=True)
class SppToMatch:
    spp: float
    low: float
    high: float
    level: float


@dataclass(kw_only=True)
class BatchTest(Outcome):
    """The sequential batch-means test of K renders and the batches it added
    and, where a rejection counted, its confirmation on a fresh batch
    (``replicated`` None: nothing needed confirming)."""

    passed: bool
    pass_fraction: float
    min_p: float
    pooled_p: list[float]
    alpha_pixel: float
    test: str
    rejected_pixels: int = 0
    replicated_pixels: int = 0
    replicated: bool | None = None
    replication_test: str | None = optional()
    #: checks.evidence.bias_outcome of the first test (minor version 3), as in Unbiasedness
    outcome: str = ""
    reason: str = ""
    tail_events: int = 0
    samples_needed: float | None = optional()
    counted_up: bool = False        # an upward rejection counted (checks/evidence.py)
    #: The sequential test (minor version 8, stages/sequential.py): looks
    #: taken, samples per pixel reached, the image mean's relative bias per
    #: channel and the half-width of its interval at the last look's level.
    looks: int = 1
    samples_per_pixel: int | None = optional()
    relative_bias: list[float] | None = optional()
    half_width: float | None = optional()


@dataclass(kw_only=True)
class SunSplit:
    """The same estimator re-tested on the map without its sun (and with it widened)."""

    sun: dict                      # envmaps.sun.split facts: solid_angle, texels, …
    sunless_passed: bool
    sunless_test: str
    sunless_reference_mean: float
    expected_sun_hits_per_pixel: float | None
    sun_share_of_image: float
    sunless_outcome: str = ""      # checks.evidence.bias_outcome there (minor version 3)
    sunless_reason: str = ""
    #: The same estimator tested on the map with its sun widened
    #: (envmaps.sun.widen facts: solid_angle, texels, radiance), where the real
    #: sun's test was inconclusive and the sunless one passed (minor version 12).
    widened: dict | None = optional()
    widened_outcome: str | None = optional()
    widened_reason: str | None = optional()
    widened_test: str | None = optional()


@dataclass(kw_only=True)
class TailNumbers:
    """How one estimator's error spreads over K seeds (see stats/tails.py)."""

    relmse: Percentiles
    firefly_fraction: float
    samples_per_pixel: int
    seeds: int
    seconds_median: float
    image_mean_ratio: float | None
    spp_to_match_path: SppToMatch | None
    nonfinite_values: int = 0
    negative_values: int = 0
    missing_fraction: float | None = optional()
    tail_ratio: float | None = optional()
    test: BatchTest | None = flat()
    sun: SunSplit | None = flat()


@dataclass(kw_only=True)
class CaseRow:
    """One estimator in a failure case."""

    name: str
    refused: bool
    verdict: str = ""
    message: str | None = optional()
    numbers: TailNumbers | None = optional()
    images: dict[str, str] = field(default_factory=dict)


@dataclass(kw_only=True)
class SweepRow:
    """One estimator along a swept parameter."""

    name: str
    relmse: list[float]
    seconds: list[float]
    growth: float | None
    nonfinite_values: int
    images: dict[str, str]
    verdict: str


@dataclass(kw_only=True)
class CaseReference:
    spp: int
    capped: str | None


@dataclass(kw_only=True)
class Sweep:
    param: str
    values: list


@dataclass(kw_only=True)
class CaseResult:
    id: str
    group: str
    label: str
    scene: str
    defines: dict
    res: int
    spp: int
    seeds: int
    max_depth: int
    summary: str
    estimators: list  # list[CaseRow], or list[SweepRow] for a sweep
    reference: CaseReference | None = optional()
    sweep: Sweep | None = optional()

