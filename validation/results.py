"""What a validation run found, as dataclasses, and the files that hold it.

The pipeline builds these records; charts and the report read them. Only this
module turns them into files and back:

* ``results.json`` — :func:`to_json` / :func:`load`; schema
  ``validation/results.schema.json`` (JSON Schema 2020-12), documented in the
  README. ``version`` (major) changes when a field changes meaning, and
  readers refuse other majors; ``minor_version`` counts fields added since.
  JSON has no NaN or infinity: a non-finite number (an exact estimator's
  slope, an unbounded interval, the mean of a broken render) is written as
  null and read back as NaN.
* ``results.csv`` — one row per scene × estimator × spp;
* ``summary.md`` — for CI logs and pull requests;
* JUnit XML — one test case per check.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import types
import typing
from dataclasses import dataclass, field
from xml.sax.saxutils import escape, quoteattr

from mcillum import files
from mcillum.errors import UserError

from . import metrics

SCHEMA = "mcillum.results"
VERSION = 1
#: 1: ``minor_version``, ``estimator_facts``, ``firefly_fraction`` per run, and
#: in every failure-case row ``tail_ratio`` and the NaN/negative counts.
#: 2: per scene ``speed`` (the speed-and-images stage at the display
#: resolution); the small-image ``equal_time`` is no longer written.
#: 3: three outcomes (checks.py): ``outcome`` on every check, unbiasedness,
#: convergence and failure-case test; ``seed_set``.
#: 4: each ranking place holds the efficiency and interval it was ranked by;
#: ``consistent_with_mc`` is false where no slope was fitted.
#: 5: per scene ``quadrature`` (estimators of N directions: equal rays, bias
#: against N, calibration of the posterior std); estimator facts ``unbiased``.
#: 6: ``executor`` (where the renders ran: local or ray, workers, nodes) and
#: per speed stage ``timed_on`` (the nodes that timed its renders).
MINOR_VERSION = 6
SCHEMA_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results.schema.json")

DEFINITIONS = {
    "mse": "mean over pixels and channels of (x - r)^2",
    "relmse": f"mean of (x - r)^2 / (r^2 + {metrics.EPSILON}) (tev convention)",
    "mape": f"mean of |x - r| / (|r| + {metrics.EPSILON})",
    "bias": "image mean of (mean of K renders - reference), with standard error",
    "variance_per_render": "mean over pixels of the sample variance over K renders",
    "nonfinite_fraction": "share of NaN/Inf values in the K renders (must be 0)",
    "firefly_fraction": "share of pixels of all renders brighter than 10x the reference there",
    "efficiency": "1 / (relmse * median seconds per render)",
    "unbiasedness": "per-pixel-channel Welch t-tests (Sidak) + pooled per-channel tests "
                    "(Bonferroni), family-wise alpha, variances from each side's own renders",
    "slope": "least-squares slope of log relmse vs log spp, Student-t interval",
}


def _optional(default=None):
    """A field left out of the JSON while it is None."""
    return field(default=default, metadata={"omit_none": True})


def _flat(default=None):
    """A record whose fields are written into its parent's JSON object."""
    return field(default=default, metadata={"flatten": True})


# -------------------------------- Checks --------------------------------------

#: The three outcomes of a check (checks.py decides which).
OUTCOMES = ("pass", "fail", "inconclusive")


class _Outcome:
    """Records with ``passed`` and ``outcome``: a file from before minor
    version 3 has no outcome, which then reads pass or fail from ``passed``."""

    def __post_init__(self):
        if not self.outcome:
            self.outcome = "pass" if self.passed else "fail"


@dataclass
class Check(_Outcome):
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


# ---------------------------- Scene comparisons -------------------------------

@dataclass
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


