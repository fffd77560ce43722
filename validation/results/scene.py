"""The records of a scene comparison: per estimator its metrics at every
rung of the spp ladder, the unbiasedness test and the convergence slope;
the reference; the speed stage's and the quadrature stage's records."""

from __future__ import annotations

from dataclasses import dataclass

from .cases import SunSplit
from .common import Outcome, ReferenceSummary, optional
from .learning import Learning
from .quadrature import Quadrature
from .axis import BudgetAxis
from .speed import Speed


@dataclass(kw_only=True)
class RunStats:
    """K renders of one estimator at one spp against the reference."""

    spp: int
    renders: int
    relmse: float
    relmse_per_render: list[float]
    mse: float
    mape: float
    bias: float
    bias_se: float
    variance_per_render: float
    nonfinite_fraction: float
    median_seconds: float
    seconds: list[float]
    samples_per_second: float
    efficiency: float
    reference_relmse: float        # what the reference's own noise adds to relmse
    firefly_fraction: float | None = None     # (None in runs before minor version 1)


@dataclass(kw_only=True)
class Unbiasedness(Outcome):
    """The batch-means test of all rungs pooled against the reference."""

    spp: int
    passed: bool
    pass_fraction: float
    min_p: float
    alpha: float
    alpha_pixel: float
    pooled_p: list[float]
    summary: str
    samples_per_pixel: int | None = optional()
    #: The verdict of checks/scene.py by the rules of evidence (minor version
    #: 3): pass | fail | inconclusive, why, rejected pixels by direction,
    #: fireflies over all rungs, and (inconclusive) samples per pixel that
    #: would see the tail.
    outcome: str = ""
    reason: str = ""
    rejected_up: int = 0
    rejected_down: int = 0
    tail_events: int = 0
    samples_needed: float | None = optional()
    #: The sequential test (minor version 8, stages/sequential.py): looks
    #: taken (samples_per_pixel: reached in all), the image mean's relative
    #: bias per channel and the half-width of its interval.
    looks: int = 1
    relative_bias: list[float] | None = optional()
    half_width: float | None = optional()
    #: On a map with a sun, where the real sun's test was not a pass: the
    #: same test at the ladder's top rung without the sun and with it
    #: widened (minor version 14, stages/sun_split.py).
    sun: SunSplit | None = optional()


@dataclass(kw_only=True)
class Convergence(Outcome):
    """Slope of log relMSE against log spp with its 95 % interval."""

    slope: float
    low: float
    high: float
    exact: bool
    consistent_with_mc: bool        # −1 inside the fitted interval (exact: true; none fitted: false)
    passed: bool
    outcome: str = ""               # checks.convergence.convergence_outcome (minor version 3)
    message: str = ""
    #: The sequential fit (minor version 16, stages/scene.py: settle_convergence):
    #: looks after the ladder, renders per rung in the fit, the most renders
    #: per rung the budget allows (0: none ran), the interval's lower end at
    #: the level a fail at that look reads (sequential.level), and whether the
    #: fireflies of all its renders resolve the tail (None: not read yet).
    looks: int = 0
    renders: int = 0
    budget_renders: int = 0
    low_spent: float | None = optional()
    tail_resolved: bool | None = optional()


@dataclass(kw_only=True)
class EstimatorResult:
    name: str
    params: dict
    compile_seconds: float
    runs: list[RunStats]
    unbiasedness: Unbiasedness
    convergence: Convergence

    @property
    def top(self) -> RunStats:
        """The run at the highest spp."""
        return self.runs[-1]


@dataclass(kw_only=True)
class SceneResult:
    name: str
    path: str
    summary: str
    res: int
    max_depth: int
    ladder: list[int]
    renders: int
    reference: ReferenceSummary
    estimators: list[EstimatorResult]
    speed: Speed | None = optional()
    #: relMSE against time from a tenth of a second to a minute, where the
    #: profile asks for it (stages/budget_axis.py; minor version 21).
    budget_axis: BudgetAxis | None = optional()
    quadrature: list[Quadrature] | None = optional()
    #: Estimators that learn their pdf: error against training (minor version 11).
    learning: list[Learning] | None = optional()
    #: A scene given by path: what the run took from where, and which
    #: estimators do not render it, in sentences (minor version 7).
    notes: list[str] | None = optional()

