"""The in-process simulator behind `cdprd run --sim` and `cdprd demo`.

With `analyze`, the only place the daemon imports sim_bus (DESIGN §2): the simulator
runs as a task in the daemon's own event loop on a private in-process loop bus (one per
bus of the config), so the service under test is byte for byte the one that drives
hardware.
"""

from __future__ import annotations

import itertools
import os

import can

from cdpr import ConfigError
from daemon.config import DaemonConfig
from daemon.process.app import ServiceHook, serve
from daemon.service.bus_port import Buses
from sim_bus.bus.frame_faults import FaultyBus
from sim_bus.bus.loopbus import LoopBus
from sim_bus.config import SimConfig, parse_sim, true_base
from sim_bus.runner import SimulatorRunner
from sim_bus.virtual_robot import VirtualRobot

_channels = itertools.count()


class InProcessSimulator:
    """Simulator + the daemon's bus to it (`daemon_bus`: one bus, or one per bus name of
    a config with several).  `start()` inside the running loop (before the service
    starts), `close()` after the service stopped."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        sim = sim_section(config)
        self.robot = simulated_robot(config, sim)  # a ConfigError before any bus is open
        run = f"cdprd-sim-{os.getpid()}-{next(_channels)}"
        device: dict[str, can.BusABC] = {}
        daemon: dict[str, can.BusABC] = {}
        for bus in config.buses:
            channel = run if len(config.buses) == 1 else f"{run}-{bus.bus_name}"
            device[bus.bus_name] = LoopBus(channel=channel, bitrate=bus.bitrate)
            if sim.frame_faults.named_rules():
                device[bus.bus_name] = FaultyBus(device[bus.bus_name], sim.frame_faults)
            daemon[bus.bus_name] = LoopBus(channel=channel, bitrate=bus.bitrate)
        self._buses = [*device.values(), *daemon.values()]
        several = len(config.buses) > 1
        self.daemon_bus: Buses = daemon if several else daemon.popitem()[1]
        self.runner = SimulatorRunner(self.robot, device, wake_period=sim.wake(config.drives))

    def start(self) -> None:
        self.runner.start()

    def close(self) -> None:
        self.runner.close()
        for bus in self._buses:
            bus.shutdown()

    async def serve(self, *, companion: bool = True, after_start: ServiceHook | None = None) -> int:
        """daemon.process.app.serve() on this simulator's bus, the simulator running
        meanwhile (`cdprd run --sim`, the demo, benchmarks and tests); the exit code."""
        self.start()
        try:
            return await serve(
                self.config, self.daemon_bus, companion=companion, after_start=after_start
            )
        finally:
            self.close()


def sim_section(config: DaemonConfig) -> SimConfig:
    """The config's `sim:` section validated, its wake-up period checked against the
    drives; ConfigError names the file and the key."""
    sim = parse_sim(config.sim, config.source)
    try:
        sim.wake(config.drives)
    except ConfigError as exc:
        raise exc.within(config.source) from None
    return sim


def simulated_robot(config: DaemonConfig, sim: SimConfig) -> VirtualRobot:
    """The simulated robot of `sim` (from sim_section); ConfigError, naming the file, when
    it cannot be built: e.g. a plant mismatch whose true robot has no static equilibrium
    at its home pose."""
    where = f"{config.source}: sim.plant"
    robot = true_base(sim, config.robot, config.base, config.source)
    try:
        return VirtualRobot(robot, config.drives, sim.plant, sim.rig)
    except ConfigError as exc:
        raise exc.within(where) from None
    except ValueError as exc:  # no static equilibrium (sim_bus.plant.statics)
        raise ConfigError(f"{where}: {exc}") from None
