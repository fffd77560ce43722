"""The checks of a validation run and the rules behind each verdict.

* :mod:`.evidence` — the rules of evidence: what a rejection of the
  batch-means test means (its direction, the tail its fireflies can carry,
  a sun not yet seen), the ±ε of a pass, and the failure-case verdicts;
* :mod:`.convergence` — how errors must fall: the relMSE slope of a Monte
  Carlo estimator, the bias limit and calibration of one biased by design;
* :mod:`.scene` — per scene × estimator: ``finite``, ``unbiased``,
  ``converges``; for an estimator biased by design ``bias_shrinks`` and
  ``calibrated`` instead;
* :mod:`.cases` — per failure case × estimator: ``refuses``, ``stable``;
  per parameter sweep ``finite``.

Each check reads only the records it names and gives one of three outcomes
with a message: **pass**, **fail**, or **inconclusive** (the evidence could
not decide within the sequential test's budget, stages/sequential.py; the
run stays green unless ``--strict``). Check ids
are ``<scene or case>/<estimator>/<what>``. To add a check: write it in
scene.py or cases.py beside its kind, and call it from that module's
``judge``.
"""

from __future__ import annotations

import numpy as np

from ..results import Check


def check(prefix: str, name: str, what: str, outcome, message: str) -> Check:
    """The check ``<prefix>/<name>/<what>`` with ``outcome`` "pass", "fail" or
    "inconclusive" (or a bool: pass or fail)."""
    if isinstance(outcome, (bool, np.bool_)):
        outcome = "pass" if outcome else "fail"
    return Check(id=f"{prefix}/{name}/{what}", passed=outcome != "fail", message=message,
                 outcome=outcome)


def by_estimator(found: list[Check]) -> list[Check]:
    """``found`` with every check of one estimator before the next's (in the
    order the estimators first appear; stable within each)."""
    names = list(dict.fromkeys(c.id.split("/")[1] for c in found))
    return sorted(found, key=lambda c: names.index(c.id.split("/")[1]))
