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
A fourth kind, glossy lobes, every shipped estimator reaches; an estimator
whose weights assume a diffuse BSDF (f_r constant over the hemisphere)
declares ``diffuse_only`` and refuses them.

:func:`unreachable` lists the problems; :func:`check_reachable` raises
:class:`UnreachableContentError` naming the first few with a remedy. Nothing
here depends on the variant beyond reading flags.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import mitsuba as mi


#: Every kind of :class:`Problem`: what a continuous pdf over the reflection
#: hemisphere cannot reach (estimators declare which they reach anyway).
KINDS = ("delta_emitter", "delta_bsdf", "transmission", "glossy_bsdf", "medium")
#: Each kind in words.
KIND_NAMES = {"delta_emitter": "delta lights", "delta_bsdf": "delta BSDF lobes",
              "transmission": "transmission", "glossy_bsdf": "glossy BSDF lobes",
              "medium": "participating media"}


@dataclass(frozen=True)
class Problem:
    """One piece of scene content an estimator cannot represent."""

    kind: str  # one of KINDS
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
            f"integrator '{integrator}' cannot render this scene without bias:"
            f"\n  - {shown}{tail}"
            f"\n(to render the biased image anyway, knowing it lacks this content, "
            f"set <boolean name=\"allow_unreachable\" value=\"true\"/> on the integrator)"
        )

    def __reduce__(self):        # (pickled with its own arguments: a Ray worker sends it)
        return type(self), (self.integrator, self.problems)


_FOR_DELTA_LIGHTS = "use emitter_sampling or mis (or Mitsuba's 'path')"
_FOR_DELTA_LOBES = "use bsdf_sampling or mis (or Mitsuba's 'path')"

#: Microfacet roughness below which a lobe counts as (near-)delta. Mitsuba
#: clamps alpha = 0 to 1e-4, which a hemisphere pdf reaches as rarely as a true
#: delta (docs/measurements.md#2026-12-01-figures-moved-out-code). Lobes at
#: alpha >= 5e-3 stay allowed: unbiased, but heavy-tailed, which the failure
#: suite measures down to alpha = 0.01.
NEAR_DELTA_ALPHA = 5e-3


def _name(obj) -> str:
    ident = obj.id()
    return f"'{ident}'" if ident else "(no id)"


def _emitter_problems(em) -> list[Problem]:
    # DeltaPosition | DeltaDirection: a continuous pdf never hits them
    if not mi.has_flag(em.flags(), mi.EmitterFlags.Delta):
        return []
    return [Problem(
        "delta_emitter", f"delta emitter {_name(em)} ({em.class_name()})",
        f"a continuous direction pdf cannot reach point, spot or directional "
        f"lights; {_FOR_DELTA_LIGHTS}, or replace it with a small area emitter")]


def _flag_problems(bsdf, owner: str) -> list[Problem]:
    flags, out = bsdf.flags(), []
    # (BSDFFlags.Delta also contains Null, which is pass-through, not specular)
    if (mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
            or mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission)):
        out.append(Problem(
            "delta_bsdf", f"{owner} has a perfectly specular (delta) lobe",
            f"{_FOR_DELTA_LOBES}, or use a rough variant (roughconductor, "
            f"roughdielectric, roughplastic with alpha >= {NEAR_DELTA_ALPHA})"))
    if (mi.has_flag(flags, mi.BSDFFlags.Transmission)
            or mi.has_flag(flags, mi.BSDFFlags.Null)):
        out.append(Problem(
            "transmission", f"{owner} transmits or passes light through",
            f"hemisphere estimators integrate reflection only, and emitter samples "
            f"cannot pass through it; {_FOR_DELTA_LOBES}, or use an opaque BSDF"))
    if mi.has_flag(flags, mi.BSDFFlags.Glossy):
        out.append(Problem(
            "glossy_bsdf", f"{owner} has a glossy lobe",
            "weights that assume a diffuse BSDF (an estimator declared diffuse_only) "
            "would be wrong for it; use fibonacci_hemisphere or bayesian_hemisphere "
            "(they split their directions between the lobes), cosine_hemisphere or mis"))
    return out


#: A parameter given as a texture whose values cannot be read (a mesh
#: attribute, a user's own texture): it may hold any value.
UNREADABLE = "unreadable"

#: The traversed entries that hold a parameter's values: a plain float (the
#: parameter's own name), a uniform or sRGB spectrum's ``value``, a sampled
#: spectrum's ``values``, a bitmap's ``data`` (a checkerboard's colours are
#: such spectra).
_VALUE_KEYS = ("value", "values", "data")
#: Entries beside them that are no values: a texture's uv transform, a
#: spectrum's wavelengths. Any other entry (a mesh attribute's ``scale``)
#: makes the parameter unreadable.
_OTHER_KEYS = ("to_uv", "wavelengths", "range")
#: Microfacet BSDFs: a roughness they do not expose at all is unreadable too.
_MICROFACET = ("RoughConductor", "RoughDielectric", "RoughPlastic", "Principled",
               "PrincipledThin")
_ROUGHNESS = ("alpha", "alpha_u", "alpha_v", "roughness")


