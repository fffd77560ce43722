"""The records of the learning stage (stages/learning.py): an estimator that
learns its pdf while it renders, its error against the training before the
image."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(kw_only=True)
class LearningPoint:
    """K renders of ``spp`` image samples per pixel after ``passes`` training
    passes of ``training_spp`` samples per pixel in all."""

    passes: int
    training_spp: int
    relmse: float                # mean over renders, less the reference's share
    relmse_low: float            # 95 % interval (Student t over the renders)
    relmse_high: float
    seconds: float               # median per render, training included


@dataclass(kw_only=True)
class Learning:
    """relMSE of an estimator's image at a fixed spp against the training
    passes that came before it (0: it renders without learning)."""

    name: str
    spp: int                     # the image's own samples per pixel
    renders: int
    points: list[LearningPoint]
