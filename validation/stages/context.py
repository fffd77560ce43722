"""The context of one scene run or failure case on its way through the stages.

:class:`Run` holds what every context of one ``mcillum validate`` shares (the
profile, the variant, where files go, progress). :class:`Context` is one
scene of a profile (a :class:`~mcillum.validation.plan.profiles.SceneRun`) or
one failure case (a :class:`~mcillum.validation.plan.profiles.FailureCase`):
what it renders, and what each stage has found so far. Every field below the
line "filled by the stages" names the stage that fills it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..plan import seeds
from ..plan.plans import Sequential
from ..results import layout
from ..run import jobs
from ..run.executors import Local


@dataclass
class Run:
    """What every context of one validation run shares."""

    profile: object                 # plan.profiles.Profile
    variant: str
    cache_dir: str                  # references and generated maps
    out_dir: str                    # the run's --out
    progress: object = None         # progress.Progress, or None (silent)
    #: Where the renders run (run/executors.py); this process unless told.
    executor: object = field(default_factory=Local)
    #: ``--budget``: a sequential test's budget, × its first look's samples
    #: per pixel, for every check (None: the profile's ``[sequential]``).
    budget: float | None = None
    #: ``--seed-set``: which independent repeat every seed stream hands out
    #: (plan/seeds.py; :meth:`stream`).
    seed_set: int = 0
    #: Renders done by this process and renders loaded from the run
    #: directory (stacks.kept): a run that rendered none is a re-run.
    rendered: int = 0
    kept: int = 0
    #: The machine's time for a fixed workload (run/probe.py), taken before
    #: the run's first timed render; None while nothing was timed.
    machine_speed: dict | None = None

    @property
    def sequential(self):
        """The profile's :class:`~mcillum.validation.plan.plans.Sequential`."""
        return getattr(self.profile, "sequential", None) or Sequential()

    def growth(self, profile_budget: float) -> float:
        """The budget of a sequential test: ``--budget``, else the profile's."""
        return self.budget if self.budget is not None else profile_budget

    def stream(self, name: str, block: int = 0) -> seeds.Stream:
        """Block ``block`` of seed stream ``name`` in the run's seed set."""
        return seeds.stream(name, block, self.seed_set)

    def step(self, what: str, steps: int = 1) -> None:
        if self.progress is not None:
            self.progress(what, steps)

    def stage(self, ctx: "Context", name: str) -> None:
        """Stage ``name`` of ``ctx`` starts (a line in a log: progress.py)."""
        if self.progress is not None:
            self.progress.stage(ctx.where, name, ctx.label)