def _values(params, name: str):
    """All values of parameter ``name``, uniform or textured; None where the
    BSDF has no such parameter; :data:`UNREADABLE` where a texture gives it
    and its values cannot be read."""
    keys = [k for k in params.keys() if k.split(".")[0] == name]
    if not keys:
        return None
    values = []
    for k in keys:
        last = k.split(".")[-1]
        if last in _OTHER_KEYS:
            continue
        if k != name and last not in _VALUE_KEYS:     # (``name`` alone: a plain float)
            return UNREADABLE
        values.append(np.asarray(params[k], dtype=np.float64).ravel())
    values = [v for v in values if v.size]
    return np.concatenate(values) if values else UNREADABLE


def _smallest(params, name: str):
    v = _values(params, name)
    return v if v is None or v is UNREADABLE else float(v.min())


def _roughness_problems(bsdf, owner: str) -> list[Problem]:
    """Microfacet lobes so narrow that they are delta in all but name. A
    textured roughness counts by its smallest value; one whose values cannot
    be read counts as near-specular (it may be), and the message says so."""
    params = mi.traverse(bsdf)
    if bsdf.class_name() in _MICROFACET and not any(
            k.split(".")[0] in _ROUGHNESS for k in params.keys()):
        found = [UNREADABLE]                 # a texture that exposes nothing
    else:
        found = [_smallest(params, k) for k in ("alpha", "alpha_u", "alpha_v")]
    roughness = _smallest(params, "roughness")   # principled: alpha = roughness²
    found.append(roughness if roughness in (None, UNREADABLE) else roughness ** 2)
    clearcoat, gloss = _values(params, "clearcoat"), _values(params, "clearcoat_gloss")
    if clearcoat is UNREADABLE or gloss is UNREADABLE:
        found.append(UNREADABLE)
    elif clearcoat is not None and clearcoat.max() > 0 and gloss is not None:
        g = float(gloss.max())                       # principled's clearcoat lobe:
        found.append(0.1 * (1 - g) + 0.001 * g)      # alpha = lerp(0.1, 0.001, gloss)
    if UNREADABLE in found:
        return [Problem(
            "delta_bsdf", f"{owner} has a roughness given by a texture whose values "
            "cannot be read, so it may be near-specular",
            f"a hemisphere pdf almost never samples a near-specular lobe; "
            f"{_FOR_DELTA_LOBES}, or give the roughness as a value, a checkerboard or a "
            "bitmap")]
    alphas = [a for a in found if a is not None]
    if not alphas or min(alphas) >= NEAR_DELTA_ALPHA:
        return []
    return [Problem(
        "delta_bsdf", f"{owner} has a near-specular lobe (alpha {min(alphas):.2g} < "
        f"{NEAR_DELTA_ALPHA})",
        f"a hemisphere pdf almost never samples it, so the image comes out dark; "
        f"{_FOR_DELTA_LOBES}, or raise the roughness to alpha >= {NEAR_DELTA_ALPHA}")]


def _owner(obj, hierarchy) -> str:
    """"shape 'x' with BSDF 'y' (Class) > 'z' (Inner)" for a (nested) BSDF."""
    chain, parent = [obj], hierarchy[obj][0]
    while isinstance(parent, mi.BSDF):         # wrappers: twosided, blendbsdf, ...
        chain.insert(0, parent)
        parent = hierarchy[parent][0]
    bsdfs = " > ".join(f"{_name(b)} ({b.class_name()})" for b in chain)
    where = f"shape {_name(parent)} with " if isinstance(parent, mi.Shape) else ""
    return f"{where}BSDF {bsdfs}"


def unreachable(scene) -> list[Problem]:
    """Every emitter, BSDF and medium in ``scene`` a hemisphere pdf misses,
    including those nested in shape groups (instances) and BSDF wrappers."""
    hierarchy = mi.traverse(scene).hierarchy   # object → (parent, depth)
    problems: list[Problem] = []
    for obj, (parent, _) in hierarchy.items():
        if isinstance(obj, mi.Emitter):
            problems += _emitter_problems(obj)
        elif isinstance(obj, mi.BSDF):
            owner = _owner(obj, hierarchy)
            if not isinstance(parent, mi.BSDF):    # wrappers already union flags
                problems += _flag_problems(obj, owner)
            problems += _roughness_problems(obj, owner)
        elif isinstance(obj, mi.Shape) and obj.is_medium_transition():
            problems.append(Problem(
                "medium", f"shape {_name(obj)} bounds a participating medium",
                "media are not traced; render it with Mitsuba's 'volpath'"))
    return problems


def check_reachable(scene, integrator: str, allowed: frozenset[str] = frozenset(),
                    accept: bool = False, warn: bool = True) -> list[Problem]:
    """The problems of ``scene`` whose kind is not in ``allowed``.

    Raises :class:`UnreachableContentError` if there are any, unless ``accept``
    (the user's ``allow_unreachable``): then logs a warning (if ``warn``) that
    the image will be biased, naming what is missing, and returns them.
    """
    problems = [p for p in unreachable(scene) if p.kind not in allowed]
    if problems and not accept:
        raise UnreachableContentError(integrator, problems)
    if problems and warn:
        names = "; ".join(p.what for p in problems[:5])
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        mi.Log(mi.LogLevel.Warn,
               f"{integrator} with allow_unreachable=true: the image is BIASED, it "
               f"lacks the contribution of {names}{more}")
    return problems