@dataclass
class Unbiasedness(_Outcome):
    """The batch-means test of all rungs pooled against the reference."""

    spp: int
    passed: bool
    pass_fraction: float
    min_p: float
    alpha: float
    alpha_pixel: float
    pooled_p: list[float]
    summary: str
    samples_per_pixel: int | None = _optional()
    #: checks.py's reading of the test (minor version 3): pass | fail |
    #: inconclusive, why, rejected pixels by direction, fireflies over all
    #: rungs, and (inconclusive) samples per pixel that would see the tail.
    outcome: str = ""
    reason: str = ""
    rejected_up: int = 0
    rejected_down: int = 0
    tail_events: int = 0
    samples_needed: float | None = _optional()


@dataclass
class Convergence(_Outcome):
    """Slope of log relMSE against log spp with its 95 % interval."""

    slope: float
    low: float
    high: float
    exact: bool
    consistent_with_mc: bool        # −1 inside the fitted interval (exact: true; none fitted: false)
    passed: bool
    outcome: str = ""               # checks.convergence_outcome (minor version 3)
    message: str = ""


@dataclass
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


@dataclass
class ReferenceSummary:
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


class Interval(typing.NamedTuple):
    """A 95 % confidence interval; JSON: [low, high]."""

    low: float
    high: float


@dataclass
class CostModel:
    """t(spp) = fixed_s + per_spp_s · spp of warm renders at the display
    resolution (see costs.py), with 95 % bootstrap intervals."""

    fixed_s: float
    per_spp_s: float
    fixed_s_ci: Interval
    per_spp_s_ci: Interval
    timings: dict[str, list[float]]     # spp → wall seconds of each timed repeat


@dataclass
class BudgetRun:
    """K renders of one estimator at one time budget."""

    spp: int
    wall_seconds: list[float]
    relmse: float                       # mean over the K renders
    relmse_ci: Interval
    relmse_per_render: list[float]
    on_budget: bool                     # median wall time within ±10 % of the budget
    note: str | None = _optional()      # why not, where it is not


@dataclass
class Budget:
    """One equal-time budget: the time `path` needs for ``path_spp``."""

    seconds: float
    path_spp: int
    estimators: dict[str, BudgetRun]
    reference_relmse: float             # relMSE the reference's own noise adds


@dataclass
class Ratio:
    ratio: float
    ci: Interval


@dataclass
class Placement:
    """One estimator's place in a ranking: 1 + the number of estimators whose
    interval lies wholly above its own; those it cannot be told from."""

    estimator: str
    rank: int
    tied_with: list[str]
    efficiency: float | None = _optional()     # 1/(relMSE·t), what it was ranked by
    ci: Interval | None = _optional()          # (minor version 4)


@dataclass
class Speed:
    """The speed-and-images stage of one scene (speed.py)."""

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
    #: executors.py).
    timed_on: list[str] = field(default_factory=list)


@dataclass
class EqualRays:
    """A point-set estimator against ``baseline`` at the same number of traced
    directions per pixel (quadrature.py)."""

    baseline: str
    baseline_spp: int            # N · spp
    relmse: float                # each less the reference's relative variance
    baseline_relmse: float
    ratio: float                 # relmse / baseline_relmse (< 1: the set wins)
    ratio_low: float             # 95 % interval
    ratio_high: float
    seconds: float               # median per render
    baseline_seconds: float


@dataclass
class BiasAtN:
    directions: int
    rms_bias: float              # noise-corrected rms over pixels, / rms of the reference
    rms_bias_se: float
    mean_bias: float             # signed, image mean, / the reference's image mean


@dataclass
class Calibration:
    """Measured RMSE over predicted posterior std, per pixel."""

    median: float
    q25: float
    q75: float
    pixels: int
    verdict: str                 # calibrated | over-confident | under-confident | exact …


@dataclass
class Quadrature:
    """What the quadrature stage measured of one estimator of N directions."""

    name: str
    directions: int
    spp: int
    renders: int
    equal_rays: EqualRays | None = _optional()
    bias: list[BiasAtN] | None = _optional()
    calibration: Calibration | None = _optional()


@dataclass
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
    speed: Speed | None = _optional()
    quadrature: list[Quadrature] | None = _optional()


# ------------------------------ Failure cases ---------------------------------

@dataclass
class Percentiles:
    mean: float
    median: float
    p90: float
    p99: float
    max: float


