"""The simulators behind `cdprd run --sim` and `cdprd demo`.

With `analyze`, the only place the daemon imports sim_bus (DESIGN §2).  In process
(`InProcessSimulator`, tests and benches that reach into the plant): the simulator runs
as a task in the daemon's own event loop on a private in-process loop bus (one per bus
of the config), so the service under test is byte for byte the one that drives
hardware.  In a process of its own (`ProcessSimulator`, `run --sim` and the demo):
`python -m sim_bus` on socket pairs, at real-time priority where permitted, so that the
simulated drives, like real ones on their own processors, neither take the control
cycle's CPU nor wait for it.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import itertools
import json
import logging
import os
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import can

from cdpr import ConfigError
from daemon.config import DaemonConfig
from daemon.process.app import ServiceHook, serve
from daemon.service.bus_port import Buses
from sim_bus.bus.frame_faults import FaultyBus
from sim_bus.bus.loopbus import LoopBus
from sim_bus.bus.pairbus import PairBus, bus_pair
from sim_bus.config import SimConfig, parse_sim, true_base
from sim_bus.runner import SimulatorRunner
from sim_bus.virtual_robot import VirtualRobot

log = logging.getLogger("cdprd")
_channels = itertools.count()
SIMULATOR_PRIORITY = 40  # SCHED_FIFO, below the core's default realtime.priority (50)
READY_TIMEOUT = 30.0  # s for the simulator process to announce its drives (imports)
STOP_TIMEOUT = 5.0  # s for it to end after SIGTERM before it is killed
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
ERROR_LINES = 20  # of its standard error kept, the last of which a failure names


def realtime_child(priority: int) -> Callable[[], None]:
    """preexec_fn: SCHED_FIFO at `priority` where permitted (root, or CAP_SYS_NICE), so
    that a simulated drive, like a real one on its own processor, answers whatever else
    loads the host; ordinary scheduling where refused."""

    def apply() -> None:
        with contextlib.suppress(PermissionError, OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))

    return apply


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


def _simulator_child() -> None:
    """preexec_fn of ProcessSimulator's child: real-time priority (realtime_child), and
    SIGTERM when the daemon's process ends however it ends (PR_SET_PDEATHSIG), so that
    a killed demo leaves no simulator behind.  Its one BLAS thread it inherits: importing
    `daemon` set OPENBLAS_NUM_THREADS in this environment (daemon/__init__.py)."""
    realtime_child(SIMULATOR_PRIORITY)()
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


class ProcessSimulator:
    """`python -m sim_bus` for the config at `path` in a process of its own, one socket
    pair (sim_bus.bus.pairbus) per bus: `daemon_bus` is the daemon's side.  With
    `truth`, its truth log (the true platform every 20 ms, stamped on the monotonic
    clock) comes through a pipe into `truth` (one dict a line), never through a file: a
    write to this host's disk stalled it for tens of milliseconds.  `serve` as
    InProcessSimulator's."""

    def __init__(self, config: DaemonConfig, path: Path, truth: bool = True) -> None:
        # a ConfigError before any process starts, as InProcessSimulator's
        simulated_robot(config, sim_section(config))
        self.config, self._path, self._truth = config, path, truth
        ours: dict[str, can.BusABC] = {}
        self._theirs = []
        for bus in config.buses:
            mine, theirs = bus_pair()
            ours[bus.bus_name] = PairBus(mine, bus.channel)
            self._theirs.append(theirs)
        self.daemon_bus: Buses = ours if len(ours) > 1 else next(iter(ours.values()))
        self.truth: list[dict] = []
        self._errors: collections.deque[str] = collections.deque(maxlen=ERROR_LINES)
        self._simulating = asyncio.Event()
        self._readers: list[asyncio.Task] = []
        self.process: asyncio.subprocess.Process | None = None

    async def start(self) -> None:
        """Start the simulator and wait until it simulates (RuntimeError naming its last
        error line if it ends before)."""
        fds = [end.fileno() for end in self._theirs]
        argv = ["-m", "sim_bus", "--config", str(self._path)]
        if self._truth:
            deadline = self.config.safety.feedback_deadline / self.config.controller.rate_hz
            argv += ["--truth-log", "-", "--answer-deadline", repr(deadline)]
        for fd in fds:
            argv += ["--bus-fd", str(fd)]
        self.process = process = await asyncio.create_subprocess_exec(
            sys.executable,
            *argv,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            pass_fds=fds,
            preexec_fn=_simulator_child,
        )
        for end in self._theirs:
            end.close()  # the child's now: its end of the stream is the bus's end
        assert process.stdout is not None and process.stderr is not None
        self._readers = [
            asyncio.create_task(self._read_output(process.stdout)),
            asyncio.create_task(self._read_errors(process.stderr)),
        ]
        simulating = asyncio.create_task(self._simulating.wait())
        ended = asyncio.create_task(process.wait())
        await asyncio.wait(
            {simulating, ended}, timeout=READY_TIMEOUT, return_when="FIRST_COMPLETED"
        )
        simulating.cancel()
        ended.cancel()
        if not self._simulating.is_set():
            await self.stop()
            last = self._errors[-1] if self._errors else "no error output"
            raise RuntimeError(f"the simulator process did not start: {last}")

    async def _read_output(self, stream: asyncio.StreamReader) -> None:
        """Its standard output: truth records (JSON lines), the announcement that it
        simulates, and bus-load reports (read so that the pipe never fills)."""
        while line := await stream.readline():
            if line.startswith(b"{"):
                with contextlib.suppress(ValueError):  # a line cut short by the stop
                    self.truth.append(json.loads(line))
            elif line.startswith(b"simulating "):
                self._simulating.set()

    async def _read_errors(self, stream: asyncio.StreamReader) -> None:
        """Its log (standard error): into the daemon's at info, the last lines kept."""
        while line := await stream.readline():
            text = line.decode(errors="replace").rstrip()
            self._errors.append(text)
            log.info("simulator: %s", text)

    async def stop(self) -> None:
        """SIGTERM, then killed if it has not ended within STOP_TIMEOUT; its output read
        to the end."""
        process = self.process
        if process is not None and process.returncode is None:
            process.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(process.wait(), STOP_TIMEOUT)
            except TimeoutError:
                process.kill()
                await process.wait()
        await asyncio.gather(*self._readers)

    async def serve(self, *, companion: bool = True, after_start: ServiceHook | None = None) -> int:
        """daemon.process.app.serve() on the simulator process's buses (`companion`:
        as serve's); the exit code."""
        await self.start()
        try:
            return await serve(
                self.config, self.daemon_bus, companion=companion, after_start=after_start
            )
        finally:
            await self.stop()
            buses = self.daemon_bus
            for bus in [buses] if isinstance(buses, can.BusABC) else buses.values():
                bus.shutdown()


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
