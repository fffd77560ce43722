"""Find what in a scene a given sampling strategy cannot reach.

A hemisphere estimator draws outgoing directions from a continuous pdf over the
reflection hemisphere. Three kinds of scene content are then invisible to it,
and an image rendered anyway would be silently wrong (biased dark):

* delta emitters (point, spot, directional, ...): a continuous pdf hits a
  single position or direction with probability zero;
* delta BSDF lobes (smooth conductor/dielectric, smooth plastic's coating):
  same argument, in direction space;
* transmission and pass-through (dielectrics, thin sheets, ``null``/``mask``):
  the pdf covers only the hemisphere on the side of the incident ray.

Participating media are refused as well: these integrators do not trace them.

:func:`unreachable` lists the problems; :func:`require_reachable` raises
:class:`UnreachableContentError` naming the first few with a remedy. Nothing
here depends on the variant beyond reading flags.
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi


@dataclass(frozen=True)
class Problem:
    """One piece of scene content an estimator cannot represent."""

    kind: str  # 'delta_emitter' | 'delta_bsdf' | 'transmission' | 'medium'
    what: str  # the offending object, e.g. "point emitter 'key_light'"
    remedy: str

    def __str__(self) -> str:
        return f"{self.what}: {self.remedy}"


class UnreachableContentError(ValueError):
    """The scene holds content the chosen estimator cannot reach."""

    def __init__(self, integrator: str, problems: list[Problem]):
        self.integrator = integrator
        self.problems = list(problems)
        shown = "\n  - ".join(str(p) for p in self.problems[:5])
        more = len(self.problems) - 5
        tail = f"\n  (and {more} more)" if more > 0 else ""
        super().__init__(
            f"integrator '{integrator}' cannot render this scene without bias; "
            f"it samples directions from a continuous pdf over the reflection "
            f"hemisphere only:\n  - {shown}{tail}"
        )


_PATH = "render it with Mitsuba's 'path' integrator"

def _name(obj) -> str:
    ident = obj.id()
    return f"'{ident}'" if ident else "(no id)"


def _emitter_problems(scene) -> list[Problem]:
    out = []
    for em in scene.emitters():
        # DeltaPosition | DeltaDirection: a continuous pdf never hits them
        if mi.has_flag(em.flags(), mi.EmitterFlags.Delta):
            out.append(Problem(
                "delta_emitter",
                f"delta emitter {_name(em)} ({em.class_name()})",
                f"hemisphere sampling cannot reach point, spot or directional "
                f"lights; replace it with a small area emitter, or {_PATH}",
            ))
    return out


def _bsdf_problems(shape) -> list[Problem]:
    bsdf = shape.bsdf()
    if bsdf is None:
        return []
    flags = bsdf.flags()
    owner = f"shape {_name(shape)} with BSDF {_name(bsdf)} ({bsdf.class_name()})"
    out = []
    # (BSDFFlags.Delta also contains Null, which is pass-through, not specular)
    if (mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
            or mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission)):
        out.append(Problem(
            "delta_bsdf", f"{owner} has a perfectly specular (delta) lobe",
            "use a rough variant (roughconductor, roughdielectric, roughplastic "
            f"with alpha > 0), or {_PATH}",
        ))
    if (mi.has_flag(flags, mi.BSDFFlags.Transmission)
            or mi.has_flag(flags, mi.BSDFFlags.Null)):
        out.append(Problem(
            "transmission", f"{owner} transmits or passes light through",
            "the hemisphere estimators integrate reflection only; use an "
            f"opaque BSDF, or {_PATH}",
        ))
    return out


def unreachable(scene) -> list[Problem]:
    """Every emitter, BSDF and medium in ``scene`` a hemisphere pdf misses."""
    problems = _emitter_problems(scene)
    for shape in scene.shapes():
        problems += _bsdf_problems(shape)
        if shape.is_medium_transition():
            problems.append(Problem(
                "medium", f"shape {_name(shape)} bounds a participating medium",
                "media are not traced; render it with Mitsuba's 'volpath'",
            ))
    return problems


def require_reachable(scene, integrator: str, allowed: frozenset[str] = frozenset()) -> None:
    """Raise :class:`UnreachableContentError` unless every problem kind is allowed."""
    problems = [p for p in unreachable(scene) if p.kind not in allowed]
    if problems:
        raise UnreachableContentError(integrator, problems)
