"""Stacks of renders: K independent renders of one estimator at one spp, timed.

:func:`interleaved` is the one way mcillum renders several integrators for
comparison: K rounds, the integrators rotated every round (A B C, then
B C A, …) so that machine drift hits all of them alike; render i of every
integrator uses seed ``seeds[i]``. :func:`ladder` walks a scene's spp ladder
with it, one seed block per rung (plan/seeds.py). :func:`kept` saves every
finished set of stacks in the run directory (results/layout.py,
``renders/<id>/<file>.npz``, atomically) under a key: a re-run with the same
key loads it instead of rendering, so an interrupted run resumes and a
finished one renders nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field

import numpy as np

from mcillum import files

from ..results import layout


@dataclass
class Stack:
    """K renders of one estimator at one spp."""

    estimator: str
    spp: int
    images: np.ndarray                      # (K, H, W, C) float32
    seconds: list[float] = field(default_factory=list)
    aovs: dict = field(default_factory=dict)   # AOV group → (K, H, W, k) (renders.Render)
    #: CPU seconds other processes used during each render (run/load.py).
    others: list = field(default_factory=list)


def rotation(names: list, i: int) -> list:
    """The order of round ``i``: ``names`` rotated left by ``i``."""
    k = i % len(names)
    return names[k:] + names[:k]


def interleaved(ctx, integrators: dict, spp: dict[str, int], k: int, seeds: list[int],
                label: str = "", timed: bool = False) -> dict[str, Stack]:
    """K renders of each integrator (name → :class:`~.jobs.Integrator`) of
    context ``ctx``'s scene at its own spp, render i with ``seeds[i]``, the
    integrators rotated every round (:func:`rotation`); by the run's executor,
    one batch (``timed``: their wall times are reported, executors.py)."""
    if len(seeds) < k:
        raise ValueError(f"{k} renders need {k} seeds, got {len(seeds)}")
    names = list(integrators)
    order = [n for i in range(k) for n in rotation(names, i)]
    batch = [ctx.job(integrators[n], spp[n], seeds[i // len(names)])
             for i, n in enumerate(order)]
    shots = {n: [] for n in names}
    for n, out in zip(order, ctx.render(batch, label, timed)):
        shots[n].append(out)
    return {n: Stack(n, spp[n], np.stack([o.image for o in shots[n]]),
                     [o.seconds for o in shots[n]],
                     {g: np.stack([o.aovs[g] for o in shots[n]]) for g in shots[n][0].aovs},
                     [o.others_seconds for o in shots[n]])
            for n in names}


# ------------------------------- Kept renders -----------------------------------

def _key(ctx, names, spp: dict, seed_list, tag: str) -> str:
    """Everything that decides the images: scene content, estimators and
    their parameters, spp, seeds."""
    opted = sorted(ctx.refused)             # rendered with allow_unreachable
    return hashlib.sha256(json.dumps(
        [ctx.render_key, list(names), opted, spp, list(seed_list), tag, FORMAT]).encode()
    ).hexdigest()[:24]


FORMAT = 3


def _load(path: str, key: str):
    """(stacks, compile seconds) kept at ``path`` under ``key``, else None."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            names = [str(n) for n in z["estimators"]]
            stacks = {n: Stack(n, int(z["spp"][i]), z[f"images_{i}"],
                               z[f"seconds_{i}"].tolist(),
                               {f[len(f"aov_{i}_"):]: z[f] for f in z.files
                                if f.startswith(f"aov_{i}_")})
                      for i, n in enumerate(names)}
            return stacks, dict(zip(names, z["compile"].tolist()))
    except Exception:  # absent, partial or from another version: render anew
        return None


def _save(path: str, key: str, stacks: dict[str, Stack], compile_seconds: dict) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    arrays = {"key": key, "estimators": np.array(list(stacks)),
              "spp": np.array([u.spp for u in stacks.values()]),
              "compile": np.array([compile_seconds.get(n, np.nan) for n in stacks])}
    for i, u in enumerate(stacks.values()):
        arrays[f"images_{i}"] = u.images
        arrays[f"seconds_{i}"] = np.array(u.seconds)
        for group, layers in u.aovs.items():
            arrays[f"aov_{i}_{group}"] = layers
    files.write_arrays(path, arrays)


def kept(ctx, file: str, tag: str, integrators: dict, spp: dict[str, int], k: int,
         seed_list: list[int], compile_=None, label: str = "",
         timed: bool = False) -> dict[str, Stack]:
    """:func:`interleaved`, kept in the run directory as ``file`` (module doc)
    under a key of everything that decides the images: a re-run with the same key
    loads them (and the compile times recorded with them) instead of
    rendering. ``compile_(ctx)`` runs before the first render that is not
    kept."""
    key = _key(ctx, list(integrators), spp, seed_list[:k], tag)
    path = layout.kept_renders(ctx.run.out_dir, ctx.id, file)
    found = _load(path, key)
    if found is not None:
        stacks, compiled = found
        for n, s in compiled.items():
            ctx.compile_seconds.setdefault(n, s)
        ctx.run.step(f"{label} {file}: kept", k * len(integrators))
        ctx.run.kept += k * len(integrators)
        return stacks
    if compile_ is not None:
        compile_(ctx)
    stacks = interleaved(ctx, integrators, spp, k, seed_list, label, timed)
    _save(path, key, stacks, ctx.compile_seconds)
    return stacks


# ------------------------------- A ladder ---------------------------------------

def ladder(ctx, compile_=None) -> dict[int, dict[str, Stack]]:
    """Every rung of ``ctx.plan.ladder``, K = ``ctx.plan.renders`` renders per
    estimator of ``ctx.integrators``: {spp: {estimator: Stack}}; each rung is
    kept (:func:`kept`) as ``spp<N>.npz``."""
    names = list(ctx.integrators)
    k = ctx.plan.renders
    # distinct seeds on every rung: rungs are independent samples
    return {spp: kept(ctx, f"spp{spp}", f"rung {rung}", ctx.integrators,
                      dict.fromkeys(names, spp), k, ctx.run.stream("ladder", rung).take(k),
                      compile_, ctx.id)
            for rung, spp in enumerate(ctx.plan.ladder)}
