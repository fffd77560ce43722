"""The ``failures`` group of ``mcillum validate``: every estimator driven into
the cases where it fails, with a verdict, numbers and evidence per case.

For each case of the profile (:class:`profiles.FailureCase`), top to bottom:

    scene → refusals (and the opt-in biased image) → K seeds per estimator →
    path reference → per-render errors, fireflies, NaN/negatives, bias test →
    verdict per estimator → evidence images → checks

Groups:

* ``heavy_tail`` — small bright sources (a sun): unbiased but heavy-tailed
  estimators. Numbers of :mod:`tails` (per-render relMSE percentiles, firefly
  fraction, spp to match path at the same spp) and the batch-means test, whose
  verdict may honestly be "K too small to tell" (see :func:`verdict`).
* ``unreachable`` — delta lights and lobes: refusing estimators must refuse;
  with ``allow_unreachable=true`` they render an image whose missing share is
  measured against path ("biased by opt-in").
* ``geometry`` — grazing views, back faces, shading normals, thin objects —
  and ``numerical`` (zero-area emitters): no NaN/Inf/negative radiance and
  agreement with path.
* ``glossy`` — one parameter swept (roughness α, Phong exponent): relMSE at a
  fixed spp, and relMSE × seconds, against the parameter.

Verdicts: ``fine`` (unbiased, no tail worth naming), ``heavy-tailed``
(unbiased; the worst render's relMSE is over ``TAIL_RATIO`` × the median and
over ``TAIL_RELMSE``, or fireflies are over ``TAIL_FIREFLIES`` of pixels), ``K too small to tell``,
``refused``, ``biased (opt-in)``, and the failures ``biased`` and
``non-finite/negative``, which fail the run.
"""

from __future__ import annotations

import os

import numpy as np

from . import images, references, renders, scenes, statistics, sweeps, tails

ALPHA = statistics.ALPHA
TAIL_RATIO = 10.0
TAIL_FIREFLIES = 1e-3
TAIL_RELMSE = 1e-3
#: Seeds of the failure renders (away from the ladders' and equal-time seeds).
FIRST_SEED = 700_000


# ------------------------------- Verdicts ------------------------------------

def bad_values(x: np.ndarray) -> tuple[int, int]:
    """(NaN/Inf values, negative values) in renders ``x``."""
    return int((~np.isfinite(x)).sum()), int((x < 0).sum())


def verdict(renders_: np.ndarray, ref_moments, per_render: np.ndarray, fireflies: float,
            fresh) -> tuple[str, bool, dict]:
    """(verdict, passed, numbers) of K renders of an estimator that rendered.

    The batch-means test (per pixel, Šidák; and the image mean) at ``ALPHA``.
    If it rejects, ``fresh()`` gives K new renders and the rejection must
    replicate (:func:`replicated_test`); if it does not, the first K renders
    could not tell a bias from a tail they had not seen: "K too small to
    tell" (not a failure, never "fine").
    """
    x = renders_[..., :3]
    bad = bad_values(x)
    numbers = {"nonfinite_values": bad[0], "negative_values": bad[1]}
    if bad[0] or bad[1]:
        return "non-finite/negative", False, numbers
    test = replicated_test(x, ref_moments, fresh)
    numbers.update(test)
    med = float(np.median(per_render))
    tail_ratio = float(per_render.max() / med) if med > 0 else 1.0
    numbers["tail_ratio"] = tail_ratio
    # (a near-exact estimator's ratio of tiny numbers names no tail)
    heavy = (tail_ratio > TAIL_RATIO and float(per_render.max()) > TAIL_RELMSE) or \
        fireflies > TAIL_FIREFLIES
    if test["passed"]:
        return ("heavy-tailed" if heavy else "fine"), True, numbers
    if test["replicated"] is False:
        return "K too small to tell", True, numbers
    return "biased", False, numbers