@dataclass
class SppToMatch:
    spp: float
    low: float
    high: float
    level: float


@dataclass
class BatchTest(_Outcome):
    """The batch-means test of K renders and, where it rejected, its replication
    in K fresh renders (``replicated`` None: nothing needed replicating)."""

    passed: bool
    pass_fraction: float
    min_p: float
    pooled_p: list[float]
    alpha_pixel: float
    test: str
    rejected_pixels: int = 0
    replicated_pixels: int = 0
    replicated: bool | None = None
    replication_test: str | None = _optional()
    #: checks.bias_outcome of the first test (minor version 3), as in Unbiasedness
    outcome: str = ""
    reason: str = ""
    tail_events: int = 0
    samples_needed: float | None = _optional()
    counted_up: bool = False        # an upward rejection counted (checks.py)


@dataclass
class SunSplit:
    """The same estimator re-tested on the map without its sun."""

    sun: dict                      # envmaps.sun.split facts: solid_angle, texels, …
    sunless_passed: bool
    sunless_test: str
    sunless_reference_mean: float
    expected_sun_hits_per_pixel: float | None
    sun_share_of_image: float
    sunless_outcome: str = ""      # checks.bias_outcome there (minor version 3)
    sunless_reason: str = ""


@dataclass
class TailNumbers:
    """How one estimator's error spreads over K seeds (see tails.py)."""

    relmse: Percentiles
    firefly_fraction: float
    samples_per_pixel: int
    seeds: int
    seconds_median: float
    image_mean_ratio: float | None
    spp_to_match_path: SppToMatch | None
    nonfinite_values: int = 0
    negative_values: int = 0
    missing_fraction: float | None = _optional()
    tail_ratio: float | None = _optional()
    test: BatchTest | None = _flat()
    sun: SunSplit | None = _flat()


@dataclass
class CaseRow:
    """One estimator in a failure case."""

    name: str
    refused: bool
    verdict: str = ""
    message: str | None = _optional()
    numbers: TailNumbers | None = _optional()
    images: dict[str, str] = field(default_factory=dict)


@dataclass
class SweepRow:
    """One estimator along a swept parameter."""

    name: str
    relmse: list[float]
    seconds: list[float]
    growth: float | None
    nonfinite_values: int
    images: dict[str, str]
    verdict: str


@dataclass
class CaseReference:
    spp: int
    capped: str | None


@dataclass
class Sweep:
    param: str
    values: list


@dataclass
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
    reference: CaseReference | None = _optional()
    sweep: Sweep | None = _optional()


# -------------------------------- The run -------------------------------------

@dataclass
class EstimatorInfo:
    """The registry's facts of one estimator, as the run saw them."""

    display_name: str
    colour: str
    unreachable: list[str]
    max_direction_pdf: float | None
    unbiased: bool = True                  # False: biased by design (a quadrature)


@dataclass
class Results:
    created: str
    profile: str
    variant: str
    mitsuba_version: str
    drjit_version: str
    machine: dict
    alpha: float
    reference_fraction: float
    wall_seconds: float
    scenes: list[SceneResult]
    checks: list[Check]
    failures: list[CaseResult] = field(default_factory=list)
    estimator_facts: dict[str, EstimatorInfo] = field(default_factory=dict)
    seed_set: int = 0
    #: Where the renders ran (executors.py: ``describe()``).
    executor: dict = field(default_factory=lambda: {"kind": "local"})
    definitions: dict[str, str] = field(default_factory=lambda: dict(DEFINITIONS))
    schema: str = SCHEMA
    version: int = VERSION
    minor_version: int = MINOR_VERSION

    @property
    def passed(self) -> bool:
        """No check failed (inconclusive ones do not count against it)."""
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if c.outcome == "fail"]

    @property
    def inconclusive(self) -> list[Check]:
        return [c for c in self.checks if c.outcome == "inconclusive"]

    def counts(self) -> dict[str, int]:
        """How many checks had each outcome."""
        return {o: sum(c.outcome == o for c in self.checks) for o in OUTCOMES}


