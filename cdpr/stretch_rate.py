"""How fast the cables stretch along the reference: the rate of the tensions the
reference needs, as the drums can follow them.

A cable whose drum paid out l is l C s t longer under tension t (cdpr.stretch: C the robot
file's compliance 1/EA, s its identified scale).  When the tensions change the drums move
by l C s t' more than the geometry does, so (cdpr.controller):

- their reported rates are off the cables' by l C s t': a vertical lift changing its
  tensions by 400 N/s on 2.5 m of cable with EA 1e5 N is 10 mm/s, which the twist's
  complementary filter removes only over velocity_filter (50 ms), the derivative action
  braking the platform meanwhile (bench/planning.py's lift tracked at 0.18 mm);
- the winches need k0 l C s t' more force to move the drums that far.

The actual tensions follow the controller's commands, hence its feedback: the planned
tensions' rate fed into the twist closes a loop, which went unstable when tried.  The
tensions the reference alone needs (its wrench distributed as the controller distributes
its own) are open-loop, but a reference whose acceleration steps (a path timed without a
jerk limit) steps them too, which no drum follows: a drum of mass m0 on its cable's spring
EA / l, driven through the drive's force lag, takes about drive lag + sqrt(m0 l / EA) to
stretch it (9 ms for reference8).  So the tensions are taken through a first-order lag of
that time constant (the tensions linear between the cycles' instants), whose rate (input
minus output over the time constant) is t'.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

SETTLED = 1e-6  # N: a lagged tension this close to its input is the input (at rest)


def stretch_time(m0: Array, lengths: Array, compliance: Array, drive_lag: float) -> float:
    """The lag (s) of the drums stretching their cables: the drive's force lag plus the
    longest 1 / omega of a drum of mass m0 on its cable's spring (EA / l, C = 1/EA)."""
    return drive_lag + float(np.sqrt(m0 * lengths * compliance).max())


class TensionRate:
    """The reference's tensions through a first-order lag of `time_constant` (s), and
    their rate.  Kept as the gap between input and lagged output, the lag's rate times
    the time constant: for tensions linear between two instants h apart, the gap
    becomes change (tau / h) (1 - e^(-h / tau)) + gap e^(-h / tau)."""

    def __init__(self, time_constant: float) -> None:
        if not time_constant > 0.0:
            raise ValueError(f"the time constant must be > 0 s, got {time_constant!r}")
        self.time_constant = time_constant
        self.clear()

    def clear(self) -> None:
        """Forget the history (a reset, a reference outside W): the next tensions are
        taken as followed already."""
        self._time = -math.inf
        self._input: Array | None = None
        self._gap: Array | None = None  # None: settled (zero)

    def add(self, time: float, tensions: Array | None) -> Array | None:
        """The reference's tensions for `time` (s): the lagged tensions' rate t' (N/s)
        then, or None where it is zero (the same input array as last time, the lag caught
        up with it: a reference at rest reuses its terms).  None for tensions None (the
        reference's wrench is not in W: the history restarts) and for a time before the
        last (restarts too); the same time again is taken as a step."""
        previous = self._input
        if tensions is None or previous is None or time < self._time:
            self.clear()
            if tensions is not None:
                self._time, self._input = time, tensions
            return None
        elapsed, tau = time - self._time, self.time_constant
        self._time, self._input = time, tensions
        if tensions is previous and self._gap is None:  # settled at rest
            return None
        decay = math.exp(-elapsed / tau)
        gap = (tensions - previous) * ((tau / elapsed) * (1.0 - decay) if elapsed > 0.0 else 1.0)
        if self._gap is not None:
            gap += self._gap * decay
        if float(gap.dot(gap)) < SETTLED * SETTLED:
            self._gap = None
            return None
        self._gap = gap
        return gap / tau