def replicated_test(x: np.ndarray, ref_moments, fresh) -> dict:
    """The batch-means test of K renders ``x`` against the reference; where it
    rejects, the same test on ``fresh()`` K renders at the rejected pixels
    (Šidák over them) and on the image mean. ``replicated`` is None when
    nothing needed replicating, else whether any rejection replicated."""
    cmp_ = statistics.compare(x, ref_moments, ALPHA)
    out = {"passed": cmp_.passed, "pass_fraction": cmp_.pass_fraction, "min_p": cmp_.min_p,
           "pooled_p": [float(p) for p in cmp_.pooled_p], "alpha_pixel": cmp_.alpha_pixel,
           "test": cmp_.summary(), "rejected_pixels": 0, "replicated_pixels": 0,
           "replicated": None}
    if cmp_.passed:
        return out
    rejected = cmp_.pixel_p < cmp_.alpha_pixel
    y = fresh()[..., :3]
    again = statistics.compare(y, ref_moments, ALPHA)
    pooled_again = bool(again.pooled_p.min() < again.alpha_pooled)
    pixels_again = np.zeros_like(rejected)
    if rejected.any():
        at = statistics.compare(y, ref_moments, ALPHA, mask=rejected)
        pixels_again = rejected & (at.pixel_p < at.alpha_pixel)
    pooled_first = bool(cmp_.pooled_p.min() < cmp_.alpha_pooled)
    out.update(rejected_pixels=int(rejected.sum()), replicated_pixels=int(pixels_again.sum()),
               replicated=bool(pixels_again.any() or (pooled_first and pooled_again)),
               replication_test=again.summary())
    return out


#: Largest density a strategy puts on any direction, for the expected number
#: of sun hits N·Ω·max p (None: depends on the BSDF lobe, or NEE finds the sun).
MAX_DIRECTION_PDF = {"uniform_hemisphere": 1 / (2 * np.pi), "cosine_hemisphere": 1 / np.pi}


def sun_split_verdict(case, defines: dict, failed: list, variant: str, cache_dir: str,
                      profile, progress=None) -> dict:
    """Re-test the estimators in ``failed`` on the case's map without its sun.

    Passing there while the sun is expected to be hit less than a few times
    per pixel means the K renders are too few to tell (see envmaps/sun.py).
    Returns {estimator: numbers} with the sun's facts and the sunless test.
    """
    from mcillum.envmaps import sun

    sunless_path, facts = sun.without_sun(defines["envmap"])
    info, sdefines, scene = _load(case, {"envmap": sunless_path})
    params = {"max_depth": case.max_depth}
    names = [*failed, "path"]
    integrators_ = {n: renders.make_integrator(n, params) for n in names}
    units = sweeps.interleaved(scene, integrators_, dict.fromkeys(names, case.spp),
                               case.seeds, FIRST_SEED + 50_000, progress, f"{case.id} sunless")
    ref = _reference(scene, info, sdefines, params, variant, cache_dir, profile,
                     {"path": units["path"]}, progress)
    out = {}
    for n in failed:
        test = replicated_test(units[n].images[..., :3], ref.moments(),
                               _fresh(scene, integrators_[n], case, FIRST_SEED + 150_000))
        pdf = MAX_DIRECTION_PDF.get(n)
        hits = None if pdf is None else case.seeds * case.spp * facts["solid_angle"] * pdf
        out[n] = {"sun": facts, "sunless_passed": test["passed"] or not test["replicated"],
                  "sunless_test": test["test"],
                  "sunless_reference_mean": float(ref.mean[..., :3].mean()),
                  "expected_sun_hits_per_pixel": hits}
    return out


# ------------------------------- Renders -------------------------------------

def _load(case, extra: dict | None = None):
    info = scenes.index()[case.scene]
    defines = renders.resolve_defines(info.path, **{"res": case.res, **case.defines,
                                                    **(extra or {})})
    return info, defines, renders.load_resolved(info.path, defines)


