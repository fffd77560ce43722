"""Progress of a validation run: one step per render, with an ETA, on stderr
when it is a terminal (silent otherwise)."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, total: int, enabled: bool | None = None):
        self.total, self.done, self.start = max(total, 1), 0, time.perf_counter()
        self.enabled = sys.stderr.isatty() if enabled is None else enabled

    def __call__(self, what: str, steps: int = 1) -> None:
        if "reference" not in what:          # reference passes are not counted
            self.done += steps
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        eta = elapsed / self.done * (self.total - self.done) if self.done else 0.0
        sys.stderr.write(f"\r[{self.done}/{self.total}] {what[:60]:<60} ETA {eta:5.0f} s")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
