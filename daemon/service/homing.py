"""Length offsets in the core: which apply, whether each still holds (DESIGN §15 step 3).

The drivers turn motor positions into lengths with the config's drives.length_offset;
homing and calibration find better offsets (daemon.service.calibration_state stores
them).  `LengthOffsets` keeps, per cable, the correction from the config's offset to the
one in force, applied to every length the core reads and taken off every length it
hands to the drives, so that the drivers, and the simulated drives that share their
config, stay as configured.

A drive that restarted (its position counts from a new zero) invalidates its offset, and
enable is refused until homing finds a new one.  `watch` runs every cycle and sees it:
- the driver counts a restart in NodeStatus.restarts (a CiA 402 boot-up heartbeat);
- a drive whose feedback was missing for `silent_cycles` cycles while the other drives
  answered (an ODrive power cycle: firmware 0.6 sends no boot-up message) and that comes
  back more than `tolerance` from where it went silent.
A drive that restarted while no daemon ran is not seen here: its lengths then usually
fit no pose and the start-up trust check refuses them (daemon.service.trusted_lengths).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from daemon.service.calibration_state import CalibrationState
from drivers.base import Feedback, NodeStatus


class LengthOffsets:
    """Per-cable offsets in force (`offsets`, m) over the config's (`configured`), and why
    any no longer holds (`invalid`, None where it holds)."""

    def __init__(
        self,
        configured: Sequence[float],
        nodes: Sequence[int],
        silent_cycles: int,
        tolerance: float,
    ) -> None:
        self.configured = [float(x) for x in configured]
        self.n = n = len(self.configured)
        self.nodes = list(nodes)
        self.correction = [0.0] * n  # in force minus configured
        self.corrected = False  # any correction non-zero (the cycle skips the work if not)
        self.invalid: list[str | None] = [None] * n
        self.method = "config (drives.length_offset)"
        self.time: float | None = None
        self.silent_cycles = silent_cycles
        self.tolerance = tolerance
        self._restarts: list[int | None] = [None] * n
        self._silent = [0] * n
        self._last = [math.nan] * n  # each cable's length when it last answered

    @property
    def offsets(self) -> list[float]:
        return [c + d for c, d in zip(self.configured, self.correction, strict=True)]

    def adopt(self, state: CalibrationState) -> None:
        """Take the offsets, their validity and provenance from a stored state."""
        self.set(list(state.offsets), state.method, state.time)
        self.invalid = list(state.invalid)

    def set(self, offsets: Sequence[float], method: str, stamp: float | None) -> list[float]:
        """Put `offsets` in force, every one valid; the change of each (m)."""
        previous = self.correction
        self.correction = [o - c for o, c in zip(offsets, self.configured, strict=True)]
        self.corrected = any(self.correction)
        self.invalid = [None] * self.n
        self.method, self.time = method, stamp
        return [new - old for new, old in zip(self.correction, previous, strict=True)]

    def invalidate_all(self, why: str) -> None:
        self.invalid = [why] * self.n

    def read(self, lengths: list[float]) -> list[float]:
        """Driver lengths -> lengths with the offsets in force."""
        if not self.corrected:
            return lengths
        return [x + d for x, d in zip(lengths, self.correction, strict=True)]

    def write(self, lengths: Sequence[float]) -> list[float]:
        """Lengths with the offsets in force -> driver lengths."""
        return [x - d for x, d in zip(lengths, self.correction, strict=True)]

    def refusal(self) -> str | None:
        """Why enabling must wait for homing (None: every offset holds)."""
        lost = [
            f"drive {k} (node {self.nodes[k]}): {why}" for k, why in enumerate(self.invalid) if why
        ]
        if not lost:
            return None
        return "length offsets not valid, home first (cdprd home): " + "; ".join(lost)

    def watch(
        self, status: Sequence[NodeStatus], feedback: Sequence[Feedback], fresh: Sequence[bool]
    ) -> list[tuple[int, str]]:
        """One cycle's look for drives that lost their position (module docstring): the
        (drive, reason) of each newly lost one."""
        lost: list[tuple[int, str]] = []
        answered = any(fresh)
        for k in range(self.n):
            restarts = status[k].restarts
            seen = self._restarts[k]
            self._restarts[k] = restarts
            if seen is not None and restarts != seen:
                lost.append(
                    (k, "the drive restarted (boot-up): its position counts from a new zero")
                )
            if not fresh[k]:
                if answered:
                    self._silent[k] += 1
                continue
            length = feedback[k].length
            silent, self._silent[k] = self._silent[k], 0
            before, self._last[k] = self._last[k], length
            if silent >= self.silent_cycles and abs(length - before) > self.tolerance:
                lost.append(
                    (
                        k,
                        f"silent for {silent} cycles, it came back "
                        f"{(length - before) * 1e3:+.1f} mm from where it went silent (a power "
                        "cycle: its position counts from a new zero)",
                    )
                )
        for k, why in lost:
            if self.invalid[k] is None:
                self.invalid[k] = why
        return lost
