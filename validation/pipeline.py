"""`mcillum validate`: the one orchestrator.

For every scene of a profile and every case of its failures group, a
:class:`~.stages.context.Context` goes through a list of stages (the tuples
below), then the checks decide (:mod:`.checks`):

    scene comparison   load → choose estimators → K renders per rung of an spp
                       ladder → reference (a black one refused) → measure →
                       settle (sequential: unbiasedness, then convergence) →
                       quadrature (estimators of N directions: equal rays, bias
                       against N, calibration) → learning (estimators that
                       learn their pdf, where the plan asks: error against
                       training passes) → release the scene → images → on
                       a map with a sun, for the estimators it
                       left inconclusive, the sun split as a failure case's
                       below, at the ladder's top rung; checks; then the
                       speed-and-images stage at the display resolution
                       (stages/speed.py): cost model → equal-time
                       renders → reference → (where the profile asks: the
                       budget axis, a tenth of a second to a minute,
                       stages/budget_axis.py) → relMSE, efficiency,
                       ranking, FLIP → images
    failure case       load → refusals → K seeds → reference (a black one
                       refused) → tail numbers →
                       bias test (sequential) → release → the sunless twin
                       (a heavy-tail case on a map with a sun: the map without
                       it, through SUNLESS) → sun split → the widened twin
                       (those the real sun left inconclusive and that passed
                       without it: the map with its sun widened to a disc the
                       samples hit, envmaps/sun.py; through WIDENED) → its
                       test; checks; evidence
    sweep              each parameter value: load → K seeds → reference →
                       tail numbers; then rows along the sweep; checks

The reference comes after the estimator renders because its precision target
depends on them. Then results.json, results.csv, summary.md and the report.
"""

from __future__ import annotations

import json
import os
import platform
import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mcillum import files
from mcillum import plugins as mcillum_plugins
from mcillum.errors import Interrupted
from mcillum.integrators.core import registry

from . import report, results
from .checks import cases as case_checks
from .checks import scene as scene_checks
from .plan import profiles, scenes, seeds, user_scenes
from .results import layout
from .run import executors, mitsuba_log, renders
from .run.progress import Progress
from .stages import budget_axis, cases, common, learning, quadrature, scene, speed, sun_split
from .stages.context import Context, Run
from .stats import metrics, statistics

# (require_signal after each reference: a black one passes every check)
SCENE = (common.load, common.choose_estimators, scene.render_ladder, common.build_reference,
         common.require_signal, scene.measure, scene.settle, scene.settle_convergence,
         sun_split.note_unsplit_sun, quadrature.measure, learning.measure, common.release,
         scene.save_images, sun_split.sunless_twin)
SPEED = (speed.display, speed.time_costs, speed.render_budgets, speed.display_reference,
         budget_axis.render_axis, speed.release_display, speed.measure_speed,
         budget_axis.measure_axis, speed.save_display)
CASE = (common.load, cases.probe_refusals, cases.render_seeds, common.build_reference,
        common.require_signal, cases.tail_numbers, cases.test_bias, common.release,
        sun_split.sunless_twin)
#: The sunless twin of a heavy-tail case or of a scene comparison on a map
#: with a sun (its own context: ``ctx.sunless``), and its widened twin
#: (``ctx.widened``), whose reference reaches the budget (stages/sun_split.py).
#: No require_signal: a twin's map is derived from one whose reference is
#: lit, and a black twin's pass is failed by the check (evidence.nothing_tested).
SUNLESS = (common.load, common.choose_estimators, cases.render_seeds, common.build_reference)
WIDENED = (common.load, common.choose_estimators, cases.render_seeds,
           sun_split.widened_reference)
SWEEP_POINT = (common.load, common.choose_estimators, cases.render_seeds,
               common.build_reference, common.require_signal, cases.tail_numbers,
               common.release)


def run_stages(stage_list, ctx: Context) -> Context:
    for stage in stage_list:
        ctx.run.stage(ctx, stage.__name__)
        stage(ctx)
    return ctx


