"""Mitsuba's log during a validation run: plain text in a log, and a warning
repeated for each estimator said once.

Mitsuba's ``StreamAppender`` (the one appender of its logger) colours every
warning and error with ANSI escapes, whether or not stderr is a terminal, so
a CI log fills with ``ESC[31m``. Inside :func:`plain`, a Python
:class:`Appender` takes its place on ``mi.logger()``: it writes the same
text (Mitsuba's ``DefaultFormatter`` formats it, without colour), coloured
only on a terminal. Warnings that differ only in the integrator they name
(:data:`REPEATED`: an opted-in refusal, one per estimator of a failure case)
are held back and written as one line naming them all, on :meth:`Appender.flush`
(progress calls it when a stage starts) or before any other message.
"""

from __future__ import annotations

import re
import sys
import threading
from contextlib import contextmanager

import mitsuba as mi

from . import progress

#: Warnings said once per integrator: the group ``name`` is the integrator,
#: the rest of the match is the same for all of them.
REPEATED = (
    # integrators/core/scene_checks.py, check_reachable
    re.compile(r"(?P<name>[\w.-]+) with allow_unreachable=true: "),
)

#: The time DefaultFormatter puts first (repeats a second apart still fold).
_TIME = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s*")

#: Mitsuba's colours on a terminal (its StreamAppender's).
_COLOUR = {mi.LogLevel.Warn: "\x1b[31m", mi.LogLevel.Error: "\x1b[31m",
           mi.LogLevel.Debug: "\x1b[38;5;245m"}
_RESET = "\x1b[0m"


class Appender(mi.Appender):
    """Writes Mitsuba's log messages to ``stream`` (coloured only if
    ``colour``), folding the warnings of :data:`REPEATED` into one line per
    text until :meth:`flush`."""

    def __init__(self, stream=None, colour: bool = False):
        super().__init__()
        self.stream, self.colour = stream, colour
        #: (level, head without its time, rest) → [head, names in order]
        self.held: dict[tuple, list] = {}
        self.lock = threading.Lock()        # (Mitsuba may log from its worker threads)

    def append(self, level, text: str) -> None:
        with self.lock:
            for pattern in REPEATED:
                m = pattern.search(text)
                if m:
                    head, rest = text[:m.start("name")], text[m.end("name"):]
                    key = (level, _TIME.sub("", head), rest)
                    names = self.held.setdefault(key, [head, []])[1]
                    if m["name"] not in names:
                        names.append(m["name"])
                    return
            self._flush()
            self._write(level, text)

    def log_progress(self, progress, name, formatted, eta, ptr=None) -> None:
        """Mitsuba's own progress bars: not shown (the run has its own)."""

    def flush(self) -> None:
        """Write the held-back warnings, one line each with the integrators
        it was said for."""
        with self.lock:
            self._flush()

    def _flush(self) -> None:
        for (level, _, rest), (head, names) in self.held.items():
            who = names[0] if len(names) == 1 else \
                f"{len(names)} integrators ({', '.join(names)})"
            self._write(level, f"{head}{who}{rest}")
        self.held.clear()

    def _write(self, level, text: str) -> None:
        stream = self.stream or sys.stderr
        colour = _COLOUR.get(level, "") if self.colour else ""
        # (on a terminal, first clear a progress line that has no newline yet)
        start = "\r\x1b[K" if self.colour else ""
        stream.write(f"{start}{colour}{text}{_RESET if colour else ''}\n")
        stream.flush()


@contextmanager
def plain(stream=None, colour: bool | None = None):
    """While inside, Mitsuba's log goes through an :class:`Appender` (yielded)
    in place of its own appenders, which come back on exit. ``colour``:
    default, whether ``stream`` (stderr) is a terminal."""
    if colour is None:
        colour = progress.is_terminal(stream or sys.stderr)
    logger = mi.logger()
    own = [logger.appender(i) for i in range(logger.appender_count())]
    appender = Appender(stream, colour)
    for a in own:
        logger.remove_appender(a)
    logger.add_appender(appender)
    try:
        yield appender
    finally:
        appender.flush()
        logger.remove_appender(appender)
        for a in own:
            logger.add_appender(a)
