"""Garbage collection on the daemon's schedule, not the interpreter's.

CPython collects whenever allocations cross a threshold, wherever the program is: a
full (generation 2) collection scans every live object and stalls whatever runs, a
control cycle included.  So once start-up is done its objects are frozen out of
scanning, automatic collection is turned off, and the service calls `after_cycle` once
its commands are on the bus: the young generations (0 and 1) are collected there when
due, which is cheap because they hold only what was made since the last one.  The
oldest generation is never collected after start-up, not even while the robot stands
still, since the drives' watchdogs wait for the cycle then too (a full collection
stalled the loop for over a second in the user-mode Linux tests).  Objects reach it
only by surviving two young collections, which per-cycle garbage does not;
`tests/daemon/test_daemon_flood.py` checks that memory stays bounded.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass


@dataclass
class CollectorStats:
    """What the policy did; `max_young_us` is the longest young collection."""

    young: int = 0
    max_young_us: float = 0.0

    def summary(self) -> dict[str, float]:
        return {"young": self.young, "max_young_us": round(self.max_young_us, 1)}


class CollectorPolicy:
    """`start()` once start-up objects exist, `after_cycle()` every cycle, `close()` to
    give collection back to the interpreter."""

    def __init__(self) -> None:
        self.stats = CollectorStats()
        self._young_threshold, self._middle_threshold, _ = gc.get_threshold()
        self._active = False

    def start(self) -> None:
        """Freeze what exists now (collect before, while no watchdog waits: a full
        collection of the start-up heap takes tens of milliseconds) and take over."""
        gc.freeze()  # start-up objects never need scanning again
        gc.disable()
        self._active = True

    def after_cycle(self) -> None:
        if not self._active:
            return
        young, middle, _ = gc.get_count()
        if young >= self._young_threshold:
            started = time.perf_counter()
            gc.collect(1 if middle >= self._middle_threshold else 0)
            elapsed = (time.perf_counter() - started) * 1e6
            self.stats.young += 1
            self.stats.max_young_us = max(self.stats.max_young_us, elapsed)

    def close(self) -> None:
        if self._active:
            self._active = False
            gc.enable()
            gc.unfreeze()