def compare_scene(run: Run, plan: profiles.SceneRun, estimators, speed_stage: bool = True,
                  notes=()) -> tuple[results.SceneResult, list[results.Check]]:
    """One scene of the profile: its result and its checks (and, unless
    ``speed_stage`` is False, its speed-and-images stage). ``notes``: what
    the plan of a user's scene says about it (plan/user_scenes.py)."""
    ctx = Context(run, plan, plan.id, at_depth(estimators, plan), dict(plan.defines),
                  label=plan.id)
    ctx.scene_notes += notes
    run_stages(SCENE, ctx)
    split_the_sun(ctx)
    ctx.checks = scene_checks.judge(ctx.id, ctx.measured, ctx.evidence, ctx.quadrature)
    if speed_stage and plan.display is not None and registry.REFERENCE in ctx.integrators:
        run_stages(SPEED, ctx)
    return scene.scene_result(ctx), ctx.checks


def failure_case(run: Run, plan: profiles.FailureCase,
                 estimators) -> tuple[results.CaseResult, list[results.Check]]:
    """One case of the failures group (a sweep: every point of it): its
    result and its checks."""
    ctx = Context(run, plan, plan.id, at_depth(estimators, plan), dict(plan.defines),
                  label=plan.id)
    if plan.sweep:
        param, values = plan.sweep
        points = [run_stages(SWEEP_POINT, ctx.derive(label=f"{plan.id} {v}", **{param: v}))
                  for v in values]
        cases.sweep_rows(ctx, points)
        ctx.checks = case_checks.judge_sweep(ctx.id, ctx.sweep_rows, cases.sweep_record(plan))
        return cases.case_result(ctx), ctx.checks
    run_stages(CASE, ctx)
    split_the_sun(ctx)
    pixels = int(np.prod(ctx.reference.mean.shape[:2]))
    ctx.checks = case_checks.judge(ctx.id, ctx.rows, ctx.info.contains, pixels)
    cases.save_evidence(ctx)
    return cases.case_result(ctx), ctx.checks


def split_the_sun(ctx: Context) -> None:
    """What the real sun left undecided, tested on the map without it and
    with it widened, where ``sun_split.sunless_twin`` made the twin
    (stages/sun_split.py); each twin's scene let go after its test."""
    if ctx.sunless is not None:
        run_stages(SUNLESS, ctx.sunless)
        sun_split.split_sun(ctx)
        common.release(ctx.sunless)
        sun_split.widened_twin(ctx)
    if ctx.widened is not None:
        run_stages(WIDENED, ctx.widened)
        sun_split.split_widened(ctx)
        common.release(ctx.widened)


def at_depth(estimators, plan) -> list[str]:
    """The estimators that define the plan's ``max_depth`` (those of N
    directions per point estimate direct illumination only)."""
    depths = (registry.facts(n).depths for n in estimators)
    return [n for n, d in zip(estimators, depths) if d is None or plan.max_depth in d]


@dataclass(frozen=True)
class Setup:
    """The Mitsuba variant set and the user's plugins imported for one run."""

    variant: str
    plugins: tuple                  # mcillum.plugins.Plugin, the profile's first


def set_up(profile: profiles.Profile, variant: str | None = None, plugins=()) -> Setup:
    """Set ``variant`` (default $MCILLUM_VARIANT or llvm_ad_rgb) and import the
    profile's plugins and ``plugins``; returns what was set. Raises ValueError
    for an unknown variant, :class:`~mcillum.errors.UsageError` for a plugin
    that cannot be imported."""
    variant = renders.set_variant(variant)
    return Setup(variant, tuple(mcillum_plugins.load(p, variant)
                                for p in dict.fromkeys([*profile.plugins, *plugins])))


