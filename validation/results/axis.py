"""The records of the budget axis (stages/budget_axis.py): relMSE against
wall time per render from a tenth of a second to a minute, per estimator,
measured or drawn from a checked model; a ranking at each budget and the
budgets where an estimator's efficiency crosses `path`'s."""

from __future__ import annotations

from dataclasses import dataclass, field

from .common import optional
from .speed import Interval, Placement


def seconds_text(t: float) -> str:
    """A budget as a reader says it: 0.1 s, 4.2 s, 60 s (the axis's notes
    and its section of the report)."""
    return f"{t:.2g} s" if t < 10 else f"{t:.0f} s"


@dataclass(kw_only=True)
class AxisPoint:
    """One estimator at one budget: K timed renders (``measured``), or its
    model's relMSE at the budget (not measured: no spp, no times)."""

    budget: float                       # seconds per render asked for
    measured: bool
    seconds: float                      # median wall time; the budget where modelled
    relmse: float                       # of one render (stats/axis.py)
    relmse_ci: Interval
    #: Log-scale standard error of relMSE·t (what its efficiency ratios read).
    log_se: float
    spp: int | None = optional()
    wall_seconds: list[float] = field(default_factory=list)
    efficiency_vs_path: float | None = optional()
    efficiency_vs_path_ci: Interval | None = optional()


@dataclass(kw_only=True)
class AxisModel:
    """relMSE(t) = c/(t − t0) fitted to a fixed-pdf estimator's points up to
    ``fitted_to`` seconds, checked by a point measured at ``checked_at``."""

    c: float
    t0: float
    log_se: float                       # of log c
    fitted_to: float
    checked_at: float | None = optional()
    predicted: float | None = optional()   # the model's relMSE there
    agrees: bool | None = optional()       # within both's 95 % intervals


@dataclass(kw_only=True)
class AxisCrossing:
    """Where an estimator's efficiency ÷ path changes sides: behind path
    (its interval below 1) at one budget, ahead (above 1) at another, ties
    between; ``seconds`` where the ratio passes 1 (stats/axis.py)."""

    estimator: str
    seconds: float
    overtakes: bool                     # True: better than path above it
    behind_at: float                    # a budget where its interval lies below 1
    ahead_at: float                     # ... and one where it lies above, ties between
    text: str


@dataclass(kw_only=True)
class AxisBudget:
    """The ranking at one budget, by efficiency 1/(relMSE·t) with ties."""

    seconds: float
    ranking: list[Placement]


@dataclass(kw_only=True)
class BudgetAxis:
    """The budget axis of one scene at the display resolution (minor
    version 21)."""

    res: int
    renders: int                        # K per estimator and measured budget
    budgets: list[float]                # seconds per render
    curves: dict[str, list[AxisPoint]]
    models: dict[str, AxisModel]
    rankings: list[AxisBudget]
    crossings: list[AxisCrossing]
    notes: list[str] = field(default_factory=list)