# ------------------------------ JSON, both ways --------------------------------

def to_json(record) -> dict:
    """A record as the JSON object results.json holds (see the schema)."""
    out = _encode(record)
    if isinstance(record, Results):
        out["passed"] = record.passed
    return out


def _encode(value):
    if dataclasses.is_dataclass(value):
        out = {}
        for f in dataclasses.fields(value):
            item = getattr(value, f.name)
            if item is None and f.metadata.get("omit_none"):
                continue
            if f.metadata.get("flatten"):
                if item is not None:
                    out.update(_encode(item))
                continue
            out[f.name] = _encode(item)
        return out
    if isinstance(value, dict):
        return {str(k): _encode(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v) for v in value]
    if hasattr(value, "item"):              # numpy scalars
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None                         # (JSON has no NaN or infinity)
    return value


def _decode(hint, data):
    """``data`` (from JSON) as the type ``hint`` describes."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        empty = data == {} and dataclasses.is_dataclass(args[0])   # (older files)
        return None if data is None or empty else _decode(args[0], data)
    if hint is float and data is None:
        return math.nan                     # written as null (see the module doc)
    if isinstance(hint, type) and issubclass(hint, tuple) and hasattr(hint, "_fields"):
        return hint(*(math.nan if v is None else v for v in data))   # an Interval
    if dataclasses.is_dataclass(hint):
        return from_json(hint, data)
    if origin is list:
        (item,) = typing.get_args(hint) or (typing.Any,)
        return [_decode(item, v) for v in data]
    if origin is dict:
        _, item = typing.get_args(hint) or (str, typing.Any)
        return {k: _decode(item, v) for k, v in data.items()}
    return data


def from_json(cls, data: dict):
    """A record of dataclass ``cls`` from its JSON object (inverse of
    :func:`to_json`); unknown keys are ignored, missing ones raise KeyError."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if f.metadata.get("flatten"):
            inner = [a for a in typing.get_args(hint) if a is not type(None)][0]
            required = [g.name for g in dataclasses.fields(inner)
                        if g.default is dataclasses.MISSING
                        and g.default_factory is dataclasses.MISSING]
            kwargs[f.name] = from_json(inner, data) if all(k in data for k in required) \
                else None
        elif f.name in data:
            kwargs[f.name] = _decode(hint, data[f.name])
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise KeyError(f.name)
    record = cls(**kwargs)
    if cls is CaseResult:                   # rows of a sweep or of a case
        row = SweepRow if record.sweep is not None else CaseRow
        record.estimators = [from_json(row, r) for r in data["estimators"]]
    return record


class ResultsError(UserError, ValueError):
    """results.json is unreadable, of another version, or incomplete."""


class NoResultsError(ResultsError, FileNotFoundError):
    """The directory holds no results.json (the command line names no run)."""

    usage = True


def load(run_dir: str) -> Results:
    """The :class:`Results` of ``run_dir/results.json``; :class:`ResultsError`
    says what is wrong with it and what to do."""
    path = os.path.join(run_dir, "results.json")
    again = f"run `mcillum validate --out {run_dir}` again"
    if not os.path.isfile(path):
        raise NoResultsError(f"no results.json in {run_dir}: run `mcillum validate "
                             f"--out {run_dir}` first")
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (ValueError, UnicodeDecodeError) as err:
        raise ResultsError(f"{path} is not valid JSON ({err}): {again}") from None
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise ResultsError(f"{path} is not an mcillum results file (no \"schema\": "
                           f"\"{SCHEMA}\")")
    if data.get("version") != VERSION:
        raise ResultsError(f"{path} has results version {data.get('version')!r}; this "
                           f"mcillum reads version {VERSION}: {again}")
    try:
        record = from_json(Results, data)
        record.minor_version = data.get("minor_version", 0)
        return record
    except KeyError as err:
        raise ResultsError(f"{path} lacks the field {err}: {again}") from None


# ---------------------------------- Files -------------------------------------