def validate(profile_name="quick", scene_names=None, estimators=None,
             out_dir: str = "out/validate", cache_dir: str | None = None,
             variant: str | None = None, progress: bool | None = None,
             groups=profiles.GROUPS, seed_set: int = 0,
             speed_stage: bool = True, executor: str = "local",
             ray_address: str | None = None, ray_workers: int | None = None,
             plugins=(), settings: dict | None = None, defines: dict | None = None,
             res: int | None = None, budget: float | None = None,
             setup: Setup | None = None) -> results.Results:
    """Run a profile (a bundled name, a profile file's path, or a
    :class:`~.plan.profiles.Profile`): its
    scene comparisons and/or its failures group (``groups``), filtered by
    scene name; write the results and the report. ``scene_names`` may hold
    scene files' paths: each is compared by the profile's ``user_scenes``
    rule (plan/user_scenes.py) with ``defines`` ($-parameters), ``settings``
    (``max_depth``, ``rr_depth``, ``hide_emitters``: over the scene's own)
    and ``res`` (the statistics film's longest side); no failure case runs
    for them. ``plugins`` (files or modules, with the profile's) are
    imported first, here and on every worker (mcillum/plugins.py).
    ``progress``: False shows none; None (default) one updating line on
    a terminal, plain lines in a log (run/progress.py).
    ``budget`` overrides the profile's sequential budgets (× a check's first
    look's samples per pixel, stages/sequential.py).
    ``seed_set`` picks an independent repeat (plan/seeds.py); ``speed_stage``
    False leaves out the speed-and-images stage (no verdict depends on it).
    ``executor`` says where the renders run (run/executors.py: ``local``, or
    ``ray`` at ``ray_address`` with ``ray_workers``); the images do not
    depend on it.

    Ctrl-C raises :class:`mcillum.errors.Interrupted` saying what was left and what
    to do (finished renders are kept and reused by the next run).
    """
    profile = (profile_name if isinstance(profile_name, profiles.Profile)
               else profiles.resolve(profile_name))
    if setup is None:
        setup = set_up(profile, variant, plugins)
    elif variant is not None or plugins:
        raise ValueError("give either setup or variant and plugins, not both")
    variant, loaded = setup.variant, setup.plugins
    seed_set = seeds.check_set(seed_set)
    estimators = list(estimators or profile.estimator_names())
    cases_estimators = list(dict.fromkeys([*estimators, registry.REFERENCE]))
    names = list(scene_names or [])
    bundled = [n for n in names if not scenes.is_path(n)]
    files_given = ([n for n in names if scenes.is_path(n)] if names else profile.scene_files) \
        if "scenes" in groups else []
    user = [user_scenes.scene_run(profile, p, defines=defines, settings=settings, res=res,
                                  label=label)
            for p, label in zip(files_given, _user_scene_labels(files_given))]
    notes = {plan.id: said for plan, said in user}
    plans = [r for r in profile.runs if "scenes" in groups
             and (not names or r.scene in bundled or r.id in bundled)] + [plan for plan, _ in user]
    case_plans = [c for c in profile.failures if "failures" in groups
                  and (not names or c.scene in bundled or c.label in bundled)]
    cache_dir = cache_dir or files.cache_dir()
    os.makedirs(out_dir, exist_ok=True)
    for d in (out_dir, cache_dir):   # left by a killed run (one writer at a time)
        files.remove_stale_partials(d, recursive=True)
    json_path = layout.results_json(out_dir)
    before = _stamp(json_path)
    total = sum(r.renders * len(at_depth(estimators, r)) * len(r.ladder) +
                quadrature.planned_renders(at_depth(estimators, r), r.renders) +
                learning.planned_renders(at_depth(estimators, r), r.renders, r)
                for r in plans) + \
        sum(r.display.renders * len(at_depth(estimators, r)) * len(r.display.path_spp) +
            budget_axis.planned_renders(at_depth(estimators, r), r.display)
            for r in plans if r.display and speed_stage) + \
        sum(c.seeds * len(at_depth(cases_estimators, c)) *
            max(1, len(c.sweep[1]) if c.sweep else 1)
            for c in case_plans)
    start = time.perf_counter()
    try:
        scene_results, case_results, checks = [], [], []
        with start_executor(executor, ray_address, ray_workers, variant, loaded) as ex, \
                mitsuba_log.plain() as log:
            bar = Progress(total, progress, log=log)
            run = Run(profile, variant, cache_dir, out_dir, bar, ex, budget, seed_set=seed_set)
            try:
                for plan in plans:
                    result, found = compare_scene(run, plan, estimators, speed_stage,
                                                  notes.get(plan.id, ()))
                    scene_results.append(result)
                    checks += found
                for plan in case_plans:
                    result, found = failure_case(run, plan, cases_estimators)
                    case_results.append(result)
                    checks += found
            finally:
                bar.close()
            where = ex.record()
        seconds = time.perf_counter() - start
        first = _first_run(json_path, run) if before is not None else None
        out = results.Results(
            created=time.strftime("%Y-%m-%dT%H:%M:%S%z"), profile=profile.name,
            variant=variant, mitsuba_version=mi.__version__, drjit_version=dr.__version__,
            machine=_machine(first[1] if first is not None else run.machine_speed),
            alpha=statistics.ALPHA, reference_fraction=profile.reference_fraction,
            wall_seconds=first[0] if first is not None else seconds,
            rerun_seconds=seconds if first is not None else None,
            scenes=scene_results, checks=checks,
            failures=case_results,
            estimator_facts=estimator_facts([*estimators, *cases_estimators]),
            seed_set=seed_set, executor=where, definitions=dict(metrics.DEFINITIONS))
        results.write_json(json_path, out)
    except KeyboardInterrupt:
        raise Interrupted(_left_behind(out_dir, json_path, before)) from None
    try:
        results.write_csv(layout.results_csv(out_dir), out)
        results.write_summary(out_dir, out)
        report.build(out_dir, out)
    except KeyboardInterrupt:
        raise Interrupted(f"while writing the report: {json_path} is complete; run "
                          f"`mcillum report {out_dir}` to write the report") from None
    return out


