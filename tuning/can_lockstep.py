"""The host's driver and the simulator's drives exchanging CAN frames in simulated time.

Every frame the driver sends is the drive's to answer (VirtualRobot.handle), every frame
a drive sends reaches the driver's `receive`: the same codecs, state machines and
watchdogs as on a bus, without a bus or a wall clock, so an experiment of a minute takes
a few seconds and is deterministic.  `LockstepLink` is a drivers.base.Link (start-up and
enable sequences wait in simulated time); `run_cycles` runs a cycle function at a fixed
period the way the daemon's cycle does (SYNC where the protocol has it, then the newest
feedback, then the commands).
"""

from __future__ import annotations

import asyncio
import math
from collections import deque
from collections.abc import Callable

import can

from drivers.base import ActuatorDriver, BrakeMode, DriverError
from sim_bus.virtual_robot import VirtualRobot
from tuning.experiment import Abort, WinchExperiment

CycleFunction = Callable[[float], "list[float] | None"]  # t -> forces, None: stop


class LockstepLink:
    """Frames between `driver` and `robot` in simulated time `t` (s)."""

    def __init__(self, robot: VirtualRobot, driver: ActuatorDriver) -> None:
        self.robot, self.driver = robot, driver
        self.t = robot.t
        self.step = robot.plant.config.step
        self._inbox: deque[can.Message] = deque()
        self._due: list[tuple[float, Callable[[], list[can.Message]]]] = []
        self.frames_sent = 0
        self.frames_received = 0

    def now(self) -> float:
        return self.t

    def send(self, message: can.Message) -> None:
        self.frames_sent += 1
        self._inbox.extend(self.robot.handle(message, self.t))

    def deliver(self) -> None:
        """Hand every frame the drives sent so far to the driver."""
        while self._inbox:
            self._receive(self._inbox.popleft())

    def advance(self, t: float) -> None:
        """Simulated time runs to `t` (rounded to whole plant steps) a plant step at a
        time, each frame delivered (and stamped) at the step that sent it."""
        self.deliver()
        while self.t < t - 0.5 * self.step:
            self._step()
            self.deliver()

    def schedule(self, t: float, action: Callable[[], list[can.Message]]) -> None:
        """Run `action` (a device fault: VirtualRobot.drive_fault, ...) once simulated
        time reaches `t`; the frames it returns go on the bus."""
        self._due.append((t, action))
        self._due.sort(key=lambda item: item[0])

    def _step(self) -> None:
        """One plant step; what the drives send waits in the inbox."""
        self.t = (round(self.t / self.step) + 1) * self.step
        self._inbox.extend(self.robot.advance_to(self.t))
        while self._due and self._due[0][0] <= self.t:
            self._inbox.extend(self._due.pop(0)[1]())

    def _receive(self, message: can.Message) -> None:
        self.frames_received += 1
        self.driver.receive(message, self.t)

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        end = self.t + timeout
        while True:
            while self._inbox:
                message = self._inbox.popleft()
                self._receive(message)
                if match(message):
                    return message
            if self.t >= end - 1e-12:
                raise DriverError(f"no answer within {timeout * 1e3:.0f} ms: {what}")
            self._step()


def bring_up(link: LockstepLink, forces: list[float], period: float) -> None:
    """The driver's start sequence, one cycle for the lengths, then its enable sequence
    over `link` (DriverError if a drive does not come up); from then on the drives
    follow force commands, starting at `forces`."""
    driver = link.driver
    link.advance(link.t + 0.1)  # the drives are powered and talking before the host starts
    asyncio.run(driver.start(link, link.now))
    run_cycles(link, period, lambda t: None, period)
    link.advance(link.t + period)
    lengths = [fb.length for fb in driver.feedback]
    asyncio.run(driver.enable(link, lengths, forces))


def run_cycles(link: LockstepLink, period: float, cycle: CycleFunction, limit: float) -> None:
    """Call `cycle(t)` every `period` s of simulated time after opening the cycle (SYNC)
    and delivering the feedback, send its forces, until it returns None or `limit` s
    passed."""
    driver = link.driver
    start = link.t
    for k in range(1, round(limit / period) + 1):
        t = start + k * period
        link.advance(t)
        t = link.t
        for frame in driver.cycle_start():
            link.send(frame)
        link.deliver()
        forces = cycle(t)
        if forces is None:
            return
        for frame in driver.commands(forces):
            link.send(frame)


def brake(link: LockstepLink, lengths: list[float], mode: BrakeMode, hold: float = 0.05) -> None:
    """The driver's brake frames, then `hold` s of simulated time with keep-alives."""
    for frame in link.driver.brake(lengths, mode):
        link.send(frame)
    t = link.t
    while link.t < t + hold - 1e-12:
        link.advance(link.t + link.step)
        for frame in link.driver.keepalive():
            link.send(frame)
    link.deliver()


def run_experiment(
    link: LockstepLink, experiment: WinchExperiment, brake_mode: BrakeMode
) -> Abort | None:
    """Bring the drive up holding the load, run `experiment` to its end (or its abort:
    then brake at the last length and return the Abort), and brake."""
    driver = link.driver
    plan = experiment.plan
    bring_up(link, [experiment.load.hold], plan.period)
    run_cycles(
        link, plan.period, lambda t: experiment.forces(t, driver), plan.settle + plan.duration + 1.0
    )
    last = driver.feedback[0].length
    brake(link, [last if math.isfinite(last) else math.nan], brake_mode)
    return experiment.abort
