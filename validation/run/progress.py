"""Progress of a validation run: one step per render, with an ETA, on stderr.

On a terminal: one line, rewritten in place after every render. Elsewhere (a
CI log, a pipe): plain lines, no carriage return: one when each stage of a
scene or failure case starts, and otherwise one when a render finishes
:data:`INTERVAL` seconds or more after the last line, each with done/total,
the time elapsed and an ETA. Off (``--quiet``,
``enabled=False``): silent.
"""

from __future__ import annotations

import os
import sys
import time

#: Seconds between two progress lines in a log (not a terminal), when no stage
#: starts in between: often enough that a CI job visibly lives, rarely enough
#: that a run of an hour writes a readable log.
INTERVAL = 30.0
#: The environment variable that overrides :data:`INTERVAL` (seconds), e.g.
#: for a test that wants several lines from a short run.
INTERVAL_ENV = "MCILLUM_PROGRESS_SECONDS"


def interval() -> float:
    """:data:`INTERVAL`, or the positive number of seconds in
    ``$MCILLUM_PROGRESS_SECONDS``. Raises ValueError, naming the variable,
    for a value that is not a positive number."""
    text = os.environ.get(INTERVAL_ENV, "").strip()
    if not text:
        return INTERVAL
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not seconds > 0:
        raise ValueError(f"{INTERVAL_ENV} must be a positive number of seconds, got "
                         f"'{text}'; unset it for the default {INTERVAL:g} s")
    return seconds


def duration(seconds: float) -> str:
    """``seconds`` as a short text: "42 s", "3 min 05 s", "1 h 02 min"."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """Counts the renders of a run and shows them on ``stream`` (stderr).

    ``enabled``: False is silent; None or True shows progress, as one
    rewritten line when ``tty`` (default: whether the stream is a terminal),
    else as plain lines (see the module's doc). ``clock`` and ``interval_s``
    (default :func:`interval`) are for tests; ``log`` is an object whose
    ``flush()`` writes what it held back (run/mitsuba_log.py), called before
    every stage line so that Mitsuba's warnings stay next to the stage that
    caused them. Raises ValueError for a bad ``$MCILLUM_PROGRESS_SECONDS``.
    """

    def __init__(self, total: int, enabled: bool | None = None, *, stream=None,
                 tty: bool | None = None, clock=time.perf_counter,
                 interval_s: float | None = None, log=None):
        self.stream = stream or sys.stderr
        tty = is_terminal(self.stream) if tty is None else tty
        self.mode = None if enabled is False else "bar" if tty else "lines"
        self.enabled = self.mode is not None
        self.clock, self.log = clock, log
        self.interval = interval() if interval_s is None else interval_s
        self.total, self.done, self.start = max(total, 1), 0, clock()
        self.last_line = self.start          # when the last plain line was written
        self.where = ""                      # the stage now running, as lines name it
        self.label = ""                      # its context's label

    def __call__(self, what: str, steps: int = 1) -> None:
        """One render (``steps`` of them) done; ``what`` names it."""
        if "reference" not in what:          # reference passes are not counted
            self.done += steps
        if self.mode == "bar":
            self._write(f"\r[{self.done}/{self.total}] {what[:60]:<60} "
                        f"ETA {self._eta():5.0f} s")
        elif self.mode == "lines" and self.clock() - self.last_line >= self.interval:
            if self.label and what.startswith(self.label + " "):
                what = what[len(self.label) + 1:]       # (the stage's line names it)
            self._line(f"{self.where}: {what}" if self.where else what)

    def stage(self, where: str, name: str, label: str = "") -> None:
        """Stage ``name`` of ``where`` (a scene or failure case whose renders
        ``what`` begins with ``label``) starts: a line in a log; on a
        terminal, nothing new (the bar names each render)."""
        if self.log is not None:
            self.log.flush()
        self.where, self.label = f"{where}, {name.replace('_', ' ')}", label
        if self.mode == "lines":
            self._line(self.where)

    def close(self) -> None:
        """End the bar's line, or write a last line with the run's time."""
        if self.log is not None:
            self.log.flush()
        if self.mode == "bar":
            self._write("\n")
        elif self.mode == "lines":
            self._write(f"[{self.done}/{self.total}] renders done in "
                        f"{duration(self.clock() - self.start)}\n")

    # ----------------------------------------------------------------------

    def _eta(self) -> float:
        """Seconds left at the mean pace so far (0 before the first render)."""
        elapsed = self.clock() - self.start
        left = max(self.total - self.done, 0)
        return elapsed / self.done * left if self.done else 0.0

    def _line(self, text: str) -> None:
        now = self.clock()
        # (sequential tests may render past the plan: then no ETA is known)
        eta = f"ETA {duration(self._eta())}" if 0 < self.done < self.total else "ETA unknown"
        self._write(f"[{self.done}/{self.total}] {text} ({duration(now - self.start)} "
                    f"elapsed, {eta})\n")
        self.last_line = now

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()


def is_terminal(stream) -> bool:
    """Whether ``stream`` is a terminal (False for a closed or file-less one)."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):     # (a closed or file-less stream)
        return False
