"""Estimator renders: K independent renders per (estimator, spp), timed.

For one scene, every estimator is first rendered once untimed-for-ranking
(kernel compile or cache load: reported as compile time), then the ladder is
walked with estimators interleaved (A B C, then B C A, …) so that machine
drift hits all of them equally. Each finished (spp) step is saved to
``<out>/renders/<scene>/spp<N>.npz`` (atomically) under a key; a re-run with
the same key loads it instead of rendering: an interrupted run resumes.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field

import numpy as np

from . import images, renders

#: Seed offset of the timed renders (the compile render uses seed 999_999).
SEED_BASE = 0


@dataclass
class Unit:
    """K renders of one estimator at one spp."""

    estimator: str
    spp: int
    images: np.ndarray                      # (K, H, W, C) float32
    seconds: list[float] = field(default_factory=list)


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
    with images.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def compile_times(scene, integrators: dict) -> dict[str, float]:
    """Seconds of each integrator's first render (compile or kernel-cache load)."""
    return {name: renders.render(scene, integ, 1, seed=999_999).seconds
            for name, integ in integrators.items()}


def run(scene, scene_key: str, integrators: dict, ladder, k: int, out_dir: str,
        scene_name: str, progress=None) -> dict[int, dict[str, Unit]]:
    """All units of one scene: {spp: {estimator: Unit}}."""
    names = list(integrators)
    result = {}
    for rung, spp in enumerate(ladder):
        key = _key(scene_key, names, spp, k, rung)
        path = os.path.join(out_dir, "renders", scene_name, f"spp{spp}.npz")
        cached = _load(path, key)
        if cached is not None:
            result[spp] = cached
            if progress:
                progress(f"{scene_name} {spp} spp: loaded", steps=k * len(names))
            continue
        # distinct seeds on every rung: rungs are independent samples
        result[spp] = interleaved(scene, integrators, dict.fromkeys(names, spp), k,
                                  SEED_BASE + 10_000 * rung, progress, scene_name)
        _save(path, key, spp, result[spp])
    return result


def interleaved(scene, integrators: dict, spp: dict[str, int], k: int, first_seed: int,
                progress=None, label: str = "") -> dict[str, Unit]:
    """K renders of each estimator at its own spp (seeds first_seed + i), the
    estimators rotated every round (A B C, B C A, …) so drift hits all alike."""
    names = list(integrators)
    shots = {n: [] for n in names}
    times = {n: [] for n in names}
    for i in range(k):
        for n in names[i % len(names):] + names[:i % len(names)]:
            out = renders.render(scene, integrators[n], spp[n], seed=first_seed + i)
            shots[n].append(out.image)
            times[n].append(out.seconds)
            if progress:
                progress(f"{label} {n} {spp[n]} spp #{i + 1}/{k}")
    return {n: Unit(n, spp[n], np.stack(shots[n]), times[n]) for n in names}


def equal_time_renders(scene, integrators: dict, spp: dict[str, int], k: int,
                       progress=None) -> dict[str, Unit]:
    """K renders of each estimator at its own spp (the equal-time check)."""
    return interleaved(scene, integrators, spp, k, 500_000, progress, "equal time")
