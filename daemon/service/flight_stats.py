"""What one trajectory's flight did, cycle by cycle, as the core saw it.

The trajectory_done event carries it: the largest position and orientation tracking
errors and the lowest and highest cable tension over every cycle of the flight.  Sampled
states cannot give that: they are published at the companion's rate, and a companion
starved of CPU (a busy host, a one-CPU guest) publishes none over a whole flight.
"""

from __future__ import annotations

import math

from cdpr.controller import ControlOutput


class FlightStats:
    """Extremes over the cycles added since construction (one flight)."""

    __slots__ = ("cycles", "orientation_error", "position_error", "tension_max", "tension_min")

    def __init__(self) -> None:
        self.cycles = 0
        self.position_error = 0.0  # m
        self.orientation_error = 0.0  # rad
        self.tension_min = math.inf  # N
        self.tension_max = -math.inf  # N

    def add(self, tracking_errors: tuple[float, float], output: ControlOutput) -> None:
        """One cycle: its tracking errors' norms as the safety check judged them
        (SafetyMonitor.tracking_errors: m, rad) and its output's tensions (plain floats,
        no numpy reductions)."""
        tensions = output.tensions.tolist()
        self.cycles += 1
        self.position_error = max(self.position_error, tracking_errors[0])
        self.orientation_error = max(self.orientation_error, tracking_errors[1])
        self.tension_min = min(self.tension_min, *tensions)
        self.tension_max = max(self.tension_max, *tensions)

    def summary(self) -> dict[str, float | int]:
        """The event's fields (tensions null when no cycle was added)."""
        flown = self.cycles > 0
        return {
            "cycles": self.cycles,
            "max_position_error": self.position_error,
            "max_orientation_error": self.orientation_error,
            "tension_min": self.tension_min if flown else None,
            "tension_max": self.tension_max if flown else None,
        }
