"""The fastest rest-to-rest motion of one coordinate within a speed, an acceleration and a
jerk limit: the double-S (seven-phase) profile (Biagiotti and Melchiorri, Trajectory
Planning for Automatic Machines and Robots, 2008, section 3.4, rest to rest).

Jerk +j, 0, -j ramps the acceleration up to its peak and back while the speed rises to
its cruise, the cruise holds, and the mirror image brings the motion to rest; the
acceleration's plateau is absent where the cruise speed is reached first, the cruise
where the distance is too short for it.  Piecewise cubic in time: a quintic Hermite
segment between two phase boundaries (cdpr.trajectory.core) reproduces it exactly.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass


@dataclass(frozen=True)
class DoubleS:
    """A profile over `distance` (> 0): jerk phases of `jerk_time` s at +-`jerk`, an
    acceleration phase (jerk phases included) of `accel_time` s, and a cruise of
    `cruise_time` s."""

    distance: float
    jerk: float
    jerk_time: float
    accel_time: float
    cruise_time: float

    @classmethod
    def fastest(cls, distance: float, speed: float, accel: float, jerk: float) -> DoubleS:
        """The shortest profile over `distance` within the limits (all > 0)."""
        if speed * jerk >= accel * accel:  # the acceleration reaches its limit
            t_j, t_a = accel / jerk, accel / jerk + speed / accel
        else:
            t_j = math.sqrt(speed / jerk)
            t_a = 2.0 * t_j
        cruise = distance / speed - t_a
        if cruise < 0.0:  # the cruise speed is not reached
            cruise = 0.0
            t_j = accel / jerk
            t_a = 0.5 * (t_j + math.sqrt(t_j * t_j + 4.0 * distance / accel))
            if t_a < 2.0 * t_j:  # nor is the acceleration limit
                t_j = (0.5 * distance / jerk) ** (1.0 / 3.0)
                t_a = 2.0 * t_j
        return cls(distance, jerk, t_j, t_a, cruise)

    @property
    def duration(self) -> float:
        return 2.0 * self.accel_time + self.cruise_time

    def lasting(self, duration: float) -> DoubleS:
        """The same profile slowed down uniformly to last `duration` (>= its own): every
        time x k, the jerk / k^3, the acceleration / k^2, the speed / k."""
        k = duration / self.duration
        return DoubleS(
            self.distance, self.jerk / k**3, self.jerk_time * k, self.accel_time * k,
            self.cruise_time * k,
        )  # fmt: skip

    def boundaries(self) -> list[float]:
        """The times at which its jerk changes, from 0 to the end (phases of zero length
        left out)."""
        t_j, t_a, t_v = self.jerk_time, self.accel_time, self.cruise_time
        edges = [0.0, t_j, t_a - t_j, t_a, t_a + t_v, t_a + t_v + t_j, self.duration - t_j]
        out = [0.0]
        for t in [*edges[1:], self.duration]:
            if t > out[-1]:
                out.append(t)
        return out

    def at(self, t: float) -> tuple[float, float, float]:
        """(position, speed, acceleration) at time t (rest before 0 and after the end)."""
        if t <= 0.0:
            return 0.0, 0.0, 0.0
        if t >= self.duration:
            return self.distance, 0.0, 0.0
        starts, states, jerks = self._phases()
        i = bisect_right(starts, t) - 1
        s, v, a = states[i]
        d = t - starts[i]
        j = jerks[i]
        return s + v * d + a * d * d / 2.0 + j * d**3 / 6.0, v + a * d + j * d * d / 2.0, a + j * d

    def _phases(self) -> tuple[list[float], list[tuple[float, float, float]], list[float]]:
        """Each phase's start time, state (s, v, a) there and jerk."""
        t_j, t_a, t_v, j = self.jerk_time, self.accel_time, self.cruise_time, self.jerk
        lengths = [t_j, t_a - 2.0 * t_j, t_j, t_v, t_j, t_a - 2.0 * t_j, t_j]
        jerks = [j, 0.0, -j, 0.0, -j, 0.0, j]
        starts, states = [], []
        t, s, v, a = 0.0, 0.0, 0.0, 0.0
        for length, jerk in zip(lengths, jerks, strict=True):
            starts.append(t)
            states.append((s, v, a))
            d = length
            s, v, a = (
                s + v * d + a * d * d / 2 + jerk * d**3 / 6,
                v + a * d + jerk * d * d / 2,
                a + jerk * d,
            )
            t += d
        return starts, states, jerks