def _refusal(scene, name: str, params: dict) -> str | None:
    """The refusal message of ``name`` on ``scene``, or None if it renders."""
    from mcillum.integrators import UnreachableContentError

    try:
        renders.render(scene, renders.make_integrator(name, params), 1, FIRST_SEED - 1)
    except Exception as exc:  # noqa: BLE001  (mi.render wraps the plugin's error)
        cause = renders.root_cause(exc)
        if isinstance(cause, UnreachableContentError):
            return str(cause)
        raise
    return None


def _reference(scene, info, defines, params, variant, cache_dir, profile, units, progress):
    target = references.target_for([u.images for u in units.values()],
                                    profile.reference_fraction)
    return references.ensure(scene, info.path, defines, params, variant, cache_dir, target,
                             profile.reference_spp_per_pass, profile.reference_max_spp,
                             profile.reference_max_seconds, progress)


def _fresh(scene, integrator, case, first_seed: int):
    """A callable giving ``case.seeds`` new renders (for replication)."""
    return lambda: sweeps.interleaved(scene, {"x": integrator}, {"x": case.spp}, case.seeds,
                                      first_seed)["x"].images


def _evidence(case_dir: str, name: str, x: np.ndarray, per_render: np.ndarray) -> dict:
    """The median-error and worst-error renders, written as EXR; their files."""
    order = np.argsort(per_render)
    out = {}
    for label, k in (("median", order[len(order) // 2]), ("worst", order[-1])):
        f = f"{name}_{label}.exr"
        images.write_exr(os.path.join(case_dir, f), x[k].astype(np.float32),
                         {"integrator": name, "seed_index": int(k),
                          "relmse": float(per_render[k])})
        out[label] = f
    return out


# ------------------------------- One case -------------------------------------

def run_case(case, estimators, out_dir: str, cache_dir: str, variant: str, profile,
             checks: list, progress=None) -> dict:
    """Run one failure case (heavy_tail, unreachable or geometry)."""
    info, defines, scene = _load(case)
    params = {"max_depth": case.max_depth}
    case_dir = os.path.join(out_dir, "failures", case.id)
    os.makedirs(case_dir, exist_ok=True)

    # ------------------- Refusals, and the opt-in image ---------------------
    integrators_, refused = {}, {}
    for name in estimators:
        message = _refusal(scene, name, params) if name != "path" else None
        if message is not None:
            refused[name] = message
            if case.group != "unreachable":
                continue
            integrators_[name] = renders.make_integrator(
                name, {**params, "allow_unreachable": True})
        else:
            integrators_[name] = renders.make_integrator(name, params)

    # ------------------------- K seeds per estimator ------------------------
    sweeps.compile_times(scene, integrators_)
    units = sweeps.interleaved(scene, integrators_, dict.fromkeys(integrators_, case.spp),
                               case.seeds, FIRST_SEED, progress, case.id)

    # ------------------------------ Reference -------------------------------
    ref = _reference(scene, info, defines, params, variant, cache_dir, profile,
                     {"path": units["path"]}, progress)
    r = ref.mean[..., :3]
    images.write_exr(os.path.join(case_dir, "reference.exr"), r.astype(np.float32),
                     {"spp": ref.spp})
    path_rel = tails.per_render_relmse(units["path"].images, r)

    # ------------------------ Numbers and verdicts ---------------------------
    rows = []
    for name in estimators:
        row = {"name": name, "refused": name in refused}
        if name in refused:
            row["message"] = refused[name].splitlines()[0] + " " + \
                refused[name].splitlines()[1].strip()
        declared = name in info.refused_by
        if name in refused or declared:
            _check(checks, case.id, name, "refuses", name in refused and declared,
                   "refused as declared" if name in refused and declared else
                   ("refused, but the scene header does not declare it" if name in refused
                    else "rendered a scene it must refuse"))
        if name not in integrators_:
            row.update(verdict="refused", numbers={})
            rows.append(row)
            continue
        x = units[name].images[..., :3].astype(np.float64)
        per = tails.per_render_relmse(x, r)
        fireflies = tails.firefly_fraction(x, r)
        numbers = {"relmse": tails.percentiles(per), "firefly_fraction": fireflies,
                   "samples_per_pixel": case.seeds * case.spp, "seeds": case.seeds,
                   "seconds_median": float(np.median(units[name].seconds)),
                   "image_mean_ratio": float(x.mean() / r.mean()) if r.mean() > 0 else None,
                   "spp_to_match_path": tails.spp_to_match(per, path_rel, case.spp)}
        if name in refused:   # biased by the user's choice: measure what is missing
            v, ok = "biased (opt-in)", bad_values(x) == (0, 0)
            numbers["missing_fraction"] = 1.0 - numbers["image_mean_ratio"]
            numbers["spp_to_match_path"] = None     # no spp makes a biased image match
        else:
            v, ok, test = verdict(x, ref.moments(), per, fireflies,
                                  _fresh(scene, integrators_[name], case, FIRST_SEED + 100_000))
            numbers.update(test)
        row.update(verdict=v, numbers=numbers, images=_evidence(case_dir, name, x, per))
        rows.append(row)

    # ---------- Missed sun or bias? Re-test the failures without the sun ----------
    failed = [row["name"] for row in rows if row.get("verdict") == "biased"]
    if failed and case.group == "heavy_tail" and "envmap" in defines:
        split = sun_split_verdict(case, defines, failed, variant, cache_dir, profile,
                                  progress)
        for row in rows:
            extra = split.get(row["name"])
            if extra is None:
                continue
            extra["sun_share_of_image"] = 1.0 - extra["sunless_reference_mean"] / float(r.mean())
            row["numbers"].update(extra)
            hits = extra["expected_sun_hits_per_pixel"]
            if extra["sunless_passed"] and (hits is None or hits < 3):
                row["verdict"] = "K too small to tell"
    for row in rows:
        if "numbers" in row and row["verdict"] != "refused":
            v = row["verdict"]
            ok = v not in ("biased", "non-finite/negative")
            _check(checks, case.id, row["name"], "stable", ok, _describe(v, row["numbers"]))
    return {"id": case.id, "group": case.group, "label": case.label or case.scene,
            "scene": case.scene, "defines": dict(case.defines), "res": case.res,
            "spp": case.spp, "seeds": case.seeds, "max_depth": case.max_depth,
            "summary": info.summary, "reference": {"spp": ref.spp, "capped": ref.capped},
            "estimators": rows}


def _describe(v: str, n: dict) -> str:
    if v == "non-finite/negative":
        return (f"{n['nonfinite_values']} NaN/Inf and {n['negative_values']} negative "
                "values in the renders")
    if v == "biased (opt-in)":
        return (f"allow_unreachable=true: image mean {100 * n['image_mean_ratio']:.1f} % of "
                f"path's ({100 * n['missing_fraction']:.1f} % missing)")
    rel = n["relmse"]
    text = (f"{v}: relMSE median {rel['median']:.3g}, p99 {rel['p99']:.3g}, max "
            f"{rel['max']:.3g}; fireflies {100 * n['firefly_fraction']:.3f} %")
    if v == "K too small to tell" and "sun" in n:
        hits = n["expected_sun_hits_per_pixel"]
        text += (f"; the per-pixel test rejects ({n['rejected_pixels']} px) with the sun, "
                 f"passes without it; the sun ({n['sun']['solid_angle']:.2g} sr, "
                 f"{100 * n['sun_share_of_image']:.0f} % of path's image) is expected "
                 + (f"{hits:.2g} direct hits per pixel in all {n['samples_per_pixel']} samples"
                    if hits is not None else "to be found only through the BSDF lobe"))
    elif v == "K too small to tell":
        text += (f"; the test rejected {n['rejected_pixels']} px (pooled p = "
                 f"{min(n['pooled_p']):.3g}) and no rejection replicated in "
                 f"{n['seeds']} fresh renders")
    elif "sunless_test" in n:
        text += f"; {n['test']}; without the sun: {n['sunless_test']}"
    elif "test" in n:
        text += f"; {n['test']}"
    return text


def _check(checks: list, case_id: str, name: str, what: str, passed: bool, msg: str):
    checks.append({"id": f"{case_id}/{name}/{what}", "passed": bool(passed), "message": msg})


# ------------------------------- Glossy sweep ----------------------------------

def run_sweep(case, estimators, out_dir: str, cache_dir: str, variant: str, profile,
              checks: list, progress=None) -> dict:
    """relMSE at ``case.spp`` (and × seconds) against one swept scene parameter."""
    param, values = case.sweep
    case_dir = os.path.join(out_dir, "failures", case.id)
    os.makedirs(case_dir, exist_ok=True)
    params = {"max_depth": case.max_depth}
    table = {n: {"relmse": [], "seconds": [], "nonfinite": 0} for n in estimators}
    evidence = {}
    for i, value in enumerate(values):
        info, defines, scene = _load(case, {param: value})
        integrators_ = {n: renders.make_integrator(n, params) for n in estimators
                        if n not in info.refused_by}
        sweeps.compile_times(scene, integrators_)
        units = sweeps.interleaved(scene, integrators_, dict.fromkeys(integrators_, case.spp),
                                   case.seeds, FIRST_SEED, progress, f"{case.id} {value}")
        ref = _reference(scene, info, defines, params, variant, cache_dir, profile,
                         {"path": units["path"]}, progress)
        r = ref.mean[..., :3]
        for n, u in units.items():
            x = u.images[..., :3].astype(np.float64)
            per = tails.per_render_relmse(x, r)
            table[n]["relmse"].append(float(np.mean(per)))
            table[n]["seconds"].append(float(np.median(u.seconds)))
            table[n]["nonfinite"] += sum(bad_values(x))
            if i == len(values) - 1:    # evidence at the narrowest lobe
                evidence[n] = _evidence(case_dir, n, x, per)
        if i == len(values) - 1:
            images.write_exr(os.path.join(case_dir, "reference.exr"), r.astype(np.float32),
                             {"spp": ref.spp, param: value})
    rows = []
    for n, t in table.items():
        growth = t["relmse"][-1] / t["relmse"][0] if t["relmse"][0] > 0 else None
        ok = t["nonfinite"] == 0
        _check(checks, case.id, n, "finite", ok,
               f"relMSE ×{growth:.3g} from {param} = {values[0]} to {values[-1]}"
               if ok and growth is not None else f"{t['nonfinite']} NaN/Inf/negative values")
        rows.append({"name": n, "relmse": t["relmse"], "seconds": t["seconds"],
                     "growth": growth, "nonfinite_values": t["nonfinite"],
                     "images": evidence.get(n, {}),
                     "verdict": "fine" if ok else "non-finite/negative"})
    return {"id": case.id, "group": case.group, "label": case.label or case.scene,
            "scene": case.scene, "defines": dict(case.defines), "res": case.res,
            "spp": case.spp, "seeds": case.seeds, "max_depth": case.max_depth,
            "summary": scenes.index()[case.scene].summary,
            "sweep": {"param": param, "values": list(values)}, "estimators": rows}


def run(cases, estimators, out_dir: str, cache_dir: str, variant: str, profile,
        checks: list, progress=None) -> list[dict]:
    """Every failure case of the profile, in order."""
    estimators = list(dict.fromkeys([*estimators, "path"]))
    known = scenes.index()
    out = []
    for case in cases:
        if case.scene not in known:
            raise ValueError(f"failure case {case.id}: no scene '{case.scene}' in scenes/")
        runner = run_sweep if case.sweep else run_case
        out.append(runner(case, estimators, out_dir, cache_dir, variant, profile, checks,
                          progress))
    return out