def write_json(path: str, results: Results) -> None:
    files.write_text(path, json.dumps(to_json(results), indent=2, allow_nan=False,
                                      default=float) + "\n")


CSV_FIELDS = ["scene", "estimator", "spp", "renders", "relmse", "mse", "mape", "bias",
              "bias_se", "variance_per_render", "nonfinite_fraction", "median_seconds",
              "samples_per_second", "efficiency"]


def write_csv(path: str, results: Results) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, CSV_FIELDS)
    w.writeheader()
    for scene in results.scenes:
        for est in scene.estimators:
            for run in est.runs:
                w.writerow({"scene": scene.name, "estimator": est.name,
                            **{k: getattr(run, k) for k in CSV_FIELDS[2:]}})
    files.write_text(path, buf.getvalue())


def summary(results: Results) -> str:
    """summary.md: the verdict, then a table per scene and the failures group."""
    checks, failed, n = results.checks, results.failed, results.counts()
    lines = [f"# mcillum validation — profile {results.profile}",
             "",
             f"{n['pass']} of {len(checks)} checks pass, {n['inconclusive']} inconclusive, "
             f"{n['fail']} fail; "
             f"{results.variant}, mitsuba {results.mitsuba_version}, "
             f"drjit {results.drjit_version}, {results.wall_seconds:.0f} s.", ""]
    for scene in results.scenes:
        ref = scene.reference
        capped = f", capped: {ref.capped}" if ref.capped else ""
        lines += [f"## {scene.name} ({scene.res}², max_depth {scene.max_depth})",
                  "", f"Reference: `path`, {ref.spp} spp in {ref.passes} passes{capped}.",
                  "",
                  "| estimator | relMSE @ top spp | bias ± se | unbiased (pass %) | slope [95% CI] "
                  "| samples/s | efficiency |",
                  "|---|---|---|---|---|---|---|"]
        for est in scene.estimators:
            top, u, c = est.top, est.unbiasedness, est.convergence
            facts = results.estimator_facts.get(est.name)
            by_design = facts is not None and not facts.unbiased
            lines.append(
                f"| {est.name} | {top.relmse:.3g} | {top.bias:+.2e} ± {top.bias_se:.1e} | "
                + ("biased by design " if by_design else f"{_word(u.outcome)} ")
                + f"({100 * u.pass_fraction:.1f}) | "
                + ("exact" if c.exact else
                   ("not tested " if by_design else f"{_word(c.outcome)} ") +
                   f"{c.slope:+.2f} [{c.low:+.2f}, {c.high:+.2f}]")
                + f" | {top.samples_per_second / 1e6:.2f} M | {top.efficiency:.3g} |")
        if scene.speed:
            lines += ["", *speed_summary(scene.speed)]
        for q in scene.quadrature or []:
            lines += ["", quadrature_summary(q)]
        lines.append("")
    if results.failures:
        lines += ["## Where methods fail", "",
                  "| case | estimator | verdict | relMSE median / p99 / max | fireflies "
                  "| spp to match path |", "|---|---|---|---|---|---|"]
        for case in results.failures:
            for est in case.estimators:
                lines.append(f"| {case.label} | {est.name} | {est.verdict} | "
                             f"{_failure_cells(case, est)} |")
        lines.append("")
    if failed:
        lines += ["## Failed checks", ""] + [f"- `{c.id}`: {c.message}" for c in failed]
    if results.inconclusive:
        lines += ["", "## Inconclusive at this budget", ""] + \
            [f"- `{c.id}`: {c.message}" for c in results.inconclusive]
    return "\n".join(lines) + "\n"


def _word(outcome: str) -> str:
    """pass, **FAIL** or *inconclusive* for summary.md."""
    return {"fail": "**FAIL**", "inconclusive": "*inconclusive*"}.get(outcome, outcome)


def ranking_text(ranking: list[Placement]) -> str:
    """"a > b = c > d": ">" where the intervals separate, "=" for a tie."""
    out = ""
    for i, p in enumerate(ranking):
        if i:
            tied = ranking[i - 1].estimator in p.tied_with
            out += " = " if tied else " > "
        out += p.estimator
    return out


