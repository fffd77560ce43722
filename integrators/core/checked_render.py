"""The entry of every mcillum estimator's render: the scene checked once,
whether this estimator renders it or a wrapper calls its ``sample()``, and
wavefronts beyond 2³² samples split into passes (passes.py).

:class:`CheckedRender` sits between Mitsuba's ``SamplingIntegrator`` and
:class:`~.estimator.IlluminationEstimator`, which supplies
:meth:`check_scene`. Like estimator.py, this module must be (re)imported
after a variant is set: its class derives from that variant's
``mi.SamplingIntegrator`` (``mcillum.integrators.register()`` takes care of
it).
"""

from __future__ import annotations

import signal
import threading

import mitsuba as mi

from . import passes


def _scene_fingerprint(scene) -> tuple:
    """Which scene a check was for: its address and what it holds (a scene
    cannot be weakly referenced, and a strong reference would keep it alive,
    slowing every later render; an address alone may be reused)."""
    box = scene.bbox()
    return (id(scene), len(scene.shapes()), len(scene.emitters()),
            tuple(float(x) for x in box.min), tuple(float(x) for x in box.max))


class CheckedRender(mi.SamplingIntegrator):
    """Mitsuba's integrator with the scene checked before any work and
    renders beyond 2³² samples split into passes (not registered)."""

    def check_scene(self, scene) -> None:
        """Refuse a scene this estimator would render wrong (raise
        :class:`~.scene_checks.UnreachableContentError`): the subclass's."""
        raise NotImplementedError

    def check_wrapped(self, scene) -> None:
        """The scene check where :meth:`render` was not the entry: another
        integrator (``moment``, ``aov``, a user's wrapper) calls
        :meth:`sample` directly. Once per scene, as :meth:`render` would
        have run it; within this estimator's own render, nothing."""
        if getattr(self, "_in_pass", False):
            return
        seen = _scene_fingerprint(scene)
        if getattr(self, "_checked", None) != seen:
            self.check_scene(scene)
            self._checked = seen

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if getattr(self, "_in_pass", False):
            # (Mitsuba's render calls back into this override: the outer call
            # has checked the scene and planned the passes already.)
            return self._mitsuba_render(scene, sensor, seed, spp, develop, evaluate)

        self.check_scene(scene)

        # Split wavefronts beyond 32 bits into passes (see passes.py).
        sensor_ = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        spp = spp or sensor_.sampler().sample_count()
        plan = passes.plan_passes(passes.film_lanes(sensor_.film()), spp)
        self._in_pass = True
        try:
            return self._render_passes(scene, sensor, seed, spp, plan, develop, evaluate)
        finally:
            self._in_pass = False

    def _render_passes(self, scene, sensor, seed, spp, plan, develop, evaluate):
        if len(plan) == 1:
            return self._mitsuba_render(scene, sensor, seed, spp, develop, evaluate)
        if not develop:
            raise ValueError(
                f"{self.plugin_name}: {spp} spp need {len(plan)} passes (over 2^32 "
                "samples), which cannot accumulate into an undeveloped film; "
                "render with develop=True or fewer spp per call")
        return passes.render_in_passes(
            plan, seed, lambda s, n: self._mitsuba_render(scene, sensor, s, n, True, True))

    def _mitsuba_render(self, scene, sensor, seed, spp, develop, evaluate):
        """Mitsuba's own render, nested inside the caller's ``mi.render``.

        Mitsuba's render binding installs a SIGINT handler for its duration and
        keeps the one it replaced in a single static variable. A nested render
        would save the *outer* render's handler there and leave it installed
        for good: every later Ctrl-C in the process would only log "Received
        interrupt signal". Re-installing Python's own handler first makes the
        nested render save and restore Python's, so Ctrl-C stays a
        KeyboardInterrupt (tests/test_plugins.py).
        """
        if threading.current_thread() is threading.main_thread():
            handler = signal.getsignal(signal.SIGINT)
            if handler is not None:        # None: not installed from Python
                signal.signal(signal.SIGINT, handler)
        return super().render(scene, sensor, seed, spp, develop, evaluate)
