"""Cycle records as fixed-size rows of float64, for the telemetry that leaves the core
(DESIGN §16).

The core writes each recorded cycle into the next row of a table it allocated once
(nothing is allocated per cycle but one list of floats), and hands the filled rows to
the companion as bytes; the companion turns them back into
daemon.process.recording.CycleRecord for the MCAP recorder.  One row, for n cables:

    t | position (3) | quaternion w x y z (4) | twist (6) | lengths (n) | tensions (n) |
    forces (n) | safety state (its index in SafetyState) | reference position (3) |
    reference quaternion (4)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from cdpr.controller import ControlOutput
from daemon.process.recording import CycleRecord
from daemon.service.safety import SafetyState

STATES = tuple(SafetyState)
_STATE_INDEX = {state: float(k) for k, state in enumerate(STATES)}


def row_width(n: int) -> int:
    """Floats in the row of a robot with n cables."""
    return 22 + 3 * n


class CycleRows:
    """A table of `capacity` rows the core fills and empties in turn."""

    def __init__(self, n: int, capacity: int) -> None:
        self.n = n
        self.table = np.zeros((capacity, row_width(n)))
        self.filled = 0

    @property
    def full(self) -> bool:
        return self.filled == len(self.table)

    def add(
        self, t: float, out: ControlOutput, lengths: Sequence[float], state: SafetyState
    ) -> None:
        """Write one cycle into the next row (the caller checks `full` first)."""
        pose, ref = out.pose, out.reference.pose
        self.table[self.filled] = [
            t,
            *pose.position_tuple,
            *pose.quaternion_tuple,
            *out.twist.tolist(),
            *lengths,
            *out.tensions.tolist(),
            *out.commands.tolist(),
            _STATE_INDEX[state],
            *ref.position_tuple,
            *ref.quaternion_tuple,
        ]
        self.filled += 1

    def take(self) -> bytes:
        """The filled rows as bytes; the table is empty again."""
        data = self.table[: self.filled].tobytes()
        self.filled = 0
        return data


def records(data: bytes, n: int) -> list[CycleRecord]:
    """The CycleRecords of rows written by CycleRows.add for n cables."""
    rows = np.frombuffer(data, dtype=np.float64).reshape(-1, row_width(n))
    out = []
    for row in rows.tolist():
        k = 14
        lengths, tensions, forces = (
            row[k : k + n],
            row[k + n : k + 2 * n],
            row[k + 2 * n : k + 3 * n],
        )
        k += 3 * n
        out.append(
            CycleRecord(
                t=row[0],
                position=row[1:4],
                quaternion=row[4:8],
                twist=row[8:14],
                lengths=lengths,
                tensions=tensions,
                forces=forces,
                safety=STATES[int(row[k])].value,
                reference=(row[k + 1 : k + 4], row[k + 4 : k + 8]),
            )
        )
    return out


class Throttle:
    """Lets through at most `rate_hz` cycle times a second, on a fixed grid: one cycle
    time per period, the first at or after each grid point (a gap restarts the grid)."""

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError(f"a throttle's rate must be positive, not {rate_hz}")
        self.period = 1.0 / rate_hz
        self._next = -math.inf

    def due(self, t: float) -> bool:
        """Whether cycle time `t` (s, increasing) is let through."""
        if t < self._next:
            return False
        late = t - self._next > self.period
        self._next = t + self.period if late else self._next + self.period
        return True
