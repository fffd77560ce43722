"""The records of the speed-and-images stage (stages/speed.py): the cost
model, the equal-time budgets, efficiency against `path` and the ranking."""

from __future__ import annotations

import typing
from dataclasses import dataclass, field

from .common import ReferenceSummary, optional


class Interval(typing.NamedTuple):
    """A 95 % confidence interval; JSON: [low, high]."""

    low: float
    high: float


@dataclass(kw_only=True)
class CostModel:
    """t(spp) = fixed_s + per_spp_s · spp of warm renders at the display
    resolution (see stats/costs.py), with 95 % bootstrap intervals."""

    fixed_s: float
    per_spp_s: float
    fixed_s_ci: Interval
    per_spp_s_ci: Interval
    timings: dict[str, list[float]]     # spp → wall seconds of each timed repeat


@dataclass(kw_only=True)
class Try:
    """One set of K timed renders of an estimator at a budget: the spp the
    cost model (first try) or the times of the tries before (secant)
    chose, and what they took."""

    spp: int
    wall_seconds: list[float]
    #: Cores other processes used on average meanwhile (run/load.py; None:
    #: unknown, not Linux).
    others_cores: float | None = None


@dataclass(kw_only=True)
class BudgetRun:
    """K renders of one estimator at one time budget: the try whose median
    came nearest the budget."""

    spp: int
    wall_seconds: list[float]
    relmse: float                       # mean over the K renders
    relmse_ci: Interval
    relmse_per_render: list[float]
    on_budget: bool                     # median wall time within ±10 % of the budget
    note: str | None = optional()      # why not, where it is not
    #: Every try in order, the measured one among them (minor version 9).
    tries: list[Try] = field(default_factory=list)


@dataclass(kw_only=True)
class Budget:
    """One equal-time budget: the time `path` needs for ``path_spp``."""

    seconds: float
    path_spp: int
    estimators: dict[str, BudgetRun]
    reference_relmse: float             # relMSE the reference's own noise adds
    reference_relmse_se: float = 0.0   # its standard error (stats/costs.py)


#: What an efficiency figure means (Ratio.kind).
KINDS = {
    "unbiased": "1/(relMSE·t), relMSE net of the reference's noise",
    "reference_limited": "its error is within 2x of the reference's own noise: "
                         "a lower bound (the estimator may be exact here)",
    "biased": "biased by design: relMSE includes bias², which more time does not "
              "remove, so the figure holds at this budget only",
    "heavy_tailed": "rare large errors (fireflies) carry its error, with a tail K renders "
                    "cannot bound: an upper bound (its mean error may be larger than "
                    "they show)",
    "off_budget": "withheld: its renders' median wall time (or path's) missed the budget "
                  "by more than the stage's tolerance (stages/budgets.py EQUAL_TIME) after "
                  "every correction: not an equal-time figure",
}


@dataclass(kw_only=True)
class Ratio:
    ratio: float                        # NaN: withheld (kind off_budget)
    ci: Interval                        # high = inf: a lower bound; low = 0: an upper one
    kind: str = "unbiased"              # a key of KINDS (minor version 9)
    reason: str | None = optional()    # why withheld (off_budget, minor version 20)


@dataclass(kw_only=True)
class Placement:
    """One estimator's place in a ranking: 1 + the number of estimators whose
    interval lies wholly above its own; those it cannot be told from."""

    estimator: str
    rank: int
    tied_with: list[str]
    efficiency: float | None = optional()     # 1/(relMSE·t), what it was ranked by
    ci: Interval | None = optional()          # (minor version 4)


@dataclass(kw_only=True)
class Speed:
    """The speed-and-images stage of one scene (stages/speed.py)."""

    res: int
    renders: int                        # K per estimator and budget
    cost_model: dict[str, CostModel]
    budgets: list[Budget]
    efficiency_vs_path: dict[str, Ratio]   # at the largest budget
    ranking: list[Placement]               # by efficiency at the largest budget
    reference: ReferenceSummary
    mean_flip: dict[str, float]            # at the largest budget, first render
    notes: list[str] = field(default_factory=list)   # overhead and budget misses
    #: The nodes whose renders were timed (one, unless a worker moved;
    #: run/executors.py).
    timed_on: list[str] = field(default_factory=list)
    #: Cores other processes used on average during the timed renders
    #: (cost model and budgets; run/load.py), of ``cores``; None: unknown.
    others_cores: float | None = optional()
    cores: int | None = optional()
    loaded: bool = False                # others_cores above LOADED (stages/speed.py)

