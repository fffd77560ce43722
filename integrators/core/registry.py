"""The estimators mcillum knows, and the facts the validation suite reads off them.

Each plugin class declares its facts as class attributes beside its strategy
(see :class:`~mcillum.integrators.core.estimator.IlluminationEstimator`):

* ``plugin_name`` — the name Mitsuba knows it by (``<integrator type=...>``);
* ``display_name`` — a few words for people;
* ``colour`` — its colour on every chart of a report;
* ``reachable`` — the kinds of scene content
  (:data:`~mcillum.integrators.core.scene_checks.KINDS`) it renders without bias
  although a continuous hemisphere pdf cannot (delta lights, delta lobes,
  transmission); it refuses scenes holding any other kind;
* ``max_direction_pdf`` — the largest density it puts on any direction, which
  bounds how often it can hit a small source (None: it depends on the BSDF
  lobe, or next-event estimation finds the source anyway);
* ``listing_order`` — where it stands in tables and charts;
* ``depths`` — the ``max_depth`` values it defines (None: any);
* ``unbiased`` — False for an estimator biased by design (a quadrature such
  as bayesian_hemisphere): the suite then measures its bias against N
  instead of testing for none — which it can only for an estimator of N
  directions (derived from ``DirectionSetEstimator``): a user's class that
  is not one is tested as unbiased whatever it declares;
* ``equal_rays_baseline`` — the Monte Carlo estimator an estimator of N
  directions is compared with at equal rays;
* ``diffuse_only`` — it refuses glossy lobes too (``glossy_bsdf``);
* ``learns`` — it learns its sampling density while it renders, in training
  passes it takes from the render's samples (properties ``train_passes`` and
  ``train_fraction``): the learning stage measures its error against them;
* ``equal_rays_baseline`` — for an estimator of N directions per shading
  point, the Monte Carlo estimator it is compared with at equal rays (the
  quadrature stage): ``cosine_hemisphere`` unless it samples the light,
  then ``emitter_sampling``.

:func:`register` (called at the bottom of every plugin file) registers the
class with Mitsuba for the current variant and records its facts here. Facts
do not depend on the variant, so once recorded they stay readable after a
variant switch. Mitsuba's own ``path``, the reference of every comparison,
has its facts in :data:`PATH`.

:func:`names` lists the registered estimators: profiles, charts, the
failures group and the tests all read this list, so adding an estimator is
adding its file.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import mitsuba as mi

from .scene_checks import KINDS

#: Name of the reference integrator (Mitsuba's path tracer).
REFERENCE = "path"

#: Colours for integrators that declare none (any Mitsuba plugin can be validated).
SPARE_COLOURS = ("#e377c2", "#bcbd22", "#7f7f7f", "#aec7e8", "#ffbb78")


@dataclass(frozen=True)
class Facts:
    """What the validation suite needs to know about one integrator."""

    name: str
    display_name: str
    colour: str | None
    reachable: frozenset = frozenset()
    max_direction_pdf: float | None = None
    listing_order: int = 100
    ours: bool = True
    depths: tuple[int, ...] | None = None
    unbiased: bool = True
    diffuse_only: bool = False
    equal_rays_baseline: str = "cosine_hemisphere"
    learns: bool = False
    #: N directions per shading point (derived from DirectionSetEstimator):
    #: the validation's quadrature stage measures it (equal rays, bias against N).
    point_set: bool = False
    #: Its render() is the same launches whatever it is called with but spp
    #: and seed (no Python work between them): the validation may record it
    #: once and replay it (validation/run/replays.py).
    freezable: bool = False
    #: Its render() learns in Python between launches, each of them its
    #: class's ``launch_pass`` (a function of its arguments alone): the
    #: validation may record each launch and replay it (``frozen_pass``).
    freezes_passes: bool = False

    @property
    def reaches(self) -> frozenset:
        """``reachable``, and glossy lobes unless it is diffuse only."""
        return self.reachable | (frozenset() if self.diffuse_only else {"glossy_bsdf"})

    @property
    def unreachable(self) -> tuple[str, ...]:
        """The kinds of content it refuses (participating media always)."""
        return tuple(k for k in KINDS if k not in self.reaches)

    def renders(self, contains, max_depth: int | None = None) -> bool:
        """Does it render a scene holding these kinds of content (at this
        ``max_depth``, if given)?"""
        return (all(kind in self.reaches for kind in contains)
                and (max_depth is None or self.depths is None or max_depth in self.depths))


#: Mitsuba's `path`: emitter sampling and BSDF sampling, MIS; no media.
PATH = Facts(REFERENCE, "path tracer (Mitsuba)", "#444444",
             frozenset({"delta_emitter", "delta_bsdf", "transmission"}), None,
             listing_order=1000, ours=False, freezable=True)

_facts: dict[str, Facts] = {}
_classes: dict[str, type] = {}


def facts_of(cls) -> Facts:
    """The :class:`Facts` a plugin class declares."""
    return Facts(cls.plugin_name, cls.display_name or cls.plugin_name, cls.colour,
                 frozenset(cls.reachable), cls.max_direction_pdf, cls.listing_order,
                 # (classes not derived from IlluminationEstimator may omit these)
                 depths=getattr(cls, "depths", None), unbiased=getattr(cls, "unbiased", True),
                 diffuse_only=getattr(cls, "diffuse_only", False),
                 equal_rays_baseline=getattr(cls, "equal_rays_baseline", "cosine_hemisphere"),
                 learns=getattr(cls, "learns", False), point_set=is_point_set_class(cls),
                 # (declared by the class itself: a subclass may do host work)
                 freezable=bool(vars(cls).get("freezable", False)),
                 freezes_passes=bool(vars(cls).get("freezes_passes", False)))


def is_point_set_class(cls) -> bool:
    """Is plugin class ``cls`` an estimator of N directions per shading point
    (derived from mcillum's DirectionSetEstimator)?"""
    return any(c.__name__ == "DirectionSetEstimator" for c in cls.__mro__)


def register(cls) -> type:
    """Register plugin class ``cls`` with Mitsuba (current variant) under its
    ``plugin_name``, and record its facts. Returns ``cls``."""
    mi.register_integrator(cls.plugin_name, lambda props, cls=cls: cls(props))
    _facts[cls.plugin_name] = facts_of(cls)
    _classes[cls.plugin_name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget the facts of ``name`` (Mitsuba keeps the plugin until exit)."""
    _facts.pop(name, None)
    _classes.pop(name, None)


def plugin_class(name: str) -> type | None:
    """The class of mcillum's estimator ``name`` as last registered (None
    for any other plugin)."""
    return _classes.get(name)


def names() -> list[str]:
    """Every registered mcillum estimator, in listing order (not ``path``)."""
    if not _facts:
        raise RuntimeError(
            "no mcillum estimator is registered yet: set a Mitsuba variant first "
            "(mi.set_variant('llvm_ad_rgb') after `import mcillum`); the plugin classes "
            "bind to it")
    return sorted(_facts, key=lambda n: (_facts[n].listing_order, n))


def facts(name: str) -> Facts:
    """Facts of a registered estimator or ``path``; a user's integrator those
    its class declares (:func:`learn`); an integrator we know nothing about
    (any other Mitsuba plugin) gets neutral facts: no colour of its own,
    assumed to reach everything."""
    if name == REFERENCE:
        return PATH
    if name in _facts:
        return _facts[name]
    if name in _learned:
        return _learned[name]
    return Facts(name, name, None, frozenset(KINDS), None, listing_order=500, ours=False)


#: The facts a user's integrator class may declare as class attributes,
#: each as mcillum's estimators do (module docstring); what it leaves out
#: stays neutral (its name, a spare colour, reaches every kind of content,
#: no pdf bound, any max_depth, unbiased).
DECLARABLE = ("display_name", "colour", "reachable", "max_direction_pdf", "listing_order",
              "depths", "unbiased", "diffuse_only", "learns", "equal_rays_baseline")

#: name → Facts declared by a user's integrator class (not one of ours).
_learned: dict[str, Facts] = {}


def learn(name: str, cls) -> Facts | None:
    """Record the facts plugin class ``cls``, registered as ``name`` by a
    user's code, declares (:data:`DECLARABLE`), and return them; None (and
    nothing recorded) for one of mcillum's estimators, ``path`` or a class
    that declares none. Raises ValueError for a ``reachable`` kind that is
    not one of :data:`KINDS`."""
    if name == REFERENCE or name in _facts:
        return None
    declared = {k: getattr(cls, k) for k in DECLARABLE if hasattr(cls, k)}
    if not declared:
        return None
    reachable = declared.get("reachable", KINDS)
    unknown = [k for k in reachable if k not in KINDS]
    if unknown:
        raise ValueError(f"integrator '{name}' ({cls.__name__}) declares reachable "
                         f"{', '.join(map(str, unknown))}; the kinds are {', '.join(KINDS)}")
    depths = declared.get("depths")
    sets = is_point_set_class(cls)
    found = Facts(name, declared.get("display_name") or name, declared.get("colour"),
                  frozenset(reachable), declared.get("max_direction_pdf"),
                  declared.get("listing_order", 500), ours=False,
                  depths=tuple(depths) if depths is not None else None,
                  # (biased by design exempts it from the unbiasedness test only
                  # where its bias is measured against N instead: a point set)
                  unbiased=bool(declared.get("unbiased", True)) or not sets,
                  diffuse_only=bool(declared.get("diffuse_only", False)),
                  learns=bool(declared.get("learns", False)),
                  equal_rays_baseline=declared.get("equal_rays_baseline", "cosine_hemisphere"),
                  point_set=sets)
    _learned[name] = found
    return found


def palette(names_) -> dict[str, str]:
    """Name → colour for the integrators ``names_``: their own, else a spare
    one (stable for a given list)."""
    names_ = list(names_)
    spare = iter(SPARE_COLOURS * (1 + len(names_) // len(SPARE_COLOURS)))
    out = {}
    for n in names_:
        out[n] = facts(n).colour or next(spare)
    return out


def is_estimator(integrator) -> bool:
    """Is ``integrator`` an instance of one of mcillum's estimator classes
    (which plan their own passes beyond 2³² samples)?"""
    # (the module binds to a variant, so it is looked up, not imported, here)
    base = sys.modules.get(f"{__package__}.estimator")
    return base is not None and isinstance(integrator, base.IlluminationEstimator)
