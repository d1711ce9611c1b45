"""One short progress line on stderr for preparation that runs long (sign grids,
measuring the arithmetic): silent for the first `AFTER_S` seconds."""

from __future__ import annotations

import sys
import time

__all__ = ["Progress", "AFTER_S"]

AFTER_S = 2.0


class Progress:
    """``say(message)`` rewrites one stderr line once `AFTER_S` have passed since the
    start; ``done(message)`` ends it (only if a line was shown or the work was long)."""

    def __init__(self):
        self.start = time.perf_counter()

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def say(self, message: str, end: bool = False) -> None:
        if self.elapsed >= AFTER_S:
            print(f"\r{message:<78}", end="\n" if end else "", file=sys.stderr, flush=True)

    def done(self, message: str) -> None:
        self.say(message, end=True)
