"""The in-process simulator behind `cdprd run --sim` and `cdprd demo`.

With `analyze`, the only place the daemon imports sim_bus (DESIGN §2): the simulator
runs as a task in the daemon's own event loop on a private in-process loop bus, so the
service under test is byte for byte the one that drives hardware.
"""

from __future__ import annotations

import itertools
import os

import can

from daemon.config import DaemonConfig
from sim_bus.config import parse_sim
from sim_bus.frame_faults import FaultyBus
from sim_bus.loopbus import LoopBus
from sim_bus.runner import SimulatorRunner
from sim_bus.virtual_robot import VirtualRobot

_channels = itertools.count()


class InProcessSimulator:
    """Simulator + the daemon's bus to it.  `start()` inside the running loop (before
    the service starts), `close()` after the service stopped."""

    def __init__(self, config: DaemonConfig) -> None:
        sim = parse_sim(config.sim, "sim")
        channel = f"cdprd-sim-{os.getpid()}-{next(_channels)}"
        bitrate = config.can.bitrate
        device_bus: can.BusABC = LoopBus(channel=channel, bitrate=bitrate)
        if sim.frame_faults.named_rules():
            device_bus = FaultyBus(device_bus, sim.frame_faults)
        self.daemon_bus = LoopBus(channel=channel, bitrate=bitrate)
        self.robot = VirtualRobot(config.robot, config.drives, sim.plant)
        self.runner = SimulatorRunner(self.robot, device_bus, wake_period=sim.wake(config.drives))
        self._device_bus = device_bus

    def start(self) -> None:
        self.runner.start()

    def close(self) -> None:
        self.runner.close()
        self._device_bus.shutdown()
        self.daemon_bus.shutdown()
