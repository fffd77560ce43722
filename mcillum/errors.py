"""Errors that reach a user, and Mitsuba's error text made readable.

* :class:`UserError` — a mistake in what the user gave, with a message that
  says what was wrong and what to do. Every such error of mcillum derives
  from it (bad maps and map parameters, unwritable outputs, unknown
  integrators, broken scenes, unreadable results). ``usage`` says whether the
  command line alone shows it (exit code 2 in the CLI: an unknown integrator
  or parameter, an output path that cannot be written) or it was found while
  loading or rendering (exit code 1: a broken scene file, an unknown
  $-parameter, a refused environment map). :class:`NoSignal` is found while
  rendering but exits 2 all the same: the scene as given cannot be validated
  at all (a black reference, which every estimator would match).
* :class:`Interrupted` — Ctrl-C or SIGTERM, with what was left and what to do;
  :func:`sigterm_as_interrupt` turns SIGTERM into a KeyboardInterrupt
  (:class:`Terminated`), so that every clean-up path of Ctrl-C runs for it too.
* :func:`message` — the innermost cause of an exception as one line: Mitsuba
  wraps a plugin's error in "At dictionary node …", source locations and the
  Python traceback of the plugin; only the cause is kept.
"""

from __future__ import annotations

import re
import signal
import threading
from contextlib import contextmanager


class UserError(Exception):
    """A mistake in the user's input; the message says what to do."""

    usage = False


class UsageError(UserError):
    """A mistake the command line alone shows."""

    usage = True


class IntegratorError(UserError):
    """An unknown integrator, a plugin that is not one, or a bad parameter."""

    usage = True


class SceneError(UserError):
    """A scene that cannot be loaded as given."""


class NoSignal(SceneError):
    """A user's scene whose reference is black in every pixel (no emitter,
    or none the sensor sees): nothing to validate, since any estimator
    matches black. ``usage`` is True so that the CLI exits 2 as for a usage
    error: no check of such a scene could fail, and a run that reported
    them would pass vacuously (issue 66)."""

    usage = True


class Interrupted(Exception):
    """Ctrl-C or SIGTERM, with what was left and what to do."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised as an interrupt (see :func:`sigterm_as_interrupt`)."""


def _raise_terminated(signum, frame):
    raise Terminated()


@contextmanager
def sigterm_as_interrupt():
    """While inside, SIGTERM raises :class:`Terminated` in the main thread
    (elsewhere nothing changes); the previous handler comes back on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def root_cause(exc: BaseException) -> BaseException:
    """The innermost exception of a chain (``mi.render`` wraps plugin errors)."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return exc


def is_interrupt(exc: BaseException) -> bool:
    """Ctrl-C, possibly wrapped by Mitsuba or Dr.Jit on its way out of a render."""
    return isinstance(root_cause(exc), KeyboardInterrupt) or "KeyboardInterrupt" in str(exc)


#: Mitsuba's "[parser.cpp:1718] " source locations.
_SOURCE = re.compile(r"\[[\w./\\-]+\.(?:cpp|h|inl|py):\d+\]\s*")
_TRACEBACK = "Traceback (most recent call last):"
#: The head of Mitsuba's errors from ``mi.load_dict`` (no file, no line: noise).
_DICT_HEAD = re.compile(r'^(?:While loading|At) dictionary node "[^"]*":\s*'
                        r'(?:failed to instantiate [\w ]*plugin of type "[^"]*":\s*)?')


def message(err: BaseException, context: bool = True) -> str:
    """The innermost cause of ``err`` as one clean message: no Mitsuba source
    locations, and no Python traceback (Mitsuba embeds one in the message of a
    Python plugin's exception): only its last exception line. ``context=False``
    drops Mitsuba's "At dictionary node ...: failed to instantiate ..." head."""
    cause = root_cause(err)
    text = str(cause).strip() or f"{type(cause).__name__} (no message)"
    head, marker, _ = text.partition(_TRACEBACK)
    if marker:
        lines = text.rpartition(_TRACEBACK)[2].splitlines()[1:]
        start = next((k for k, line in enumerate(lines) if line and not line[0].isspace()),
                     len(lines))
        last = re.sub(r"^[A-Za-z_][\w.]*(?:Error|Exception): ", "",
                      "\n".join(lines[start:]).strip())
        head = head.strip().rstrip(":").strip()
        text = f"{head}: {last}" if head and context else last
    text = _SOURCE.sub("", text).replace("unknown plugin of type", "plugin of type")
    if not context:
        text = _DICT_HEAD.sub("", text)
    return text.strip()


def unused_defines(text: str) -> list[str]:
    """The $-parameters Mitsuba's parser reports as given but unused."""
    return re.findall(r"^\s*- \$(\w+)=", text, re.M)


def plugin_not_found(text: str) -> bool:
    return re.search(r'Plugin "[^"]*" not found', text) is not None


def unreferenced_properties(text: str) -> list[str]:
    """The properties Mitsuba reports as given to a plugin that never read them."""
    if "unreferenced propert" not in text:
        return []
    return re.findall(r'^\s*- \w+ "([^"]+)"', text, re.M)
