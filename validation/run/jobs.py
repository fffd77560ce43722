"""The unit of work of a validation: one render, as data another process can run.

A :class:`Job` names everything that decides its image: the scene
(:class:`SceneSpec`: its file, its $-parameters as Mitsuba gets them and its
content key), the integrator (:class:`Integrator`: plugin name and
properties), spp and seed. The process that made a job also keeps the loaded
scene and the integrator in it (``live``); they never travel. Another process
rebuilds them from the names in a :class:`Workshop`, which keeps the scene it
is rendering (by content key) and the integrators it made (by name and
properties), so that a worker loads each scene and compiles each kernel once.

A worker on another machine may lack the scene's files (a generated map lives
in the driver's cache) or have them elsewhere: :func:`scene_files` reads them
on the driver, and a workshop given them writes a copy with the same layout
into its node's cache when the files it finds differ (:meth:`Workshop.scene`).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass, field

from mcillum import files as mcillum_files

from ..plan import scenes
from ..plan.scene_files import Film
from . import renders
from .replays import Replays


#: Scenes a workshop keeps loaded. One: every live scene's shapes, BSDFs and
#: emitters join Dr.Jit's instance registry, which every virtual call in a
#: kernel dispatches over, so each scene kept slows every render
#: (docs/measurements.md#2026-11-24-live-scenes-slow-process). A validation
#: renders one scene after another, so a reload is rare.
SCENES_KEPT = 1


@dataclass(frozen=True)
class SceneSpec:
    """A scene as a worker loads it."""

    path: str                                  # the XML file (absolute)
    defines: tuple[tuple[str, str], ...]       # renders.resolve_defines' output
    key: str                                   # references.cache_key: the content hash
    film: tuple[int, int] | None = None        # a user's scene at a reduced film
    crop: tuple[int, int, int, int] | None = None  # (x, y, w, h): that window of the film

    @property
    def loaded(self) -> tuple:
        """What a loaded scene is kept by: its content and its window."""
        return self.key, self.crop

    @property
    def load_film(self):
        """``film`` as renders.load_resolved takes it: with the window, if any."""
        return self.film if self.crop is None else Film(*self.film, self.crop)


@dataclass(frozen=True)
class Integrator:
    """An integrator as a worker makes it, and (``made``) the one this
    process made from the same name and properties (never sent)."""

    name: str
    params: tuple[tuple[str, object], ...]
    made: object = field(default=None, compare=False, repr=False)

    def __getstate__(self):
        return {"name": self.name, "params": self.params, "made": None}

    def __setstate__(self, state):
        for k, v in state.items():
            object.__setattr__(self, k, v)


def make(name: str, params: dict | None = None) -> Integrator:
    """:func:`renders.make_integrator`, remembering how it was made."""
    params = dict(params or {})
    return Integrator(name, tuple(sorted(params.items())), renders.make_integrator(name, params))


def make_taking(name: str, settings: dict) -> Integrator:
    """:func:`make` with those of ``settings`` the integrator takes
    (:func:`renders.make_taking`): its ``params`` say which."""
    made, taken = renders.make_taking(name, settings)
    return Integrator(name, tuple(sorted(taken.items())), made)


@dataclass
class Job:
    """One render: ``integrator`` on ``scene`` at ``spp`` with ``seed``.
    ``live`` is the loaded scene of the process that made the job (never sent)."""

    scene: SceneSpec
    integrator: Integrator
    spp: int
    seed: int
    live: object = field(default=None, compare=False, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "live": None}


def scene_files(spec: SceneSpec) -> dict[str, bytes]:
    """The bytes of the scene file and of every file it references (includes,
    meshes, maps), by absolute path."""
    out = {}
    for path in scenes.referenced_files(spec.path, dict(spec.defines)):
        with open(path, "rb") as f:
            out[path] = f.read()
    return out


class Workshop:
    """The scenes and integrators of one process, built from jobs and kept
    (the last :data:`SCENES_KEPT` scenes used)."""

    def __init__(self):
        self.scenes: OrderedDict[tuple, object] = OrderedDict()   # by SceneSpec.loaded
        self.integrators: dict[tuple, object] = {}
        self.copied: list[str] = []         # scene keys rendered from a copy
        self.replays = Replays()

    def run(self, job: Job, files=None, timed: bool = True) -> renders.Render:
        """Render ``job`` (with its live scene and integrator when it has
        them); ``files()`` gives :func:`scene_files` when the scene is new
        here. An untimed render is replayed where it can be (replays.py); a
        timed one is rendered warm (renders.timed_render)."""
        if timed:
            self.replays.clear()
        scene = job.live if job.live is not None else self.scene(job.scene, files)
        integrator = job.integrator.made
        if integrator is None:
            spec = job.integrator
            integrator = self.integrators.get((spec.name, spec.params))
            if integrator is None:
                integrator = renders.make_integrator(spec.name, dict(spec.params))
                self.integrators[(spec.name, spec.params)] = integrator
        if timed:
            return renders.timed_render(scene, integrator, job.spp, job.seed)
        replay = self.replays.launcher(scene, integrator, job.integrator.name)
        return renders.render(scene, integrator, job.spp, job.seed, replay)

    def scene(self, spec: SceneSpec, files=None):
        """The scene of ``spec``, loaded once per content key and window:
        from its own files when they are here with the same bytes, else from
        a copy of ``files()`` in this node's cache."""
        if spec.loaded not in self.scenes:
            self.scenes[spec.loaded] = renders.load_resolved(*self._local(spec, files),
                                                             film=spec.load_film)
            while len(self.scenes) > SCENES_KEPT:
                self.scenes.popitem(last=False)
        self.scenes.move_to_end(spec.loaded)
        return self.scenes[spec.loaded]

    def _local(self, spec: SceneSpec, files) -> tuple[str, dict]:
        defines = dict(spec.defines)
        if files is None:
            return spec.path, defines
        content = files()
        if all(_same(path, data) for path, data in content.items()):
            return spec.path, defines
        # a copy with the same layout, kept by content key in this node's
        # cache (each file written whole: workers of one node may share it)
        root = mcillum_files.cache_dir("scene_copies", spec.key)
        moved = {}
        for path, data in content.items():
            moved[path] = os.path.join(root, path.lstrip(os.sep))
            if not _same(moved[path], data):
                os.makedirs(os.path.dirname(moved[path]), exist_ok=True)
                with mcillum_files.atomic_path(moved[path]) as tmp:
                    with open(tmp, "wb") as f:
                        f.write(data)
        # relative references follow the copied layout; absolute ones come
        # from $-parameters (a map's checked file): point them at the copies
        self.copied.append(spec.key)
        return moved[spec.path], {k: moved.get(os.path.abspath(v), v) if os.path.isabs(v)
                                  else v for k, v in defines.items()}


def _same(path: str, data: bytes) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read() == data
    except OSError:
        return False
