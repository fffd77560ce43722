"""What the rest of the machine did while a render was timed.

A timed render's wall time counts whatever else shares the CPUs. Linux says
how busy the CPUs were (``/proc/stat``) and how much of that was this
process (``/proc/self/stat``, every thread): the difference over a render's
wall time is how many cores other processes used meanwhile. Elsewhere
:func:`snapshot` returns None and the load is unknown.

The counters tick at the kernel's clock (usually 100 Hz), so one render of
a few ms reads 0 or a whole tick: sum over a batch (:func:`cores`), not
per render.
"""

from __future__ import annotations

import os
import time
import typing

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


class Snapshot(typing.NamedTuple):
    wall: float          # time.perf_counter()
    busy: int            # ticks every CPU spent on anything but idle and iowait
    own: int             # ticks this process spent (user + system, all threads)


def snapshot() -> Snapshot | None:
    """The counters now; None where /proc is not there (not Linux)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            cpu = [int(x) for x in f.readline().split()[1:]]
        with open("/proc/self/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, ValueError, IndexError):
        return None
    # /proc/stat: user nice system idle iowait irq softirq steal ...
    busy = sum(cpu) - cpu[3] - (cpu[4] if len(cpu) > 4 else 0)
    # /proc/self/stat after the name: field 14 utime and 15 stime are at 11, 12
    return Snapshot(time.perf_counter(), busy, int(fields[11]) + int(fields[12]))


def others_seconds(before: Snapshot | None, after: Snapshot | None) -> float | None:
    """CPU seconds other processes used between two snapshots (None if
    either is unknown)."""
    if before is None or after is None:
        return None
    return max((after.busy - before.busy) - (after.own - before.own), 0) / _TICK


def cores(others: list, seconds: list) -> float | None:
    """The cores other processes used on average over renders that took
    ``seconds`` while they used ``others`` CPU seconds; None if any is
    unknown or the renders took no time."""
    wall = float(sum(seconds))
    if not others or any(o is None for o in others) or wall <= 0:
        return None
    return float(sum(others)) / wall
