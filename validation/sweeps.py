"""Estimator renders: K independent renders per (estimator, spp), timed.

:func:`interleaved` is the one way mcillum renders several integrators for
comparison: K rounds, the integrators rotated every round (A B C, then
B C A, …) so that machine drift hits all of them alike; render i of every
integrator uses seed ``seeds[i]``. :func:`run` walks a scene's spp ladder with
it, one seed block per rung (seeds.py), and saves each finished rung to
``<out>/renders/<scene>/spp<N>.npz`` (atomically) under a key: a re-run with
the same key loads it instead of rendering, so an interrupted run resumes.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field

import numpy as np

from mcillum import files

from . import renders
from .seeds import stream


@dataclass
class Unit:
    """K renders of one estimator at one spp."""

    estimator: str
    spp: int
    images: np.ndarray                      # (K, H, W, C) float32
    seconds: list[float] = field(default_factory=list)


def rotation(names: list, i: int) -> list:
    """The order of round ``i``: ``names`` rotated left by ``i``."""
    k = i % len(names)
    return names[k:] + names[:k]


def interleaved(scene, integrators: dict, spp: dict[str, int], k: int, seeds: list[int],
                progress=None, label: str = "") -> dict[str, Unit]:
    """K renders of each integrator at its own spp, render i with ``seeds[i]``,
    the integrators rotated every round (:func:`rotation`)."""
    if len(seeds) < k:
        raise ValueError(f"{k} renders need {k} seeds, got {len(seeds)}")
    names = list(integrators)
    shots = {n: [] for n in names}
    times = {n: [] for n in names}
    for i in range(k):
        for n in rotation(names, i):
            out = renders.render(scene, integrators[n], spp[n], seed=seeds[i])
            shots[n].append(out.image)
            times[n].append(out.seconds)
            if progress:
                progress(f"{label} {n} {spp[n]} spp #{i + 1}/{k}")
    return {n: Unit(n, spp[n], np.stack(shots[n]), times[n]) for n in names}


# ------------------------------- A ladder ---------------------------------------

def _key(scene_key: str, estimators, spp: int, k: int, rung: int) -> str:
    return hashlib.sha256(json.dumps([scene_key, list(estimators), spp, k, rung, 2]).encode()
                          ).hexdigest()[:24]


def _load(path: str, key: str):
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            names = [str(n) for n in z["estimators"]]
            return {n: Unit(n, int(z["spp"]), z[f"images_{i}"], z[f"seconds_{i}"].tolist())
                    for i, n in enumerate(names)}
    except Exception:  # absent, partial or from another version: render anew
        return None


def _save(path: str, key: str, spp: int, units: dict[str, Unit]) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    arrays = {"key": key, "spp": spp, "estimators": np.array(list(units))}
    for i, u in enumerate(units.values()):
        arrays[f"images_{i}"] = u.images
        arrays[f"seconds_{i}"] = np.array(u.seconds)
    with files.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def run(ctx) -> dict[int, dict[str, Unit]]:
    """Every rung of ``ctx.plan.ladder``, K = ``ctx.plan.renders`` renders per
    estimator of ``ctx.integrators``: {spp: {estimator: Unit}}."""
    names = list(ctx.integrators)
    k = ctx.plan.renders
    result = {}
    for rung, spp in enumerate(ctx.plan.ladder):
        key = _key(ctx.scene_key, names, spp, k, rung)
        path = os.path.join(ctx.run.out_dir, "renders", ctx.id, f"spp{spp}.npz")
        cached = _load(path, key)
        if cached is not None:
            result[spp] = cached
            ctx.run.step(f"{ctx.id} {spp} spp: loaded", k * len(names))
            continue
        # distinct seeds on every rung: rungs are independent samples
        result[spp] = interleaved(ctx.scene, ctx.integrators, dict.fromkeys(names, spp), k,
                                  stream("ladder", rung).take(k), ctx.run.step, ctx.id)
        _save(path, key, spp, result[spp])
    return result
