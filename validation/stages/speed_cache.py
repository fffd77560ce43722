"""The speed stage's kept timings and renders (``renders/<scene>/speed.npz``,
results/layout.py) under a key (scene content, estimators, the display plan,
the budgets' rules): a re-run into a finished directory renders nothing, and
reports the first run's timings (speed.py)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import numpy as np

from mcillum import files

from ..results import Try, layout
from ..run.stacks import Stack
from .budgets import MAX_SCALE, MIN_BUDGET, MIN_LEARNER_SPP, MIN_SPP


def _cache_file(ctx, version: list) -> tuple[str, str]:
    sub, d = ctx.display, ctx.plan.display
    key = hashlib.sha256(json.dumps(
        [sub.render_key, list(sub.integrators), dataclasses.asdict(d),
         MAX_SCALE, MIN_SPP, MIN_BUDGET, MIN_LEARNER_SPP, *version]
    ).encode()).hexdigest()[:24]
    return layout.kept_renders(ctx.run.out_dir, ctx.id, "speed"), key


def load(ctx, version: list) -> None:
    """The timings and renders an earlier run of this stage kept, where its
    key (``version``: the stage's own parts) matches; else nothing."""
    path, key = _cache_file(ctx, version)
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return
            meta = json.loads(str(z["meta"]))
            found = [{n: Stack(n, spp, z[f"images_{j}_{i}"], z[f"seconds_{j}_{i}"].tolist())
                      for i, (n, spp) in enumerate(budget)}
                     for j, budget in enumerate(meta["spp"])]
    except Exception:  # absent, partial or from another version: time and render anew
        return
    ctx.timings = {n: {int(s): t for s, t in v.items()} for n, v in meta["timings"].items()}
    ctx.budget_path_spp = [int(x) for x in meta["path_spp"]]
    ctx.budget_stacks = found
    ctx.budget_tries = [{n: [Try(**t) for t in ts] for n, ts in tries.items()}
                        for tries in meta["tries"]]
    ctx.timing_load = [tuple(x) for x in meta["timing_load"]]
    ctx.timed_on = list(meta.get("timed_on", []))
    loaded = len(found) * ctx.plan.display.renders * len(ctx.display.integrators)
    ctx.run.step(f"{ctx.id} speed stage: loaded", loaded)
    ctx.run.kept += loaded


def save(ctx, version: list) -> None:
    """Keep the stage's timings and renders for a re-run (:func:`load`)."""
    path, key = _cache_file(ctx, version)
    arrays = {"key": key, "meta": json.dumps({
        "timings": {n: {str(s): t for s, t in v.items()} for n, v in ctx.timings.items()},
        "path_spp": ctx.budget_path_spp,
        "timed_on": ctx.timed_on,
        "tries": [{n: [dataclasses.asdict(t) for t in ts] for n, ts in tries.items()}
                  for tries in ctx.budget_tries],
        "timing_load": [list(x) for x in ctx.timing_load],
        "spp": [[[n, u.spp] for n, u in by_name.items()] for by_name in ctx.budget_stacks]})}
    for j, by_name in enumerate(ctx.budget_stacks):
        for i, u in enumerate(by_name.values()):
            arrays[f"images_{j}_{i}"] = u.images
            arrays[f"seconds_{j}_{i}"] = np.asarray(u.seconds)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    files.write_arrays(path, arrays)