@dataclass
class Context:
    run: Run
    plan: object                    # plan.profiles.SceneRun or FailureCase
    id: str                         # scene name or case id: the prefix of its checks
    estimators: list[str]           # asked for, `path` last
    defines: dict = field(default_factory=dict)   # $-parameters besides res
    label: str = ""                 # what progress lines call it
    #: Seed streams (plan/seeds.py) of its K renders and of the batches a
    #: sequential test adds (stages/sequential.py).
    streams: dict = field(default_factory=lambda: {"renders": "failure",
                                                   "sequential": "sequential"})

    # ----------------------- filled by the stages ---------------------------
    info: object = None             # load: plan.scenes.SceneInfo
    resolved: dict = None           # load: $-parameters as Mitsuba gets them
    scene: object = None            # load: the mi.Scene
    scene_key: str = ""             # load: content hash (run.references.cache_key)
    render_key: str = ""            # load: the same over the renders' code (its kept renders)
    scene_spec: object = None       # load: run.jobs.SceneSpec, the scene as a worker loads it
    params: dict = None             # load: integrator properties ({"max_depth": d})
    #: choose_estimators / probe_refusals: name → jobs.Integrator
    integrators: dict = field(default_factory=dict)
    refused: dict = field(default_factory=dict)       # probe_refusals: name → error
    compile_seconds: dict = field(default_factory=dict)  # render_*: first render each
    stacks: dict = field(default_factory=dict)        # render_*: spp → name → run.stacks.Stack
    reference: object = None        # build_reference: run.references.Reference
    measured: dict = field(default_factory=dict)      # measure: name → EstimatorResult
    #: measure, replicate: name → checks.evidence.Evidence, what the verdicts read
    evidence: dict = field(default_factory=dict)
    quadrature: dict = field(default_factory=dict)    # quadrature.measure: name → Quadrature
    learning: dict = field(default_factory=dict)      # learning.measure: name → Learning
    rows: dict = field(default_factory=dict)          # tail_numbers …: name → CaseRow
    per_render: dict = field(default_factory=dict)    # tail_numbers: name → relMSE per seed
    sunless: "Context" = None       # sun_split.sunless_twin: on its map without the sun
    sun: dict = None                # sun_split.find_sun: the sun's facts (None: no sun)
    sunless_map: str = None         # sun_split.find_sun: the map without it
    widened: "Context" = None       # sun_split.widened_twin: with its sun widened
    #: sun_split.widened_twin: this context's map holds the widened sun (some
    #: pixels see it only through a sliver: checks.sun.partly_hidden)
    disc: bool = False
    sweep_rows: list = field(default_factory=list)    # cases.sweep_rows: SweepRow per estimator
    display: "Context" = None       # speed.display: the scene at the display resolution
    speed: object = None            # speed.measure_speed: results.Speed
    timings: dict = None            # speed.time_costs: name → {spp: [seconds]}
    costs: dict = field(default_factory=dict)         # speed.time_costs: name → CostModel
    budget_path_spp: list = None    # speed.time_costs: path's spp at each budget
    budgets: list = field(default_factory=list)       # speed.render_budgets: (T, path spp)
    budget_stacks: list = field(default_factory=list)  # speed.render_budgets: name → Stack each
    budget_tries: list = field(default_factory=list)   # speed.render_budgets: name → [Try] each
    timing_load: list = field(default_factory=list)    # speed.time_costs: (seconds, others)
    flip_maps: dict = field(default_factory=dict)     # speed.measure_speed: name → (H, W)
    timed_on: list = field(default_factory=list)      # speed.render_budgets: nodes that timed
    notes: list = field(default_factory=list)         # speed.*: what did not hold
    #: budget_axis.render_axis: name → [(budget, Stack, [Try])] of its measured budgets
    axis_renders: dict = field(default_factory=dict)
    axis_notes: list = field(default_factory=list)    # budget_axis.*: what did not hold
    axis_models: dict = field(default_factory=dict)   # budget_axis.render_axis: name → AxisModel
    budget_axis: object = None      # budget_axis.measure_axis: results.BudgetAxis
    #: pipeline, choose_estimators: what a user's scene's result says (its
    #: settings and film, estimators that do not render it, settings not taken)
    scene_notes: list = field(default_factory=list)
    checks: list = field(default_factory=list)        # pipeline, by checks/: results.Check

    @property
    def scene_name(self) -> str:
        return self.plan.scene

    @property
    def res(self) -> int:
        return self.plan.res

    @property
    def max_depth(self) -> int:
        return self.plan.max_depth

    @property
    def is_case(self) -> bool:
        """A failure case (or a point of one's sweep), not a scene comparison."""
        return hasattr(self.plan, "group")

    @property
    def where(self) -> str:
        """What progress lines call this context: a case's label (it names
        its group), or "scene" and the scene's label."""
        return self.label if self.is_case else f"scene {self.label}"

    @property
    def images_dir(self) -> str:
        """Where this context's images go (results/layout.py; created on
        first use)."""
        where = layout.case_dir if self.is_case else layout.images_dir
        return layout.made(where(self.run.out_dir, self.id))

    def job(self, integrator, spp: int, seed: int) -> "jobs.Job":
        """One render of this context's scene with ``integrator`` (a
        :class:`~mcillum.validation.run.jobs.Integrator`)."""
        return jobs.Job(self.scene_spec, integrator, spp, seed, live=self.scene)

    def render(self, batch: list, label: str = "", timed: bool = False) -> list:
        """The renders of ``batch`` (jobs), by the run's executor; each
        finished one is a step of the progress bar (none if ``label`` is None)."""
        def step(job):
            self.run.step(f"{label} {job.integrator.name} {job.spp} spp")
        self.run.rendered += len(batch)
        return self.run.executor.render(batch, step if label is not None else None, timed)

    def derive(self, estimators=None, *, label: str = "", streams: dict | None = None,
               plan=None, **defines) -> "Context":
        """The same plan (or ``plan``: another resolution) with other
        $-parameters (a sweep point, the sunless map) and, optionally, fewer
        estimators or other seed streams; nothing measured yet."""
        return Context(self.run, plan or self.plan, self.id,
                       list(estimators or self.estimators),
                       {**self.defines, **defines}, label or self.label,
                       dict(streams or self.streams))
