"""The loop latency a command lead allows for (controller.command_lead "auto"): the time
from a cycle's sample instant to its commands leaving for the drives, as the cycle
measures it, handed to the controller as a median over a window of cycles and bounded.

A median, so that single late cycles (host hiccups of several milliseconds happen)
never move the timing of every command; bounded by one period, because a command that
leaves later than that has missed its cycle, which the deadline counts, not the lead.
"""

from __future__ import annotations

LATENCY_WINDOW = 51  # cycles per median (odd: the middle sample); 0.1 s at 500 Hz


class LatencyMedian:
    """Median of successive windows of measured latencies (s), within [0, bound]."""

    def __init__(self, bound: float, window: int = LATENCY_WINDOW) -> None:
        if window < 1 or not bound > 0.0:
            raise ValueError(f"window must be >= 1 and bound > 0, got {window}, {bound}")
        self.bound = bound
        self._samples = [0.0] * window  # preallocated: no allocation per cycle
        self._count = 0

    def add(self, latency: float) -> float | None:
        """Record one cycle's latency; the window's median once it is full (every
        `window` cycles), else None."""
        samples = self._samples
        i = self._count
        samples[i] = latency
        self._count = i = i + 1
        if i < len(samples):
            return None
        self._count = 0
        median = sorted(samples)[len(samples) // 2]
        return min(max(median, 0.0), self.bound)
