"""Many renders in one launch: the tiles of a batch sensor.

At the statistics' film sizes (8²–24² pixels) a render costs mostly its
launch: tracing the integrator's Python, looking its kernel up, launching it
(5–7 ms at 8², whatever the spp: docs/measurements.md, 2026-12-03). The suite
renders such images by the thousand (64 seeds of every estimator in every
failure case, the ladders, the sequential tests), so the renders that are not
timed are put side by side: Mitsuba's ``batch`` sensor holding the scene's own
sensor K times, on a film K times as wide, renders K images in one launch.

Each tile is a render of its own. The independent sampler seeds every lane
from (launch seed, lane index) and no two tiles share a lane; a box filter
keeps every sample in its own pixel; the integrator sees the same scene, whose
first sensor is still the scene's own (the batch sensor is passed to
``mi.render``, never added to the scene). So a tile's pixels have the
distribution of a render launched alone, but its values differ from a lone
render with the same seed.

Not tiled (one launch per render, as before):

* timed renders: their wall time is the measurement (the caller decides);
* an integrator that learns within a launch (fact ``learns``): its tiles would
  share what it learned; or a user's class that replaces ``render``: what it
  does across a launch's pixels is unknown;
* a scene whose film filter is not a box (samples would splat across a tile's
  edge), whose sampler is not ``independent`` (others correlate lanes on
  purpose), or whose film has a crop window.
"""

from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np

from mcillum.integrators import registry

from . import renders

#: Most lanes (pixels × spp, all tiles) in one launch: beyond 2²⁰ the fixed
#: cost is under a few per cent of the launch, and a wavefront's memory grows
#: with its lanes.
MAX_LANES = 1 << 20


# ---------------------------------- Grouping ----------------------------------

def per_launch(pixels: int, spp: int, max_lanes: int = MAX_LANES) -> int:
    """How many renders of ``pixels`` pixels at ``spp`` one launch holds."""
    return max(1, max_lanes // max(1, pixels * spp))


def scene_refusal(scene) -> str | None:
    """Why renders of ``scene`` cannot be tiles of one launch; None if they can."""
    sensor = scene.sensors()[0]
    film = sensor.film()
    if sensor.class_name() == "BatchSensor":
        return "its sensor is a batch sensor already"
    if film.rfilter().class_name() != "BoxFilter":
        return f"its film filter is {film.rfilter().class_name()}, not a box"
    if sensor.sampler().class_name() != "IndependentSampler":
        return f"its sampler is {sensor.sampler().class_name()}, not independent"
    if tuple(film.crop_size()) != tuple(film.size()) or any(film.crop_offset()):
        return "its film has a crop window"
    return None


def integrator_refusal(integrator) -> str | None:
    """Why renders with ``integrator`` (a :class:`~.jobs.Integrator`) cannot
    be tiles of one launch; None if they can."""
    if registry.facts(integrator.name).learns:
        return "it learns within a launch"
    made = integrator.made
    if made is None:
        return "it was not made in this process"
    if not registry.is_estimator(made) and \
            type(made).render is not mi.SamplingIntegrator.render:
        return "its class replaces render()"
    return None


def grouped(jobs: list) -> tuple[list, list[list[int]]]:
    """(the launches that render ``jobs``, and per launch the indices of the
    jobs it renders). Jobs of one scene, integrator and spp that may be
    tiled (:func:`scene_refusal`, :func:`integrator_refusal`) go into
    launches of up to :func:`per_launch` tiles, in order; every other job is
    a launch of its own. Which jobs share a launch depends on ``jobs`` alone,
    never on the executor."""
    groups: dict = {}
    order: list = []
    refused: dict = {}
    for i, job in enumerate(jobs):
        scene = job.live
        if scene is not None and id(scene) not in refused:
            refused[id(scene)] = scene_refusal(scene)
        if job.seeds or scene is None or refused[id(scene)] or \
                integrator_refusal(job.integrator):
            order.append([i])
            continue
        key = (id(scene), job.scene, job.integrator, job.spp)
        if key not in groups:
            groups[key] = []
            order.append(groups[key])
        groups[key].append(i)
    launches, slots = [], []
    for members in order:
        job = jobs[members[0]]
        if len(members) == 1:
            launches.append(job)
            slots.append(members)
            continue
        w, h = job.live.sensors()[0].film().crop_size()
        k = per_launch(int(w) * int(h), job.spp)
        for at in range(0, len(members), k):
            part = members[at:at + k]
            seeds = tuple(jobs[i].seed for i in part)
            launches.append(jobs[part[0]] if len(part) == 1 else
                            dataclasses.replace(job, seed=launch_seed(seeds), seeds=seeds))
            slots.append(part)
    return launches, slots


def ungrouped(outs: list, slots: list[list[int]]) -> list:
    """The renders of :func:`grouped`'s launches (``outs``: a render, or a
    tiled launch's list of them) back in the order of the jobs."""
    result = [None] * sum(len(s) for s in slots)
    for out, members in zip(outs, slots):
        for i, one in zip(members, out if isinstance(out, list) else [out]):
            result[i] = one
    return result


def launch_seed(seeds) -> int:
    """The seed of a launch whose tiles stand for renders with ``seeds``: a
    32-bit mix of all of them, so launches of other seed lists (and lone
    renders with small seeds) draw other streams."""
    x = 0x6A09E667 ^ len(seeds)
    for s in seeds:
        x = (x ^ (int(s) & 0xFFFFFFFF)) * 0x9E3779B1 & 0xFFFFFFFF
        x ^= x >> 15
        x = x * 0x85EBCA77 & 0xFFFFFFFF
        x ^= x >> 13
    return x


# ----------------------------------- Render -----------------------------------

def batch_sensor(sensor, k: int):
    """A ``batch`` sensor of ``sensor`` K times on a box-filtered film K
    times as wide, with its sampler."""
    w, h = (int(x) for x in sensor.film().crop_size())
    spec = {"type": "batch", "sampler": sensor.sampler(),
            "film": {"type": "hdrfilm", "width": k * w, "height": h,
                     "pixel_format": _PIXEL_FORMATS[sensor.film().base_channels_count()],
                     "rfilter": {"type": "box"}}}
    for i in range(k):
        spec[f"tile{i}"] = sensor
    return mi.load_dict(spec)


#: hdrfilm's pixel format by its base channel count (its AOVs come after).
_PIXEL_FORMATS = {1: "luminance", 2: "luminance_alpha", 3: "rgb", 4: "rgba"}


def render(scene, integrator, spp: int, seed: int, seeds) -> list:
    """One launch of ``integrator`` on ``scene`` at ``spp`` and ``seed``
    whose tiles are the renders for ``seeds``: a
    :class:`~.renders.Render` per seed, each with the launch's seconds
    shared out evenly."""
    k = len(seeds)
    whole = renders.render(scene, integrator, spp, seed,
                           sensor=batch_sensor(scene.sensors()[0], k))
    share = 1.0 / k
    others = None if whole.others_seconds is None else whole.others_seconds * share
    meta = {**whole.meta, "launch": {"tiles": k, "seed": seed}}
    return [renders.Render(tile(whole.image, k, i), whole.seconds * share, spp, s, dict(meta),
                           {g: tile(a, k, i) for g, a in whole.aovs.items()}, others)
            for i, s in enumerate(seeds)]


def tile(image: np.ndarray, k: int, i: int) -> np.ndarray:
    """Tile ``i`` of ``k`` side by side in ``image`` (H, K·W, C)."""
    w = image.shape[1] // k
    return np.ascontiguousarray(image[:, i * w:(i + 1) * w])
