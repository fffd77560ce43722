"""Untimed renders replayed: Dr.Jit records a render once and replays it.

A render of a few thousand paths costs 3-9 ms, nearly all of it tracing the
integrator's Python and C++ code into a kernel again; the kernel itself is
cached. A frozen function (``dr.freeze``) traces once per spp and replays
the recorded launches with a new seed in about 0.3 ms, and the image is the
same bit for bit (tests/test_replays.py). The statistics render tens of
thousands of such images; timed renders are never replayed, so the speed
stage times what a user's ``mi.render`` costs.

Only integrators whose facts say ``freezable`` are replayed: Mitsuba's
``path`` and mcillum's estimators that do no work in Python between
launches. One that learns in Python between its launches (``guided_path``,
facts ``freezes_passes``) has each launch replayed instead: its
``launch_pass``, frozen, is given to it as ``frozen_pass`` for the render,
and what it learns from still runs. A user's integrator is rendered as
written: what its ``render()`` does in Python would run at the recording
only. So is any integrator on a
scene that holds a Python plugin other than mcillum's (a user's BSDF or
emitter): one that makes a Dr.Jit array from host memory while it is traced
aborts the process during a recording, where no exception can be caught. A
scene or integrator that cannot be recorded (a member Dr.Jit cannot reach,
as Mitsuba's orthographic sensor) is rendered as written from then on.
"""

from __future__ import annotations

import contextlib
import gc

import drjit as dr
import mitsuba as mi

from mcillum.integrators.core import registry

from .renders import launch

#: Recordings kept per (scene, integrator): one per spp, the least recently
#: used dropped first.
RECORDINGS = 8
#: ... of an integrator replayed pass by pass: one per pass of a render
#: (training and image, of their spp), and as many again where a guide's
#: arrays change which of them have the same size.
PASS_RECORDINGS = 32


def freezable(name: str, integrator) -> bool:
    """May ``integrator``, made as plugin ``name``, be recorded and
    replayed: its facts say so, and it is of the class registered under
    that name (a subclass may do Python work the facts do not know of)?"""
    if not registry.facts(name).freezable:
        return False
    if name == registry.REFERENCE:
        return integrator.class_name() == "PathIntegrator"
    return type(integrator) is registry.plugin_class(name)


def freezes_passes(name: str, integrator) -> bool:
    """May each launch of ``integrator``'s render be recorded and replayed
    (facts ``freezes_passes``, the class registered under ``name``)?"""
    return (registry.facts(name).freezes_passes
            and type(integrator) is registry.plugin_class(name))


def foreign_plugins(scene) -> list[str]:
    """The Python plugin classes in ``scene`` that are not mcillum's (its
    own integrator aside: a replay renders with another)."""
    found = {type(obj) for obj in mi.traverse(scene).hierarchy
             if not isinstance(obj, mi.Integrator)}
    return sorted(f"{c.__module__}.{c.__qualname__}" for c in found
                  if not c.__module__.startswith(("mitsuba", "mcillum")))


class Replays:
    """The frozen launches of the scene last rendered untimed, per
    integrator. Only one scene's: a recording holds its scene alive, and
    every live scene's instances slow each render (run/jobs.py)."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        """Drop every recording (before a timed render: nothing held alive)."""
        self._scene, self._foreign = None, []
        self._frozen: dict[int, tuple] = {}         # id(integrator) → (integrator, fn)
        self.refused: set[str] = set()              # what could not record on this scene

    def launcher(self, scene, integrator, name: str):
        """``launch(scene, integrator, spp, seed)`` replaying the recording of
        this scene and integrator, or None where it is rendered as written
        (scalar variants, an integrator neither :func:`freezable` nor
        :func:`freezes_passes`, a scene with :func:`foreign_plugins`, one
        that could not be recorded)."""
        if not dr.is_jit_v(mi.Float) or name in self.refused:
            return None
        whole = freezable(name, integrator)
        if not (whole or freezes_passes(name, integrator)):
            return None
        if scene is not self._scene:
            self.clear()
            self._scene, self._foreign = scene, foreign_plugins(scene)
        if self._foreign:
            return None
        entry = self._frozen.get(id(integrator))
        if entry is None or entry[0] is not integrator:
            entry = (integrator, dr.freeze(launch if whole else integrator.launch_pass,
                                           limit=RECORDINGS if whole else PASS_RECORDINGS,
                                           warn_after=10 ** 6))
            self._frozen[id(integrator)] = entry
        frozen = entry[1]

        def replay(scene_, integrator_, spp, seed):
            try:
                with _no_collection():
                    if whole:
                        # (an opaque seed: one recording per spp, not one per seed)
                        return frozen(scene_, integrator_, spp, dr.opaque(mi.UInt32, seed))
                    integrator_.frozen_pass = frozen
                    try:
                        return launch(scene_, integrator_, spp, seed)
                    finally:
                        integrator_.frozen_pass = None
            except RuntimeError as err:
                if not _recording_failed(err):
                    raise
                self.refused.add(name)
                self._frozen.pop(id(integrator), None)
                return launch(scene_, integrator_, spp, seed)
        return replay


def _recording_failed(err: BaseException) -> bool:
    """Did ``err`` come from Dr.Jit failing to record? (A pass replayed
    inside ``mi.render`` fails inside its custom operation, which raises
    an error of its own from Dr.Jit's.)"""
    while err is not None:
        if "recording a frozen function" in str(err):
            return True
        err = err.__cause__
    return False


@contextlib.contextmanager
def _no_collection():
    """Python's cyclic garbage collector held off. A scene it frees
    releases its ray-tracing structure, and an array made from numpy its
    buffer, through a host function that a recording cannot hold: collected
    while a launch was recorded, an earlier stage's scene aborted the process
    (the quick profile, once in six runs; tests/test_replays.py)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()
