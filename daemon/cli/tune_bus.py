"""`cdprd tune` on a python-can bus in real time: ONE drive through the daemon's own bus
port (daemon.service.bus_port), timerfd (drivers.clock) and protocol driver.

The cycle is the daemon's (daemon.service.service): the timer opens it (SYNC where the
protocol has one), it runs the moment the drive's fresh feedback is in, or at the
feedback deadline with what came, and sends the experiment's command
(tuning.experiment: its limits and aborts are the same as in simulated time); garbage
is collected after the commands, as the daemon does (drivers.gc_policy).  After
start-up and until enabled, and once braked, every cycle sends the driver's keep-alives
so that the drive's watchdog stays fed.  The run ends braked: at the experiment's end,
on its abort, or when the bus is lost (then nothing can be sent, and the drive's own
watchdog holds it).

Feedback is stamped with the frame's own time where the bus gives one (SocketCAN's
kernel receive time, socketcand's server time; daemon.process.recording.frame_stamp),
not when the loop read it: frames read in a batch after the host was held up would
otherwise all seem to be of the same instant, and the fit would see a delay that is
not the winch's.  The frames' median age when read is the bus's one-way delay
(Record.transit): the fit takes the commands to reach the drive that much after they
were sent.
"""

from __future__ import annotations

import asyncio
import gc
import math
import statistics
import time
from collections.abc import Callable

import can

from daemon.process.recording import frame_stamp
from daemon.service.bus_port import BusPort
from drivers.base import ActuatorDriver, BrakeMode, DriverError, Timing
from drivers.bus import stamp_age
from drivers.clock import PeriodicTimer
from drivers.gc_policy import CollectorPolicy
from tuning.experiment import Abort, WinchExperiment

STARTUP_TIMEOUT = 5.0  # s for the drive to come up (the daemon's)
FIRST_FEEDBACK = 1.0  # s to wait for a length before enabling
BRAKE_HOLD = 0.1  # s of keep-alives after the brake frames, before the run returns


