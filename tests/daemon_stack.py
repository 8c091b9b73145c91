"""An in-process daemon + simulator over the loop bus, for integration tests."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from daemon.cli.simulated import InProcessSimulator
from daemon.config import DaemonConfig, load_config
from daemon.process.realtime import realtime
from daemon.service.planner import LocalLink, Planner
from daemon.service.safety import SafetyState
from daemon.service.service import Service

CONFIGS = Path(__file__).resolve().parent.parent / "config"
DRIVER_CONFIGS = {
    "cia402": CONFIGS / "reference8-cia402.yaml",
    "odrive": CONFIGS / "reference8-odrive.yaml",
}
HIGHEST_NORMAL_PRIORITY = -20  # nice


@contextlib.contextmanager
def flight_priority(config: DaemonConfig) -> Iterator[None]:
    """For a test that flies the core and a simulator in one process: the config's CPUs
    and switch interval, and the highest normal priority (nice -20) where permitted, not
    SCHED_FIFO.  The core and the simulator need 0.7 of a CPU at 500 Hz on our host, and
    on a host slower by a third that is more than the kernel lets real-time work have
    (sched_rt_runtime_us, 95 %): it then stops the thread for up to 50 ms each second,
    and the drives' heartbeat consumers brake the robot (reproduced with a cgroup at
    60 %: tests/daemon/test_stack_priority.py).  Nice -20 still wins the CPU from any
    normal task on a busy host, and is never stopped that way.  Threads started inside
    inherit it (Linux: niceness is a thread's)."""
    settings = config.realtime.model_copy(update={"priority": 0, "lock_memory": False})
    with realtime(settings):
        niceness = os.getpriority(os.PRIO_PROCESS, 0)  # this thread's
        with contextlib.suppress(PermissionError):
            os.setpriority(os.PRIO_PROCESS, 0, HIGHEST_NORMAL_PRIORITY)
        try:
            yield
        finally:
            os.setpriority(os.PRIO_PROCESS, 0, niceness)


class Stack:
    """Service + planner + simulator in the running loop; `plant` is the simulated truth.

    While it runs, the test's thread has `flight_priority`."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self._priority = flight_priority(config)
        self.sim = InProcessSimulator(config)
        self.service = Service(config, self.sim.daemon_bus)
        self.planner = Planner(config, LocalLink(self.service))  # hold, goto, trajectories
        self.events: list[dict] = []
        self.service.subscribe(self.events.append)

    @property
    def plant(self):
        return self.sim.robot.plant

    async def __aenter__(self) -> Stack:
        self._priority.__enter__()
        self.sim.start()
        await self.service.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.service.close()
        self.sim.close()
        self._priority.__exit__(None, None, None)

    async def enable(self) -> None:
        await self.service.command("enable", {})
        assert self.service.machine.state is SafetyState.HOLD

    async def until(self, condition: Callable[[], bool], timeout: float) -> float:
        """Wait until `condition()` holds; the seconds it took (AssertionError on timeout)."""
        start = time.monotonic()
        while not condition():
            if time.monotonic() - start > timeout:
                raise AssertionError(f"condition not met within {timeout} s")
            await asyncio.sleep(0.002)
        return time.monotonic() - start

    async def finish(self, reply: dict, timeout: float = 10.0) -> None:
        """Wait until the trajectory of the accepted `reply` has ended and the robot holds
        again.  Not the state right after the reply: a planned start more than the
        planning lead ahead is scheduled, and the robot holds until it comes."""
        service = self.service
        assert reply["accepted"], reply

        def ended() -> bool:
            tracking = service.machine.state is SafetyState.TRACKING
            return service.now() >= reply["end"] and not tracking

        await self.until(ended, timeout)
        assert service.machine.state is SafetyState.HOLD, service.machine.fault

    async def watch(self, duration: float) -> tuple[np.ndarray, float]:
        """Sample the true platform position and the lowest cable tension for `duration`
        seconds of simulated time (a simulator slowed by a busy host shows the same
        physics): (positions, lowest tension seen)."""
        plant = self.plant
        positions, lowest = [], np.inf
        end = plant.time + duration
        give_up = time.monotonic() + 10.0 * duration + 5.0
        while plant.time < end:
            if time.monotonic() > give_up:
                raise AssertionError(f"the simulator did not run {duration} s in time")
            positions.append(plant.pose.position.copy())
            lowest = min(lowest, float(plant.tensions.min()))
            await asyncio.sleep(0.005)
        return np.array(positions), lowest


def config_for(protocol: str, **overrides: object) -> DaemonConfig:
    """An example config, with top-level sections replaced by `overrides`."""
    return load_config(DRIVER_CONFIGS[protocol], lambda data: data.update(overrides))
