"""`mcillum validate`: the pipeline, top to bottom, for each scene of a profile.

    scene → estimator renders (sweeps) → reference (references) →
    statistics and metrics (analysis) → equal-time check → results files

The reference comes after the estimator renders because its precision target
depends on them: its standard error must be at most ``reference_fraction`` of
the smallest error it is compared against (the RMSE of one render of the least
noisy estimator at its highest spp).
"""

from __future__ import annotations

import os
import platform
import sys
import time
from dataclasses import asdict

import numpy as np

from . import analysis, failures, images, profiles, references, renders, results, scenes
from . import statistics, sweeps

ALPHA = statistics.ALPHA


class Progress:
    """One step per render with an ETA, on stderr when it is a terminal."""

    def __init__(self, total: int, enabled: bool | None = None):
        self.total, self.done, self.start = max(total, 1), 0, time.perf_counter()
        self.enabled = sys.stderr.isatty() if enabled is None else enabled

    def __call__(self, what: str, steps: int = 1) -> None:
        if "reference" not in what:
            self.done += steps
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        eta = elapsed / self.done * (self.total - self.done) if self.done else 0.0
        sys.stderr.write(f"\r[{self.done}/{self.total}] {what[:60]:<60} ETA {eta:5.0f} s")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def _check(checks: list, cid: str, passed: bool, message: str) -> None:
    checks.append({"id": cid, "passed": bool(passed), "message": message})


