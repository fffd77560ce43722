"""What every record of a run shares: the three outcomes, a check, the
summary of a reference, and the two kinds of field that results.json writes
in its own way."""

from __future__ import annotations

from dataclasses import dataclass, field


def optional(default=None):
    """A field left out of the JSON while it is None."""
    return field(default=default, metadata={"omit_none": True})


def flat(default=None):
    """A record whose fields are written into its parent's JSON object."""
    return field(default=default, metadata={"flatten": True})


#: The three outcomes of a check (the checks package decides which).
OUTCOMES = ("pass", "fail", "inconclusive")


class Outcome:
    """Records with ``passed`` and ``outcome``: a file from before minor
    version 3 has no outcome, which then reads pass or fail from ``passed``."""

    def __post_init__(self):
        if not self.outcome:
            self.outcome = "pass" if self.passed else "fail"


@dataclass(kw_only=True)
class Check(Outcome):
    """One verdict of the run: ``id`` is ``<scene or case>/<estimator>/<what>``;
    ``outcome`` one of :data:`OUTCOMES`. ``passed`` is "did not fail": true
    for pass and for inconclusive (the evidence could not decide), which
    is what the exit code and JUnit go by unless ``--strict``."""

    id: str
    passed: bool
    message: str
    outcome: str = ""

    def __post_init__(self):
        super().__post_init__()
        if self.outcome not in OUTCOMES:
            raise ValueError(f"check outcome must be one of {OUTCOMES}, got {self.outcome!r}")
        self.passed = self.outcome != "fail"


def having(checks, outcome: str) -> list[Check]:
    """The checks of ``checks`` whose outcome is ``outcome``."""
    return [c for c in checks if c.outcome == outcome]


@dataclass(kw_only=True)
class ReferenceSummary:
    """A `path` reference as the results record it: its samples, passes,
    time, the precision it was rendered to, and the cap it hit, if any."""

    integrator: str
    spp: int
    passes: int
    spp_per_pass: int
    seconds: float
    cached_passes: int
    rendered_passes: int
    target_variance: float
    achieved_variance: float
    capped: str | None
    key: str
