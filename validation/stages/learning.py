"""The learning stage: does an estimator that learns its pdf while it
renders (registry facts ``learns``: guided_path) learn?

On a scene whose plan asks for it (profile key ``learning``), at the
ladder's resolution: K renders (the plan's, at most :data:`RENDERS`) of u
image samples per pixel after 0, 1, …, :data:`PASSES` training passes of
doubling spp (u, 2u, 4u, …), u a quarter of the ladder's top rung, so that
the image's own samples stay the same and only what was learned before them
changes. (An image of u, not of the top rung's 4u: each point's guides are
what the same training passes learn, so its ratio to the first point
estimates the same change in variance per sample, K sets the intervals'
relative width, and the stage renders a third fewer samples.) Per point the
relMSE of the renders less the reference's share, with its 95 % interval,
and the median seconds of a render (training included). A learned pdf that helps
makes the curve fall from its first point (no training: the estimator's
fallback, e.g. `mis`) and flatten; one that does not, stays level.

The renders are kept in the run directory like the quadrature stage's
(common.stream_renders): a re-run loads them.
"""

from __future__ import annotations

import numpy as np

from mcillum.integrators.core import registry

from ..results import Learning, LearningPoint
from ..stats import costs, metrics
from . import common

#: Training passes of the curve's points (each doubles the one before).
PASSES = (0, 1, 2, 3, 4)
#: Renders per point at most (the plan's K, if fewer).
RENDERS = 8
#: guided_path's max_variance_ratio that keeps whatever it learned.
KEEP_EVERY_DENSITY = 1e30


def learners(names) -> list[str]:
    """Those of ``names`` whose facts say they learn (a user's integrator
    may declare ``learns = True``; it must then take the properties
    ``train_passes`` and ``train_fraction``)."""
    return [n for n in names if registry.facts(n).learns]


def planned_renders(names, k: int, plan) -> int:
    """Renders this stage makes for ``names`` at K renders each (progress)."""
    return min(k, RENDERS) * len(PASSES) * len(learners(names)) if plan.learning else 0


def image_spp(ladder) -> int:
    """u, the image's samples per pixel and the first training pass's: a
    quarter of the ladder's top rung (at least 1)."""
    return max(max(ladder) // 4, 1)


def training(spp: int, passes: int) -> tuple[int, dict]:
    """(total spp, properties) of a render whose image has ``spp`` samples
    per pixel after ``passes`` training passes of spp, 2·spp, 4·spp, …"""
    train = spp * (2 ** passes - 1)
    total = spp + train
    # (+½: the plugin takes int(fraction · total) training samples)
    return total, {"train_passes": passes, "train_fraction": (train + 0.5) / total}


def measure(ctx) -> None:
    """Per learning estimator of the scene: ``ctx.learning[name]``."""
    ctx.learning = {}
    names = learners(ctx.integrators) if ctx.plan.learning else []
    spp, k = image_spp(ctx.plan.ladder), min(ctx.plan.renders, RENDERS)
    ref = ctx.reference
    for i, name in enumerate(names):
        points = []
        # (the image's own samples alone: guided_path would otherwise average
        # its training passes' images in, and the curve would mix the two)
        made = ctx.integrators[name].made
        alone = {"combine_passes": False} if hasattr(made, "combine_passes") else {}
        # (and every pass's density kept: the curve shows what was learned,
        # not the plugin's choice to drop a density that pays too little)
        if hasattr(made, "max_variance_ratio"):
            alone["max_variance_ratio"] = KEEP_EVERY_DENSITY
        for j in PASSES:
            total, params = training(spp, j)
            params = {**params, **alone}
            stack = common.stream_renders(ctx, "learning", name, params, total, k,
                                          len(PASSES) * i + j, timed=True)
            mean, ci = costs.relmse_interval(
                metrics.net_relmse(stack.images, ref.mean, ref.variance_of_mean))
            points.append(LearningPoint(passes=j, training_spp=total - spp, relmse=mean,
                                        relmse_low=ci.low, relmse_high=ci.high,
                                        seconds=float(np.median(stack.seconds))))
        ctx.learning[name] = Learning(name=name, spp=spp, renders=k, points=points)