def validate_scene(run: profiles.SceneRun, profile: profiles.Profile, estimators,
                   out_dir: str, cache_dir: str, variant: str, checks: list,
                   progress: Progress) -> dict:
    info = scenes.index()[run.scene]
    defines = renders.resolve_defines(info.path, **{"res": run.res, **run.defines})
    scene = renders.load_resolved(info.path, defines)
    params = {"max_depth": run.max_depth}
    names = [e for e in estimators if e not in info.refused_by]
    integrators = {e: renders.make_integrator(e, params) for e in names}
    scene_key = references.cache_key(info.path, defines, params, variant)

    # ------------------------------ Estimators ------------------------------
    compile_s = sweeps.compile_times(scene, integrators)
    units = sweeps.run(scene, scene_key, integrators, run.ladder, run.renders, out_dir,
                       run.scene, progress)

    # ------------------------------ Reference -------------------------------
    # Smallest error compared against: one render of the least noisy
    # (estimator, spp) unit.
    target = references.target_for([u.images for spp in run.ladder
                                    for u in units[spp].values()],
                                   profile.reference_fraction)
    ref = references.ensure(scene, info.path, defines, params, variant, cache_dir, target,
                            profile.reference_spp_per_pass, profile.reference_max_spp,
                            profile.reference_max_seconds, progress)
    img_dir = os.path.join(out_dir, "images", run.scene)
    os.makedirs(img_dir, exist_ok=True)
    images.write_exr(os.path.join(img_dir, "reference.exr"), ref.mean.astype(np.float32),
                     {"spp": ref.spp, "passes": ref.passes})
    images.write_exr(os.path.join(img_dir, "reference_variance.exr"),
                     ref.variance_of_mean.astype(np.float32), {"passes": ref.passes})

    # ------------------------------ Statistics ------------------------------
    est_out, per_est = [], {}
    for name in names:
        stats_ = [analysis.run_stats(units[spp][name], ref) for spp in run.ladder]
        per_est[name] = stats_
        top = units[run.ladder[-1]][name]
        finite = all(s.nonfinite_fraction == 0 for s in stats_)
        if finite:
            pooled = statistics.Moments.pooled({spp: units[spp][name].images[..., :3]
                                                for spp in run.ladder})
            cmp_ = statistics.compare(pooled, ref.moments(), ALPHA)
            unbiased = {"spp": top.spp, "passed": cmp_.passed,
                        "samples_per_pixel": int(sum(spp * run.renders for spp in run.ladder)),
                        "pass_fraction": cmp_.pass_fraction, "min_p": cmp_.min_p,
                        "alpha": ALPHA, "alpha_pixel": cmp_.alpha_pixel,
                        "pooled_p": [float(p) for p in cmp_.pooled_p],
                        "summary": cmp_.summary()}
        else:
            unbiased = {"spp": top.spp, "passed": False, "pass_fraction": 0.0, "min_p": 0.0,
                        "alpha": ALPHA, "alpha_pixel": 0.0, "pooled_p": [],
                        "summary": "not tested: non-finite pixels"}
        slope = analysis.convergence(stats_)
        images.write_exr(os.path.join(img_dir, f"{name}_spp{top.spp}.exr"), top.images[0],
                         {"integrator": name, "spp": top.spp, "seed": 0})
        images.write_exr(os.path.join(img_dir, f"{name}_spp{top.spp}_mean.exr"),
                         top.images.mean(axis=0), {"integrator": name, "spp": top.spp,
                                                   "renders": len(top.images)})
        cid = f"{run.scene}/{name}"
        _check(checks, f"{cid}/finite", finite,
               "no NaN/Inf" if finite else "non-finite pixels in renders")
        _check(checks, f"{cid}/unbiased", unbiased["passed"], unbiased["summary"])
        _check(checks, f"{cid}/converges", slope.converges,
               "exact (zero variance at every spp)" if slope.exact else
               f"relMSE slope {slope.slope:+.2f} [{slope.low:+.2f}, {slope.high:+.2f}]")
        est_out.append({
            "name": name, "params": params, "compile_seconds": compile_s[name],
            "runs": [asdict(s) for s in stats_], "unbiasedness": unbiased,
            "convergence": {"slope": slope.slope, "low": slope.low, "high": slope.high,
                            "exact": slope.exact,
                            "consistent_with_mc": slope.consistent_with_mc,
                            "passed": slope.converges},
        })

    # ------------------------------ Equal time ------------------------------
    equal = analysis.equal_time_plan(per_est)
    if equal is not None:
        top_spp = run.ladder[-1]
        spp = {n: min(s, 4 * top_spp) for n, s in equal.spp.items()}
        equal.spp = spp
        measured = sweeps.equal_time_renders(scene, integrators, spp,
                                             max(4, run.renders // 2), progress)
        analysis.equal_time_measure(equal, measured, ref)
        for name, unit in measured.items():
            images.write_exr(os.path.join(img_dir, f"{name}_equal_time.exr"), unit.images[0],
                             {"integrator": name, "spp": unit.spp,
                              "render_seconds": float(unit.seconds[0])})

    return {
        "name": run.scene, "path": os.path.relpath(info.path, os.getcwd()),
        "summary": info.summary, "res": run.res, "max_depth": run.max_depth,
        "ladder": list(run.ladder), "renders": run.renders,
        "reference": {
            "integrator": "path", "spp": ref.spp, "passes": ref.passes,
            "spp_per_pass": ref.spp_per_pass, "seconds": ref.seconds,
            "cached_passes": ref.cached_passes,
            "rendered_passes": ref.meta.get("rendered_passes", 0),
            "target_variance": target,
            "achieved_variance": float(ref.variance_of_mean.mean()),
            "capped": ref.capped, "key": ref.key,
        },
        "estimators": est_out,
        "equal_time": None if equal is None else {
            "budget_seconds": equal.budget_seconds, "spp": equal.spp,
            "predicted_relmse": equal.predicted_relmse,
            "predicted_ranking": equal.predicted_ranking,
            "measured_relmse": equal.measured_relmse,
            "measured_seconds": equal.measured_seconds,
            "measured_ranking": equal.measured_ranking, "agrees": equal.agrees,
        },
    }


def _remove_partials(*dirs: str) -> None:
    for d in dirs:
        for root, _, files in os.walk(d):
            for f in files:
                if f.startswith(".partial-"):
                    os.unlink(os.path.join(root, f))


def validate(profile_name: str = "quick", scene_names=None, estimators=None,
             out_dir: str = "out/validate", cache_dir: str | None = None,
             variant: str | None = None, progress: bool | None = None,
             groups=("scenes", "failures")) -> dict:
    """Run a profile; ``groups`` picks its scene comparisons and/or its
    failures group (``scene_names`` filters both, by scene name)."""
    import drjit as dr
    import mitsuba as mi

    profile = profiles.PROFILES[profile_name]
    runs = [r for r in profile.runs if "scenes" in groups
            and (not scene_names or r.scene in scene_names)]
    cases = [c for c in profile.failures if "failures" in groups
             and (not scene_names or c.scene in scene_names)]
    estimators = list(estimators or profile.estimators)
    variant = renders.set_variant(variant)
    cache_dir = cache_dir or os.path.join(os.environ.get("MCILLUM_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "mcillum"))
    os.makedirs(out_dir, exist_ok=True)
    _remove_partials(out_dir, cache_dir)   # left by a killed run (one writer at a time)
    start = time.perf_counter()
    total = sum(r.renders * len(estimators) * (len(r.ladder) + 1) for r in runs) + \
        sum(c.seeds * (len(estimators) + 1) * max(1, len(c.sweep[1]) if c.sweep else 1)
            for c in cases)
    bar = Progress(total, progress)
    checks: list = []
    scene_results = []
    try:
        for run in runs:
            scene_results.append(validate_scene(run, profile, estimators, out_dir,
                                                cache_dir, variant, checks, bar))
        failure_results = failures.run(cases, estimators, out_dir, cache_dir, variant,
                                       profile, checks, bar)
    finally:
        bar.close()
    out = {
        "schema": results.SCHEMA, "version": results.VERSION,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "profile": profile.name,
        "variant": variant, "mitsuba_version": mi.__version__, "drjit_version": dr.__version__,
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count(), "python": platform.python_version()},
        "alpha": ALPHA, "reference_fraction": profile.reference_fraction,
        "definitions": results.DEFINITIONS,
        "wall_seconds": time.perf_counter() - start,
        "scenes": scene_results, "failures": failure_results, "checks": checks,
        "passed": all(c["passed"] for c in checks),
    }
    results.write_json(os.path.join(out_dir, "results.json"), out)
    results.write_csv(os.path.join(out_dir, "results.csv"), out)
    results.write_text(os.path.join(out_dir, "summary.md"), results.summary(out))
    from . import report  # the last stage: reads what was just written

    report.build(out_dir)
    return out
