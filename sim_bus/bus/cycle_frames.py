"""The load each bus of a CiA 402 config carries at a cycle rate, from its configured
host driver and drive profile (sim_bus.bus.busload's frame model).

One steady-state torque cycle on a bus is: the SYNC of the host driver, the torque
commands it sends (one RPDO per drive, or one shared RPDO for the bus; a control RPDO
sent on change is not part of the steady state), and each drive's TPDOs on SYNC (those
sent on change are not either).  Heartbeats come at their own period, not each cycle:
every drive's (0x1017, drives.heartbeat_period) and the host's (one per bus, every
DrivesConfig.host_heartbeat_interval: 5 ms by default, 1.3 % of a 1 Mbit/s bus).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import can

from cdpr import Robot
from drivers.cia402.codec import HEARTBEAT_BASE, message
from drivers.cia402.host import Cia402Driver
from drivers.config import CanConfig, DrivesConfig
from drivers.factory import make_driver
from drivers.multibus import MultiBusDriver
from sim_bus.bus.busload import Stuffing, cycle_load

# the simulator's bus (python-can interface name, pyproject's entry point): it takes no
# bus time, so a cycle's frames fit however many there are
SIMULATED_BUS = "cdprd_loop"


@dataclass(frozen=True)
class BusCycle:
    """One bus: the frames of a steady-state cycle, and its heartbeats: the drives' at
    their own period, the host's (one per bus) at the period its cycle rate gives it."""

    name: str
    bitrate: int
    cycle: list[can.Message]
    drive_heartbeats: float  # frames per second (1 data byte each)
    drives: DrivesConfig  # the host heartbeat's period
    feedback: list[can.Message]  # the SYNC and the drives' TPDOs on it

    def feedback_time(self, stuffing: Stuffing = "worst") -> float:
        """Seconds the SYNC and every drive's answers to it occupy the bus: the earliest
        the last answer can be in after the SYNC starts, however fast the drives answer
        (the drives' own reaction comes on top)."""
        return cycle_load(self.feedback, 1.0, self.bitrate, stuffing).bits_per_cycle / (
            self.bitrate
        )

    def bits_per_cycle(self, stuffing: Stuffing = "worst") -> float:
        """The bits of one cycle's frames (heartbeats not included)."""
        return cycle_load(self.cycle, 1.0, self.bitrate, stuffing).bits_per_cycle

    def heartbeats(self, rate_hz: float) -> float:
        """Heartbeat frames per second at `rate_hz` cycles per second."""
        return self.drive_heartbeats + 1.0 / self.drives.host_heartbeat_interval(1.0 / rate_hz)

    def heartbeat_bits(self, rate_hz: float, stuffing: Stuffing = "worst") -> float:
        """The heartbeats' bits per second at `rate_hz` cycles per second."""
        beat = [message(HEARTBEAT_BASE, b"\x05")]
        return cycle_load(beat, 1.0, self.bitrate, stuffing).bits_per_cycle * self.heartbeats(
            rate_hz
        )

    def load(self, rate_hz: float, stuffing: Stuffing = "worst") -> float:
        """Fraction of the bus's bit time used at `rate_hz` cycles per second."""
        bits = self.bits_per_cycle(stuffing) * rate_hz + self.heartbeat_bits(rate_hz, stuffing)
        return bits / self.bitrate

    def max_rate_hz(self, load: float, stuffing: Stuffing = "worst") -> float:
        """The fastest cycle rate that keeps the bus at `load` (a fraction).  The host
        heartbeat's share depends on the rate (whole cycles, at most one per cycle), so
        the rate is found by bisection on the monotone `load`."""
        low, high = 0.0, load * self.bitrate / self.bits_per_cycle(stuffing)
        if self.load(high, stuffing) <= load:
            return high
        for _ in range(60):
            middle = 0.5 * (low + high)
            if middle > 0 and self.load(middle, stuffing) > load:
                high = middle
            else:
                low = middle
        return low


def bus_cycles(drives: DrivesConfig, robot: Robot, buses: Sequence[CanConfig]) -> list[BusCycle]:
    """Each bus of a CiA 402 config (`buses` as DaemonConfig.buses lists them)."""
    if drives.protocol != "cia402":
        raise ValueError(f"bus cycles are modelled for cia402 drives, not {drives.protocol}")
    driver = make_driver(drives, robot)
    parts = (
        [(part.name, part.driver) for part in driver.parts]
        if isinstance(driver, MultiBusDriver)
        else [(buses[0].bus_name, driver)]
    )
    bitrates = {bus.bus_name: bus.bitrate for bus in buses}
    out = []
    for name, part in parts:
        assert isinstance(part, Cia402Driver)
        forces = [100.0] * part.n
        part.cycle_start()  # the first cycle: the host heartbeat, the control RPDOs
        part.commands(forces)
        sync = part.cycle_start()
        answers = [
            message(layout.cob_id(node), bytes(layout.struct.size))
            for node in part.nodes
            for layout in part.plan.tpdos
            if layout.on_sync
        ]
        frames = [*sync, *part.commands(forces), *answers]
        beats = part.n / drives.heartbeat_period
        out.append(BusCycle(name, bitrates[name], frames, beats, drives, [*sync, *answers]))
    return out