def quadrature_summary(q: Quadrature) -> str:
    """One line of what the quadrature stage measured of ``q.name``."""
    parts = []
    if q.equal_rays:
        r = q.equal_rays
        parts.append(f"relMSE {r.ratio:.3g}× {r.baseline}'s at equal rays "
                     f"[{r.ratio_low:.3g}, {r.ratio_high:.3g}]")
    if q.bias:
        parts.append("rms bias " + ", ".join(f"{100 * b.rms_bias:.2f} % at N = {b.directions}"
                                             for b in q.bias))
    if q.calibration:
        c = q.calibration
        parts.append(f"posterior std {c.verdict} (RMSE/std median {c.median:.2f})")
    return f"{q.name} (N = {q.directions}, {q.spp} spp): " + "; ".join(parts) + "."


def speed_summary(speed: Speed) -> list[str]:
    """The speed stage's lines of summary.md: budgets, ratios, ranking, notes."""
    top = speed.budgets[-1]
    lines = [f"Equal time at {speed.res}² ({', '.join(f'{b.seconds * 1e3:.0f}' for b in speed.budgets)}"
             f" ms per render, K = {speed.renders}); at {top.seconds * 1e3:.0f} ms, most "
             f"efficient first: {ranking_text(speed.ranking)}.", "",
             "| estimator | spp | wall ms (median) | relMSE [95% CI] | efficiency ÷ path [95% CI] |",
             "|---|---|---|---|---|"]
    for name, run in top.estimators.items():
        r = speed.efficiency_vs_path.get(name)
        ratio = f"{r.ratio:.3g} [{r.ci.low:.3g}, {r.ci.high:.3g}]" if r else "—"
        wall = sorted(run.wall_seconds)[len(run.wall_seconds) // 2] * 1e3
        lines.append(f"| {name} | {run.spp} | {wall:.0f}{'' if run.on_budget else ' (off budget)'}"
                     f" | {run.relmse:.3g} [{run.relmse_ci.low:.3g}, {run.relmse_ci.high:.3g}]"
                     f" | {ratio} |")
    return lines + [f"- {n}" for n in speed.notes]


def _failure_cells(case: CaseResult, est) -> str:
    if case.sweep is not None:
        return (f"relMSE {', '.join(f'{r:.3g}' for r in est.relmse)} over {case.sweep.param} = "
                f"{', '.join(str(v) for v in case.sweep.values)} | | ")
    n = est.numbers
    if n is None:
        return " | | "
    r, m = n.relmse, n.spp_to_match_path
    return (f"{r.median:.3g} / {r.p99:.3g} / {r.max:.3g} | {100 * n.firefly_fraction:.3f} % | "
            + (f"{m.spp:.3g} [{m.low:.3g}, {m.high:.3g}]" if m else "never (biased)"))


def write_junit(path: str, results: Results, strict: bool = False) -> None:
    """One test case per check: a fail is a <failure>, an inconclusive check a
    <skipped> with its reason (a <failure> with ``strict``)."""
    checks = results.checks
    n = results.counts()
    failures = n["fail"] + (n["inconclusive"] if strict else 0)
    skipped = 0 if strict else n["inconclusive"]
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<testsuite name="mcillum.validate.{results.profile}" tests="{len(checks)}" '
           f'failures="{failures}" skipped="{skipped}" time="{results.wall_seconds:.3f}">']
    for c in checks:
        scene, _, rest = c.id.partition("/")
        out.append(f'  <testcase classname={quoteattr("mcillum." + scene)} '
                   f'name={quoteattr(rest)}>')
        if c.outcome == "fail" or (strict and c.outcome == "inconclusive"):
            out.append(f'    <failure message={quoteattr(c.message)}>'
                       f'{escape(c.message)}</failure>')
        elif c.outcome == "inconclusive":
            out.append(f'    <skipped message={quoteattr("inconclusive: " + c.message)}/>')
        out.append("  </testcase>")
    out.append("</testsuite>")
    files.write_text(path, "\n".join(out) + "\n")
