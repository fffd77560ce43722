"""The record of a whole run (results.json's top level) and its version."""

from __future__ import annotations

from dataclasses import dataclass, field

from .cases import CaseResult
from .common import OUTCOMES, Check, having, optional
from .scene import SceneResult

SCHEMA = "mcillum.results"
VERSION = 1
#: 1: ``minor_version``, ``estimator_facts``, ``firefly_fraction`` per run, and
#: in every failure-case row ``tail_ratio`` and the NaN/negative counts.
#: 2: per scene ``speed`` (the speed-and-images stage at the display
#: resolution); the small-image ``equal_time`` is no longer written.
#: 3: three outcomes (checks/): ``outcome`` on every check, unbiasedness,
#: convergence and failure-case test; ``seed_set``.
#: 4: each ranking place holds the efficiency and interval it was ranked by;
#: ``consistent_with_mc`` is false where no slope was fitted.
#: 5: per scene ``quadrature`` (estimators of N directions: equal rays, bias
#: against N, calibration of the posterior std); estimator facts ``unbiased``.
#: 6: ``executor`` (where the renders ran: local or ray, workers, nodes) and
#: per speed stage ``timed_on`` (the nodes that timed its renders).
#: 7: per scene ``notes`` (a scene given by path: settings, film, refusals).
#: 8: sequential tests: unbiasedness and each failure-case test carry
#: ``looks``, ``relative_bias`` and ``half_width``; a failure-case test its
#: ``samples_per_pixel`` reached.
#: 9: the speed stage's efficiency is net of the reference's noise, each
#: ratio has a ``kind``, each budget run its ``tries`` (corrections toward
#: the budget) and the stage the load other processes put on the machine
#: (``others_cores``, ``cores``, ``loaded``); ``rerun_seconds``.
#: 10: per quadrature estimator ``settings``: how it chose its settings for
#: the scene, and every candidate's held-out error.
#: 11: per scene ``learning`` (estimators that learn their pdf: relMSE at a
#: fixed spp against the training passes before it).
#: 12: a heavy-tail failure row's sun split may carry ``widened``,
#: ``widened_outcome``, ``widened_reason`` and ``widened_test``: the same test
#: with the map's sun widened, where the real sun's was inconclusive.
#: 13: a quadrature estimator's ``settings`` may carry ``glossy``: the
#: settings of the two sets at a glossy shading point.
#: 14: a scene estimator's unbiasedness may carry ``sun``: its sun split (as
#: a heavy-tail failure row's), where the scene's map has a sun and the real
#: sun's test did not pass.
#: 15: a quadrature estimator's ``equal_rays`` may carry ``baseline_read_at``:
#: the spp at which the baseline's error was measured (the ladder's top rung,
#: scaled by 1/N, where the scene's sampler is independent).
#: 16: a convergence record may carry ``looks``, ``renders``,
#: ``budget_renders``, ``low_spent`` and ``tail_resolved``: the fit continued
#: on more renders per rung where the ladder could not decide it.
#: 17: a quadrature's ``calibration`` carries ``spp`` (the rung below the
#: ladder's top, where the reference resolves the error bars at a quarter of
#: the cost) and each ``bias`` row its ``renders``.
#: 18: an efficiency ratio's ``kind`` may be ``heavy_tailed`` (its interval
#: then runs from 0: an upper bound).
#: 19: ``machine`` may carry ``speed``: the run's time for a fixed workload
#: (run/probe.py), where it timed renders.
#: 20: an efficiency ratio's ``kind`` may be ``off_budget``: withheld (ratio
#: and interval null) where a median wall time missed its budget beyond
#: stages/budgets.py EQUAL_TIME, its ``reason`` saying by how much.
#: 21: a scene may carry ``budget_axis``: relMSE against time per render
#: from a tenth of a second to a minute (stages/budget_axis.py).
MINOR_VERSION = 21


@dataclass(kw_only=True)
class EstimatorInfo:
    """The registry's facts of one estimator, as the run saw them."""

    display_name: str
    colour: str
    unreachable: list[str]
    max_direction_pdf: float | None
    unbiased: bool = True                  # False: biased by design (a quadrature)


@dataclass(kw_only=True)
class Results:
    created: str
    profile: str
    variant: str
    mitsuba_version: str
    drjit_version: str
    machine: dict
    alpha: float
    reference_fraction: float
    #: The run that rendered: a re-run into a finished directory that
    #: rendered nothing keeps the first run's and records its own as
    #: ``rerun_seconds``.
    wall_seconds: float
    scenes: list[SceneResult]
    checks: list[Check]
    failures: list[CaseResult] = field(default_factory=list)
    estimator_facts: dict[str, EstimatorInfo] = field(default_factory=dict)
    seed_set: int = 0
    #: Where the renders ran (run/executors.py: ``record()``).
    executor: dict = field(default_factory=lambda: {"kind": "local"})
    #: What each metric means (stats/metrics.py: ``DEFINITIONS``).
    definitions: dict[str, str] = field(default_factory=dict)
    rerun_seconds: float | None = optional()
    schema: str = SCHEMA
    version: int = VERSION
    minor_version: int = MINOR_VERSION

    @property
    def passed(self) -> bool:
        """No check failed (inconclusive ones do not count against it)."""
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[Check]:
        return having(self.checks, "fail")

    @property
    def inconclusive(self) -> list[Check]:
        return having(self.checks, "inconclusive")

    def counts(self) -> dict[str, int]:
        """How many checks had each outcome."""
        return {o: sum(c.outcome == o for c in self.checks) for o in OUTCOMES}