class BusExperiment:
    """`experiment` on drive 0 of `driver` (one drive's protocol driver) on `bus`;
    `await run()` returns the experiment's Abort, or None when it ran to the end.
    `deadline` is the fraction of the period the cycle waits for feedback."""

    def __init__(
        self,
        bus: can.BusABC,
        driver: ActuatorDriver,
        experiment: WinchExperiment,
        brake_mode: BrakeMode,
        deadline: float = 0.5,
        say: Callable[[str], None] | None = None,
    ) -> None:
        self.driver, self.experiment, self.brake_mode = driver, experiment, brake_mode
        self.period = experiment.plan.period
        self.deadline = deadline * self.period
        self.port = BusPort(bus, self._on_frames, driver.receive_ids())
        self.port.on_lost = self._on_lost
        self.port.on_sent = self._count_sent
        self.say = say or (lambda line: None)
        self.frames = 0  # sent and received
        self.ages: list[float] = []  # s: each feedback frame's age when read
        self.mode = "idle"  # idle (keep-alives), busy (enabling), run, braked
        self._timer: PeriodicTimer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiting = False
        self._opened = 0.0
        self._count = 0
        self._deadline_handle: asyncio.TimerHandle | None = None
        self._finished: asyncio.Future[None] | None = None
        self._braked_at = math.inf
        self.collector = CollectorPolicy()

    async def run(self) -> Abort | None:
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._finished = loop.create_future()
        gc.collect()  # now, not while the drive's watchdog waits for a cycle
        self.port.open(loop)
        try:
            return await self._run(loop)
        finally:
            self._close()
            self.collector.close()

    async def _run(self, loop: asyncio.AbstractEventLoop) -> Abort | None:
        driver, experiment = self.driver, self.experiment
        try:
            await asyncio.wait_for(driver.start(self.port, time.monotonic), STARTUP_TIMEOUT)
        except (TimeoutError, DriverError) as exc:
            return Abort("startup", f"the drive did not start: {exc or 'timeout'}")
        self.collector.start()
        self._timer = PeriodicTimer(self.period)
        loop.add_reader(self._timer.fileno(), self._on_tick)
        count = driver.feedback[0].count
        for _ in range(round(FIRST_FEEDBACK / self.period)):
            if driver.feedback[0].count > count or self.port.lost is not None:
                break
            await asyncio.sleep(self.period)
        length = driver.feedback[0].length
        if self.port.lost is not None or not math.isfinite(length):
            self._stop(Abort("no_feedback", f"no length from the drive in {FIRST_FEEDBACK} s"))
        else:
            self.mode = "busy"
            try:
                await driver.enable(self.port, [length], [experiment.load.hold])
            except DriverError as exc:
                self._stop(Abort("drive_fault", f"enable failed: {exc}"))
            else:
                if self.mode == "busy":
                    self.say("enabled: holding the load, then the excitation")
                    self.mode = "run"
        await self._finished
        if self.ages:
            experiment.record.transit = statistics.median(self.ages)
        return experiment.abort

    # -- the cycle ------------------------------------------------------------------

    def _on_tick(self) -> None:
        timer = self._timer
        if timer is None or timer.expirations() == 0:
            return
        if self._waiting:
            self._close_waiting_cycle()
        if self.driver.timing is Timing.SYNC:
            self._count = self.driver.feedback[0].count
        self._waiting = True
        self._opened = time.monotonic()
        self._send(self.driver.cycle_start())
        if self.driver.feedback[0].count > self._count:
            self._run_cycle()
            return
        assert self._loop is not None
        self._deadline_handle = self._loop.call_later(self.deadline, self._close_waiting_cycle)

    def _close_waiting_cycle(self) -> None:
        self._deadline_handle = None
        self.port.poll()  # frames that came in time may still be queued
        if self._waiting:
            self._run_cycle()

    def _on_frames(self, frames: list[can.Message], now: float) -> None:
        self.frames += len(frames)
        wall = time.time()
        for msg in frames:
            if not msg.is_error_frame:
                age = stamp_age(frame_stamp(msg, True), wall)
                if self.driver.receive(msg, now - age) is not None:
                    self.ages.append(age)
        if self._waiting and self.driver.feedback[0].count > self._count:
            self._run_cycle()

    def _run_cycle(self) -> None:
        self._waiting = False
        if self._deadline_handle is not None:
            self._deadline_handle.cancel()
            self._deadline_handle = None
        self._count = self.driver.feedback[0].count
        if self.mode == "run":
            forces = self.experiment.forces(time.monotonic(), self.driver, self._opened)
            if forces is None:
                self._brake()
            else:
                self._send(self.driver.commands(forces))
        elif self.mode in ("idle", "braked"):
            self._send(self.driver.keepalive())
            if time.monotonic() >= self._braked_at + BRAKE_HOLD:
                self._finish()
        self.collector.after_cycle()

    # -- ending -----------------------------------------------------------------------

    def _stop(self, abort: Abort) -> None:
        """End the experiment with `abort` (unless it ended already) and brake."""
        if self.experiment.abort is None:
            self.experiment.abort = abort
        self._brake()

    def _brake(self) -> None:
        if self.mode == "braked":
            return
        self.mode = "braked"
        length = self.driver.feedback[0].length
        self._send(
            self.driver.brake([length if math.isfinite(length) else math.nan], self.brake_mode)
        )
        self._braked_at = time.monotonic()
        if self.port.lost is not None:
            self._finish()

    def _on_lost(self, what: str) -> None:
        self._stop(Abort("bus_lost", what))

    def _finish(self) -> None:
        if self._finished is not None and not self._finished.done():
            self._finished.set_result(None)

    def _send(self, frames: list[can.Message]) -> None:
        for frame in frames:
            self.port.send(frame)

    def _count_sent(self, message: can.Message) -> None:
        self.frames += 1

    def _close(self) -> None:
        if self._timer is not None and self._loop is not None:
            self._loop.remove_reader(self._timer.fileno())
            self._timer.close()
            self._timer = None
        if self._deadline_handle is not None:
            self._deadline_handle.cancel()
        self.port.close()