def estimator_facts(names) -> dict[str, results.EstimatorInfo]:
    """The registry's facts of ``names``, as the results record them."""
    names = list(dict.fromkeys(names))
    colours = registry.palette(names)
    return {n: results.EstimatorInfo(display_name=registry.facts(n).display_name,
                                     colour=colours[n],
                                     unreachable=list(registry.facts(n).unreachable),
                                     max_direction_pdf=registry.facts(n).max_direction_pdf,
                                     unbiased=registry.facts(n).unbiased) for n in names}


def start_executor(kind: str = "local", address: str | None = None,
                   workers: int | None = None, variant: str | None = None, plugins=()):
    """The executor of ``kind`` (run/executors.py): ``local``, or ``ray``
    (joining the cluster at ``address``, else starting one on this machine)
    with ``workers`` workers (default: one per CPU, or per GPU for a cuda
    variant) in ``variant``, each importing ``plugins`` (mcillum/plugins.py:
    a user's integrators). Raises ValueError for another kind."""
    if kind == "local":
        return executors.Local()
    if kind == "ray":
        from .run import ray_executor
        return ray_executor.RayExecutor(address, workers, variant, plugins)
    raise ValueError(f"unknown executor '{kind}': use one of {', '.join(executors.KINDS)}")


def _user_scene_labels(paths) -> list[str]:
    """A label for each scene file: its stem, or its folder and stem where
    two stems are alike (Mitsuba's test scenes are all scene.xml)."""
    stems = [os.path.splitext(os.path.basename(p))[0] for p in paths]
    return [f"{os.path.basename(os.path.dirname(os.path.abspath(p)))}_{s}"
            if stems.count(s) > 1 else s for p, s in zip(paths, stems)]


def _machine(speed_probe: dict | None) -> dict:
    """What the run ran on; with ``speed_probe``, its time for a fixed
    workload (run/probe.py)."""
    return {"platform": platform.platform(), "processor": platform.processor(),
            "cpus": os.cpu_count(), "python": platform.python_version(),
            **({"speed": speed_probe} if speed_probe else {})}


def _first_run(json_path: str, run: Run) -> tuple[float, dict | None] | None:
    """The wall time and the machine probe (run/probe.py, or None) of the
    run whose renders this one reused, where this one rendered nothing of
    its own (a re-run into a finished directory: its own few seconds are
    ``rerun_seconds``, and the timings it reports are that run's); None
    otherwise."""
    if run.rendered or not run.kept:
        return None
    try:
        with open(json_path, encoding="utf-8") as f:
            data = json.load(f)
        seconds, speed = data.get("wall_seconds"), data.get("machine", {}).get("speed")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(seconds, (int, float)):
        return None
    return float(seconds), speed if isinstance(speed, dict) else None


def _stamp(path: str):
    """(mtime, ``created``) of a results.json; None if absent or unreadable."""
    try:
        with open(path, encoding="utf-8") as f:
            created = json.load(f).get("created") or "at an unknown date"
        return os.stat(path).st_mtime_ns, created
    except (OSError, ValueError, AttributeError):
        return None


def _left_behind(out_dir: str, json_path: str, before) -> str:
    """What an interrupted run leaves, and what to do about it."""
    resume = (f"finished renders are kept in {out_dir} and reused: run the same command "
              "again to resume")
    if before is None:
        return f"no results were written; {resume}"
    return (f"{json_path} is from an earlier run (created {before[1]}), not this one; "
            f"{resume}")
