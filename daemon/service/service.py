"""The cdprd service: the control cycle on the CAN bus, the safety state machine, and
the commands that talk to the drives (DESIGN §8, §9, §16).

What the real-time core runs.  One asyncio loop does everything time-critical: a
timerfd opens each cycle (SYNC for SYNC-driven drives), received frames are drained
into the driver as they arrive, and the cycle runs the moment every actuator's feedback
is in (or at the deadline): the controller step, the safety checks, then all command
frames.  Trajectories come planned and validated (daemon.service.planner): the service
only checks that the reference they were planned from still stands, and follows them.
A procedure that needs the cycle itself (pretension: daemon.service.pretension_run) is
driven through daemon.service.procedure.CycleProcedure alone; home and the rest checks
live in daemon.service.rest, the estimates' commands in daemon.service.estimates.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import os
import time
from collections.abc import Awaitable, Callable, Generator, Iterator
from typing import Any, TypeVar

import can
import numpy as np

from cdpr import Pose
from cdpr.controller import ControlOutput, ParallelController, static_tensions
from cdpr.pretension import Pretension
from cdpr.trajectory import Reference
from cdpr.trajectory.core import Curve
from daemon.config import DaemonConfig
from daemon.config.feedback_tolerance import NoiseWatch
from daemon.service.api import CommandError
from daemon.service.bus_port import Buses, open_port
from daemon.service.calibration_state import (
    StateFileError,
    load_state,
    robot_identity,
    state_path,
)
from daemon.service.command_lead import LatencyMedian
from daemon.service.cycle_stats import CycleStats
from daemon.service.estimates import (
    observer_command,
    observer_state,
    payload_command,
    payload_state,
)
from daemon.service.flight_stats import FlightStats
from daemon.service.hold_report import HoldReport, hold_summary
from daemon.service.homing import LengthOffsets
from daemon.service.planner import PLANNING_LEAD
from daemon.service.pretension_run import pretension
from daemon.service.procedure import CycleProcedure
from daemon.service.rest import home, position_text, rest_refusal
from daemon.service.safety import (
    Fault,
    SafetyMonitor,
    SafetyState,
    StateMachine,
    Trigger,
    missed_text,
)
from daemon.service.trusted_lengths import (
    RETRUST_CYCLES,
    Implausible,
    TrustedLengths,
    cable_accel_bound,
)
from drivers.base import ActuatorDriver, DriverError, Feedback, FrameError, Timing
from drivers.bus import CAN_ERR_BUSOFF
from drivers.clock import DeadlineTimer, PeriodicTimer
from drivers.factory import make_driver
from drivers.gc_policy import CollectorPolicy

log = logging.getLogger("cdprd")

# s for the drives to come up: a backstop only (each request has its own timeout, which
# finds a silent drive); eight CiA 402 drives configured from an EDS take a few hundred
# SDO exchanges, 5 s in a slow virtual machine, well under a second on a real bus
STARTUP_TIMEOUT = 30.0
SLACK_MARGIN = 3e-4  # s before a tick at which background work stops (> its longest step)
EXIT_BUS_LOST = os.EX_UNAVAILABLE  # 69, sysexits' "service unavailable": the bus is gone
EventSink = Callable[[dict[str, Any]], None]
Result = TypeVar("Result")


class Service:
    """One robot on its bus (or buses, by name).  `run()` until `stop()`; implements
    daemon.service.api.DaemonHandler."""

    def __init__(self, config: DaemonConfig, bus: Buses) -> None:
        self.config = config
        self.robot = robot = config.robot
        self.n = robot.n_cables
        self.driver: ActuatorDriver = make_driver(config.drives, robot)
        self.controller = ParallelController(robot, config.controller, config.drives.force_lag)
        self.period = self.controller.period
        # the measured sample-to-command latency the controller's lead allows for ("auto")
        self._latency = (
            LatencyMedian(self.period) if config.controller.command_lead == "auto" else None
        )
        self.stats = CycleStats(config.controller.rate_hz)
        self.machine = StateMachine()
        self.monitor = SafetyMonitor(config)
        self.port = open_port(bus, self._on_frames, self.driver)
        self.port.on_error = self._on_bus_error
        self.port.on_lost = self._on_bus_lost
        self.port.on_sent = self._on_sent
        self._events: list[EventSink] = []
        # observers off the safety path: (controller time, output) of every control
        # step (once its commands are out, or before the brake that replaces them), and
        # (frame, received?) for every frame in or out
        self.cycle_listeners: list[Callable[[float, ControlOutput], None]] = []
        self.frame_listeners: list[Callable[[can.Message, bool], None]] = []
        self.t0 = time.monotonic()
        self._timer: PeriodicTimer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped: asyncio.Event | None = None
        self._exit_code = 0
        self._exit_timer: asyncio.TimerHandle | None = None  # the exit after a lost bus
        self._busy = False  # a sequence is talking to the drives (drives_busy)
        # cycle bookkeeping
        self._waiting = False
        self._opened = 0.0
        self._counts = [0] * self.n
        self._deadline: DeadlineTimer | None = None  # ends the wait for feedback
        # background work waiting for the cycle's slack or its turn (slack)
        self._slack_waiters: list[tuple[asyncio.Future[bool], float]] = []
        self._source_version = 0  # changes whenever the controller's reference source does
        self._last_rx = 0.0
        # the lengths a brake or keepalive holds: the last plausible measurements
        # (rate, step, consistency); a sample may be taken up to a period late and the
        # host be held up for ~10 ms (PERF-FACTS), which the step bound allows for
        self.trust = TrustedLengths(
            robot,
            config.drives.nodes,
            max_speed=config.safety.max_cable_speed,
            tolerance=config.feedback_tolerance.total,
            slack=2.0 * self.period + 0.01,
            rest_tensions=static_tensions(robot, self.controller.tension, robot.home),
            max_accel=cable_accel_bound(
                config.trajectory, robot.geometry.attachments, min(config.reference_lengths.lower)
            ),
            stretch=self.controller.stretch,
            shortest=min(config.reference_lengths.lower),
        )
        # the length offsets in force (homing, calibration) and whether each still holds
        self.offsets = LengthOffsets(
            [s.length_offset for s in config.drives.scalings_for(robot)],
            config.drives.nodes,
            silent_cycles=math.ceil(config.drives.heartbeat_timeout / self.period),
            tolerance=config.feedback_tolerance.total,
        )
        self.identity = robot_identity(robot, config.drives)  # what stored offsets must match
        self.noise = NoiseWatch(config.feedback_tolerance, config.drives.nodes)
        self._load_offsets()
        self._trajectory: Curve | None = None
        self._scheduled: list[Curve] = []  # accepted, beginning later, by start time
        self._flight = FlightStats()  # the current trajectory's, for trajectory_done
        self.last_output = None
        self.last_output_t = math.nan  # the cycle time last_output was computed for
        self.faults: list[Fault] = []  # conditions active at the last check
        # the procedure the cycle drives (daemon.service.procedure), the last one started,
        # and the last pretension (cdpr.pretension; published while it runs and after)
        self.procedure: CycleProcedure | None = None
        self.pretension: Pretension | None = None
        self.brakes = 0  # brake() calls: a sequence that waited sees whether one came
        self.hold_report = HoldReport()  # whether the drives confirm the brake
        self.collector = CollectorPolicy()
        self._extrapolation_limit = 2.0 / config.drives.feedback_rate_hz
        self._silence_limit = config.safety.stale_cycles * self.period

    # -- lifecycle --------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """start() has opened the bus and the cycle runs (until close())."""
        return self._timer is not None

    def now(self) -> float:
        """Controller time: seconds since the service started (monotonic)."""
        return time.monotonic() - self.t0

    def subscribe(self, sink: EventSink) -> None:
        """Receive every event (state changes, faults, trajectory decisions)."""
        self._events.append(sink)

    async def start(self) -> None:
        """Open the bus, bring the drives up (held), start the cycle; IDLE on success,
        BRAKED (STARTUP) if the drives do not come up."""
        gc.collect()  # now, not while the drives' watchdogs wait for the first cycle
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._stopped = asyncio.Event()
        self.port.open(loop)
        self._timer = PeriodicTimer(self.period)
        loop.add_reader(self._timer.fileno(), self._on_tick)
        self._deadline = DeadlineTimer()
        loop.add_reader(self._deadline.fileno(), self._on_deadline)
        try:
            await asyncio.wait_for(self.driver.start(self.port, time.monotonic), STARTUP_TIMEOUT)
        except (TimeoutError, DriverError) as exc:
            why = str(exc) or f"not done within {STARTUP_TIMEOUT:g} s"
            self.brake(Fault(Trigger.STARTUP, f"drives did not start: {why}"))
            return
        self.machine.go("started")
        self.emit({"event": "state", "state": "idle", "why": "drives started"})
        self.collector.start()

    async def wait_stopped(self) -> int:
        assert self._stopped is not None
        await self._stopped.wait()
        return self._exit_code

    def stop(self, trigger: Trigger = Trigger.SIGTERM, exit_code: int = 0) -> None:
        """Brake (if anything moves), then end `wait_stopped` with `exit_code` (a
        non-zero code given before stays: a later stop does not make a failure clean)."""
        if self.machine.powered or self.machine.state is SafetyState.INIT:
            self.brake(Fault(trigger, "stop requested: braking before exit"))
        else:
            self.send_brake()
        self._exit_code = self._exit_code or exit_code
        if self._stopped is not None:
            self._stopped.set()

    def close(self) -> None:
        if self._timer is not None and self._loop is not None:
            self._loop.remove_reader(self._timer.fileno())
            self._timer.close()
            self._timer = None
        if self._deadline is not None and self._loop is not None:
            self._loop.remove_reader(self._deadline.fileno())
            self._deadline.close()
            self._deadline = None
        if self._exit_timer is not None:
            self._exit_timer.cancel()
        self._wake_slack_waiters()
        self.port.close()
        self.collector.close()

    # -- the cycle ---------------------------------------------------------------------

    def _on_tick(self) -> None:
        timer = self._timer
        if timer is None:
            return
        expired = timer.expirations()
        if expired == 0:
            return
        now = time.monotonic()
        self.stats.overruns += expired - 1
        self.stats.jitter.add(now - timer.last_expiry(now))
        # answers to the last SYNC still queued are its answers, late, and must be taken
        # before the next SYNC goes out: after it, they would be taken as its answers (a
        # period old, their rates over the wrong interval)
        self.port.poll()
        if self._waiting:  # the previous cycle never completed: close it now
            self._close_waiting_cycle()
        if self.driver.timing is Timing.SYNC:
            self._counts = [fb.count for fb in self.driver.feedback]
        self._waiting = True
        # the cycle's instant is when its SYNC goes out, the drives latching then: the
        # work above (a late cycle closed, a stall) may have held the tick up since `now`
        self._opened = opened = time.monotonic()
        self.send(self.driver.cycle_start())
        self.trust.catch_up()  # the consistency check at the last cycle's pose
        if self._all_fresh():
            self._run_cycle(opened, deadline=False)
            return
        assert self._deadline is not None
        # the wait ends on the ticks' grid, before the next tick: counted from the SYNC, a
        # tick that first closed a late cycle pushed the deadline past the next tick, which
        # then closed it again, and so on: no slack was left (a silent drive's commands,
        # the SDO hold checks after a foreign NMT command went unserved)
        self._deadline.arm(now + self.config.safety.feedback_deadline * self.period)
        if self.machine.moving and not self._busy:
            self._prepare(opened)

    def _prepare(self, now: float) -> None:
        """The controller's measurement-free work for the cycle opened at `now`, done
        while the feedback is on its way: off the path from the last feedback frame to
        the commands."""
        started = time.monotonic()
        try:
            self.controller.prepare(now - self.t0)
        except Exception:  # the step repeats the work and brakes on the error
            return
        self.stats.prepare.add(time.monotonic() - started)

    def _on_deadline(self) -> None:
        deadline = self._deadline
        if deadline is not None and deadline.expired() and self._waiting:
            self._close_waiting_cycle()

    def _close_waiting_cycle(self) -> None:
        """The wait for this cycle's feedback is over: run it with what has arrived.
        Frames already queued count (they came in time while the loop was held up, and
        the timer that ends the wait may run before the loop reads them); only feedback
        still missing after that is a miss."""
        self.port.poll()  # completes the cycle if the missing frames are queued
        if self._waiting:
            if self.machine.state is not SafetyState.INIT:  # drives still starting: none due
                self.stats.deadline_misses += 1
            self._run_cycle(time.monotonic(), deadline=True)

    def _all_fresh(self) -> bool:
        counts = self._counts
        return all(fb.count > c for fb, c in zip(self.driver.feedback, counts, strict=True))

    def _on_sent(self, frame: can.Message) -> None:
        for listener in self.frame_listeners:
            listener(frame, False)

    def _on_frames(self, frames: list[can.Message], now: float) -> None:
        for listener in self.frame_listeners:
            for msg in frames:
                listener(msg, True)
        receive, arrival = self.driver.receive, self.port.arrival
        for msg in frames:
            if msg.is_error_frame:
                error_class = msg.arbitration_id
                bus_off = bool(error_class & CAN_ERR_BUSOFF)
                self._on_bus_error(f"error frame 0x{error_class:x}", bus_off)
                continue
            if receive(msg, arrival(msg, now)) is not None:
                self._last_rx = now
        if self._waiting and self._all_fresh():
            self._run_cycle(now, deadline=False)

    def _run_cycle(self, now: float, deadline: bool) -> None:
        """One cycle on the feedback in (or, at the `deadline`, what has arrived): the
        checks that may brake, then the commands; then the bookkeeping that no brake
        decision of this cycle waits for (`_after_commands`)."""
        started = time.monotonic()
        self._waiting = False
        feedback = self.driver.feedback
        fresh, lengths, rates = self._take_feedback(feedback)
        self.stats.cycles += 1
        instant = self._opened
        lengths = self.offsets.read(lengths)
        for drive, why in self.offsets.watch(self.driver.status, feedback, fresh):
            node = self.offsets.nodes[drive]
            log.error("drive %d (node %d): length offset lost: %s", drive, node, why)
            self.emit({"event": "offset_lost", "drive": drive, "why": why})
        procedure = self.procedure
        winding = procedure is not None and procedure.winding
        judge = self.trust.track if winding else self.trust.check
        implausible = self._second_answers(feedback, judge(lengths, rates, fresh, instant))
        faults = [Fault(Trigger.IMPLAUSIBLE_FEEDBACK, f.message()) for f in implausible]
        powered = self.machine.moving
        faults += self.monitor.check_drives(feedback, self.driver.status, now, powered)
        stale = self.monitor.check_freshness(fresh)
        if stale is not None and self.machine.state is not SafetyState.INIT:
            faults.append(stale)
        bus = self.monitor.check_bus(now)
        if bus is not None:
            faults.append(bus)
        self.faults = faults
        state = self.machine.state
        output = None
        if faults and state in _WATCHED:
            self.brake(faults[0])
        elif self.machine.moving and not self._busy:
            output = self._control(lengths, rates)
        elif state is SafetyState.PRETENSION and procedure is not None:
            procedure.cycle(instant - self.t0, lengths, rates)
        elif state is not SafetyState.INIT:
            self.send(self.driver.keepalive())
            if state is SafetyState.BRAKED:
                self._report_hold()
        sent = time.monotonic()  # the cycle's frames are out
        if not deadline and self._last_rx:
            # streamed feedback may be complete before the tick: then from the tick
            self.stats.latency.add(sent - max(self._last_rx, self._opened))
        self._after_commands(output, sent)
        self.stats.compute.add(time.monotonic() - started)
        self.collector.after_cycle()  # the commands are out: now
        if self._slack_waiters:
            self._wake_slack_waiters()

    def _take_feedback(
        self, feedback: list[Feedback]
    ) -> tuple[list[bool], list[float], list[float]]:
        """Per drive: whether its feedback is fresh (new since the cycle opened), its
        length carried to the cycle's instant, and its rate; the counts are kept to judge
        the next cycle's freshness.

        Each length describes the cable at the cycle's instant, so that together they
        describe one pose (DESIGN §8): a sample taken earlier is carried forward at its
        rate.  Streamed feedback (Timing.CYCLIC) is sampled at each drive's own time, at
        most two intervals back (older samples are late, and their rate noise would grow
        with age).  A SYNC drive's fresh answer was latched at this cycle's SYNC; a stale
        one at the SYNC its last answer was to (Feedback.latched: an answer that came after
        its cycle's deadline is a period old, however long ago the drive was last fresh),
        carried at most the cycles a drive may stay silent: left a period old while the
        platform moves, it would put FK a period's motion off (a millimetre at 0.1 m/s and
        100 Hz) and fail its own-rate check."""
        counts = [fb.count for fb in feedback]
        fresh = [c > seen for c, seen in zip(counts, self._counts, strict=True)]
        self._counts = counts
        rates = [fb.rate for fb in feedback]
        instant = self._opened
        if self.driver.timing is Timing.CYCLIC:
            reach = self._extrapolation_limit
            lengths = [fb.length + fb.rate * min(instant - fb.stamp, reach) for fb in feedback]
            return fresh, lengths, rates
        reach = self._silence_limit
        lengths = [
            fb.length if new else fb.length + fb.rate * min(instant - fb.latched, reach)
            for fb, new in zip(feedback, fresh, strict=True)
        ]
        return fresh, lengths, rates

    def _after_commands(self, output: ControlOutput | None, sent: float) -> None:
        """The cycle's work that waits until its frames are out, since no brake decision
        of this cycle depends on it: after commands (`output`), the measured command
        latency, the consistency check's pose and the trajectory schedule (for the next
        cycles).  The feedback deadline is left to fire: its expiry read while no cycle
        waits is ignored (_on_deadline), and the next tick's arm forgets one unread by
        then (drivers.clock.DeadlineTimer)."""
        if output is not None:
            self._follow_up(output, sent)

    def _second_answers(
        self, feedback: list[Feedback], flagged: list[Implausible]
    ) -> list[Implausible]:
        """`flagged` and each drive not in it whose two answers to one SYNC, recorded by
        the driver since the last cycle, disagree (TrustedLengths.second_answer); the
        pairs are taken (NaN again)."""
        correction = self.offsets.correction
        for k in range(self.n):
            fb = feedback[k]
            first, second = fb.first, fb.second
            if second != second:  # NaN: none
                continue
            fb.first = fb.second = math.nan
            problem = self.trust.second_answer(k, first + correction[k], second + correction[k])
            if problem is not None and all(f.cable != k for f in flagged):
                flagged = [*flagged, problem]  # a new list: `judge` may return a kept one
        return flagged

    def _control(self, lengths: list[float], rates: list[float]) -> ControlOutput | None:
        """Controller step, checks and commands for the cycle opened at `self._opened`:
        the cycle's instant, when SYNC latched the drives' positions.  `lengths` and
        `rates` passed the plausibility checks (an implausible one brakes instead).
        The output whose commands went out, None if it braked instead."""
        t = self._opened - self.t0
        procedure = self.procedure
        if procedure is not None:
            procedure.before_step(t)
        try:
            output = self.controller.step(t, lengths, rates)
        except Exception as exc:
            log.exception("controller step raised")
            self.brake(Fault(Trigger.CONTROLLER_EXCEPTION, f"{type(exc).__name__}: {exc}"))
            return None
        self.last_output, self.last_output_t = output, t
        fault = self.monitor.check_output(output)
        if fault is not None:
            self._tell_listeners(output)  # before the brake, which changes the state
            self.brake(fault)
            return None
        try:
            # plain floats: numpy scalars make the driver's per-drive arithmetic slow
            frames = self.driver.commands(output.commands.tolist())
        except FrameError as exc:
            self._tell_listeners(output)
            self.brake(Fault(Trigger.NAN, str(exc)))
            return None
        self.send(frames)
        if procedure is not None:
            procedure.after_commands(output.commands)
        return output

    def _follow_up(self, output: ControlOutput, sent: float) -> None:
        """After a cycle's commands went out at `sent`: the cycle listeners, the command
        lead's latency, the consistency check's pose, and the trajectory that starts or
        ends now."""
        self._tell_listeners(output)
        if self._latency is not None:
            latency = self._latency.add(sent - self._opened)
            if latency is not None:
                self.controller.set_latency(latency)
        self.trust.note_pose(output.pose)  # linearised there at the next tick (catch_up)
        t = self._opened - self.t0
        while self._scheduled and t >= self._scheduled[0].start_time:
            self._trajectory = self._scheduled.pop(0)
            self._flight = FlightStats()
            if self.machine.state is SafetyState.HOLD:
                self.machine.go("track")
                self.emit({"event": "state", "why": "trajectory started"})
        trajectory = self._trajectory
        if self.machine.state is SafetyState.TRACKING and trajectory is not None:
            self._flight.add(self.monitor.tracking_errors, output)
            if t >= trajectory.end_time:
                self._trajectory = None
                self.machine.go("finish")
                self.emit({"event": "trajectory_done", "t": t, **self._flight.summary()})

    def _tell_listeners(self, output: ControlOutput) -> None:
        """The cycle listeners' (time, output) of the cycle opened at `self._opened`."""
        t = self._opened - self.t0
        for listener in self.cycle_listeners:
            listener(t, output)

    # -- faults --------------------------------------------------------------------------

    def brake(self, fault: Fault, supersede: bool = False) -> None:
        """Enter BRAKED (`supersede`: see StateMachine.brake) and freeze every cable
        (driver brake frames), logging one line.  BRAKED first: a brake frame that fails
        to send reports a bus error, which must not brake all over again."""
        braked = self.machine.brake(fault, supersede)
        self.brakes += 1
        self.hold_report.forget()
        self.send_brake()
        self._trajectory = None
        self._scheduled.clear()
        if self.procedure is not None:
            self.procedure.end(fault.message)
        if braked:
            deliberate = fault.trigger in (Trigger.SIGTERM, Trigger.COMMAND)
            level = logging.WARNING if deliberate else logging.ERROR
            missed = self.monitor.missed_feedback()
            log.log(level, fault.line() + missed_text(missed))
            self.emit({"event": "brake", "trigger": fault.trigger.value, "message": fault.message,
                       "missed_feedback": missed})  # fmt: skip

    def _report_hold(self) -> None:
        """An event when the drives' answers to the brake change the verdict (whether
        every drive confirmed its hold); a drive that cannot be confirmed is logged."""
        event = self.hold_report.update(self.driver.status)
        if event is None:
            return
        if event["event"] == "brake_unconfirmed":
            log.error("brake not confirmed: %s", "; ".join(event["unconfirmed"]))
        else:
            log.info("brake confirmed by every drive")
        self.emit(event)

    def hold_lengths(self) -> list[float]:
        """The last trusted lengths (NaN for a cable never trusted: no drive was
        enabled then, and the driver keeps it so)."""
        return self.offsets.write(self.trust.held)

    def _on_bus_error(self, what: str, bus_off: bool = False) -> None:
        self.stats.bus_errors += 1
        fault = self.monitor.bus_error(time.monotonic(), what, bus_off)
        if fault is not None and self.machine.state is not SafetyState.BRAKED:
            self.brake(fault)

    def _on_bus_lost(self, what: str) -> None:
        """The bus is gone: brake what can still be reached (those frames may fail too,
        counted), report it as the fault on record, and exit with EXIT_BUS_LOST after
        safety.bus_lost_exit seconds, for the service manager to restart the daemon,
        which comes up IDLE.  The drives' watchdogs hold once the commands stop."""
        self.stats.bus_errors += 1
        delay = self.config.safety.bus_lost_exit
        self.brake(self.monitor.bus_lost(f"{what}; exiting in {delay:g} s"), supersede=True)
        assert self._loop is not None  # the port reports only once opened on the loop
        self._exit_timer = self._loop.call_later(delay, self._exit_bus_lost)

    def _exit_bus_lost(self) -> None:
        log.error(
            "exiting with code %d: %s (%d sends and receives failed)",
            EXIT_BUS_LOST,
            self.port.lost,
            self.port.failures,
        )
        self.stop(Trigger.BUS_LOST, EXIT_BUS_LOST)

    def send(self, frames: list[can.Message]) -> None:
        self.port.send_all(frames)

    def send_brake(self, lengths: list[float] | None = None) -> None:
        """The drives' brake frames (drives.brake): each holds its cable at `lengths`
        (driver lengths), by default the last trusted ones (hold_lengths)."""
        held = self.hold_lengths() if lengths is None else lengths
        self.send(self.driver.brake(held, self.config.drives.brake))

    def emit(self, event: dict[str, Any]) -> None:
        event.setdefault("t", self.now())
        event.setdefault("state", self.machine.state.value)
        for sink in self._events:
            sink(event)

    # -- commands (daemon.service.api.DaemonHandler) -------------------------------------

    def command(self, name: str, args: dict[str, Any]) -> dict[str, Any] | Awaitable[dict]:
        """Run one command; the reply body, or an awaitable of it for commands that wait
        for the drives (enable, reset).  CommandError when refused."""
        handler = _COMMANDS.get(name)
        if handler is None:
            raise CommandError("unknown_command", f"unknown command {name!r}")
        if self._busy and name != "status" and name != "brake":
            raise CommandError("invalid_state", "the drives are busy with enable or reset")
        return handler(self, args)

    async def _enable(self, args: dict[str, Any]) -> dict[str, Any]:
        self._require(SafetyState.IDLE, "enable")
        if self.faults:
            raise CommandError(
                "invalid_state", "cannot enable: " + "; ".join(f.message for f in self.faults)
            )
        unhomed = self.offsets.refusal()
        if unhomed is not None:
            raise CommandError("invalid_state", f"cannot enable: {unhomed}")
        pose = self.measured_pose()  # refused where the FK residual is too large
        holding = -static_tensions(self.robot, self.controller.tension, pose)
        with self.drives_busy():
            try:
                await self.driver.enable(self.port, self.hold_lengths(), holding.tolist())
                # the drives hold their positions until the first torque command: the
                # tensions they measure must hold the platform at the pose the offsets say
                refusal = await rest_refusal(self, pose, "enable")
            except DriverError as exc:
                self.brake(Fault(Trigger.DRIVE_FAULT, f"enable failed: {exc}"))
                raise CommandError("drive_error", f"enable failed: {exc}") from None
            except CommandError:  # never at rest
                self.send_brake()
                raise
        if self.machine.state is not SafetyState.IDLE:  # braked meanwhile
            raise CommandError("invalid_state", f"enable aborted: {self.machine.fault.line()}")
        if refusal is not None:
            self.send_brake()
            why = (
                f"the stored length offsets put the platform at {position_text(pose)}, "
                f"but {refusal}"
            )
            log.error("enable refused: %s", why)
            raise CommandError(
                "invalid_state",
                f"cannot enable: {why}: the length offsets are wrong (home again: cdprd "
                "home), or an undeclared payload or a push acts on the platform",
            )
        self.controller.reset(pose)
        self.source_changed()
        self.machine.go("enable")
        self.emit({"event": "state", "why": "enabled"})
        return self.status()

    def _disable(self, args: dict[str, Any]) -> dict[str, Any]:
        self._require_moving("disable")
        self.send_brake()
        self._trajectory = None
        self._scheduled.clear()
        if self.procedure is not None:
            self.procedure.end("disabled")
        self.machine.go("disable")
        self.emit({"event": "state", "why": "disabled"})
        return self.status()

    def _brake_command(self, args: dict[str, Any]) -> dict[str, Any]:
        self.brake(Fault(Trigger.COMMAND, str(args.get("reason") or "brake requested")))
        return self.status()

    async def _reset(self, args: dict[str, Any]) -> dict[str, Any]:
        self._require(SafetyState.BRAKED, "reset")
        if any(f.trigger is Trigger.IMPLAUSIBLE_FEEDBACK for f in self.faults):
            # judged afresh like the first lengths at start-up: trusted again if they fit
            # one pose and stayed within the step bounds (a cable still off stays a fault);
            # waited for also where none was ever trusted (a reset right after homing)
            judged = self.trust.first_judgements
            self.trust.retrust()
            waited = 0
            while self.trust.first_judgements == judged and waited < RETRUST_CYCLES:
                await asyncio.sleep(self.period)
                waited += 1
            # no complete set came (a silent drive, say): nothing was judged, and the
            # implausible feedback persists below with whatever else keeps it from coming
            self.trust.cancel_retrust()
        # drive faults latch in the drives until cleared; every other condition must be gone
        causes = [f for f in self.faults if f.trigger is not Trigger.DRIVE_FAULT]
        if causes:
            raise CommandError(
                "invalid_state",
                "cannot reset while faults persist: " + "; ".join(f.message for f in causes),
            )
        with self.drives_busy():
            try:
                await self.driver.reset_faults(self.port)
            except DriverError as exc:
                raise CommandError("drive_error", f"fault reset failed: {exc}") from None
        await asyncio.sleep(3 * self.period)  # let fresh feedback and heartbeats arrive
        try:
            self.machine.reset(self.faults)
        except Exception as exc:
            raise CommandError("invalid_state", str(exc)) from None
        self.emit({"event": "state", "why": "reset"})
        return self.status()

    def _status(self, args: dict[str, Any]) -> dict[str, Any]:
        return self.status()

    @contextlib.contextmanager
    def drives_busy(self) -> Iterator[None]:
        """While a sequence talks to the drives (enable, reset, a rest check): the
        cycle sends no controller commands, and every command but status and brake is
        refused."""
        self._busy = True
        try:
            yield
        finally:
            self._busy = False

    def source_changed(self) -> None:
        """The controller's reference source changed (enable, a new trajectory, a closed
        loop): plans made from the old one are refused (follow_planned's "moved")."""
        self._source_version += 1

    def _load_offsets(self) -> None:
        """The stored offsets (state_dir), if any, in place of drives.length_offset; an
        unreadable state file leaves every offset invalid until homed again, and is kept."""
        if self.config.state_dir is None:
            return
        path = state_path(self.config.state_dir, self.robot.name)
        try:
            state = load_state(path, self.robot.name, self.n, self.identity)
        except StateFileError as exc:
            log.error("calibration state: %s: every offset invalid until homed again", exc)
            self.offsets.invalidate_all(f"state file unreadable: {exc}")
            return
        if state is not None:
            self.offsets.adopt(state)
            log.info("length offsets from %s (%s)", path, state.method)

    async def in_slack(self, steps: Generator[Any, None, Result]) -> Result:
        """Run a step generator (validation, transition planning: a Planner on this loop)
        to its result in the cycle's slack: from the end of one cycle's work until
        SLACK_MARGIN before the next tick, so that it never delays the handling of
        feedback or the commands."""
        while True:
            await self.slack()
            timer = self._timer
            until = math.inf if timer is None else timer.next_expiry() - SLACK_MARGIN
            while True:  # at least one step per period, however short the slack
                try:
                    next(steps)
                except StopIteration as done:
                    return done.value
                if time.monotonic() >= until:
                    break

    async def slack(self, margin: float = SLACK_MARGIN) -> None:
        """Return when no cycle is open and the next tick is more than `margin` seconds
        away (at once if so; daemon.service.api.DaemonHandler), or when this caller's
        turn has come: every completed cycle lets the first waiter in line go, however
        short its slack, and the next cycle the next one.  A cycle whose feedback does
        not come waits for it until safety.feedback_deadline, and a long deadline leaves
        less slack than any margin: without turns, the companion's calls (status,
        reset) and its "alive" messages would wait as long as a drive stays silent.  A
        turn is one step of background work (a call, a state snapshot: a few hundred
        microseconds), so the next tick is late by at most that.  A turn never runs in
        an open cycle: one that finds the next cycle opened meanwhile (its tick came
        with the last feedback) stays first in line for the end of that cycle."""
        first = False
        while self._slack_left() <= margin:
            loop = self._loop
            if loop is None:
                return
            waiter = (loop.create_future(), margin)
            self._slack_waiters.insert(0 if first else len(self._slack_waiters), waiter)
            first = await waiter[0]  # True: this caller's turn
            if first and not self._waiting:
                return

    def _slack_left(self) -> float:
        """Seconds until the next tick, 0 while a cycle is open (inf when stopped)."""
        timer = self._timer
        if timer is None or self._loop is None:
            return math.inf
        return 0.0 if self._waiting else timer.next_expiry() - time.monotonic()

    def _wake_slack_waiters(self) -> None:
        """After a cycle: the first waiter of `slack` in line for its turn, and every
        other whose margin the slack now exceeds; the rest keep their places."""
        left = self._slack_left()
        waiting, turn = [], True
        for future, margin in self._slack_waiters:
            if future.done():  # its task was cancelled
                continue
            if turn or left > margin:
                future.set_result(turn)
                turn = False
            else:
                waiting.append((future, margin))
        self._slack_waiters = waiting

    def reference_at(self, t: float) -> tuple[Reference, int]:
        """The reference the controller follows at time t, and the version of its
        source (daemon.service.planner.CoreLink)."""
        return self.controller.source.sample(t), self._source_version

    def follow_planned(self, trajectory: Curve, version: int, what: str) -> dict[str, Any]:
        """Follow a validated trajectory (its curve) planned from source `version`: a hold from its
        start (TRACKING ends; whatever was scheduled is dropped), anything else as
        `_run` says.  {"replan": "moved"} if the source changed since, {"replan": "late"}
        if its start has passed; CommandError if the robot no longer moves."""
        self._require_moving(f"run a {what}")
        if version != self._source_version:
            return {"replan": "moved"}
        if self.now() > trajectory.start_time:
            return {"replan": "late"}
        if what != "hold":
            return self._run(trajectory, what)
        self._trajectory = None
        self._scheduled.clear()
        self._follow(trajectory)
        if self.machine.state is SafetyState.TRACKING:
            self.machine.go("hold")
        self.emit({"event": "state", "why": "hold"})
        return {"accepted": True, "what": what}

    def _follow(self, trajectory: Curve) -> None:
        """The controller follows `trajectory` from its start: a new source version."""
        self.controller.follow(trajectory, at=trajectory.start_time)
        self.source_changed()

    def _run(self, trajectory: Curve, what: str) -> dict[str, Any]:
        """Follow a validated trajectory (planned from the current reference) from its
        start: TRACKING from now if it begins within the planning lead, else from its
        start (the control cycle switches then; until then the robot carries on)."""
        self._follow(trajectory)
        # what was scheduled to begin after it never will (the new source takes over)
        self._scheduled = [s for s in self._scheduled if s.start_time < trajectory.start_time]
        if trajectory.start_time > self.now() + PLANNING_LEAD:
            self._scheduled.append(trajectory)
        else:
            self._trajectory = trajectory
            self._flight = FlightStats()
            if self.machine.state is SafetyState.HOLD:
                self.machine.go("track")
                self.emit({"event": "state", "why": f"{what} accepted"})
        return {
            "accepted": True,
            "what": what,
            "start": trajectory.start_time,
            "end": trajectory.end_time,
            "duration": trajectory.end_time - trajectory.start_time,
        }

    def _require(self, state: SafetyState, action: str) -> None:
        if self.machine.state is not state:
            raise CommandError(
                "invalid_state",
                f"cannot {action} while {self.machine.state.value} (needs {state.value})",
            )

    def _require_moving(self, action: str) -> None:
        if not self.machine.moving:
            raise CommandError(
                "invalid_state", f"cannot {action} while {self.machine.state.value} (enable first)"
            )

    def measured_pose(self, tensions_at: Callable[[Pose], np.ndarray] | None = None) -> Pose:
        """The platform pose from the current lengths, stretch-corrected with the static
        tensions of the pose (the platform is at rest when enabling; `tensions_at` the
        tensions at a pose where they are others): forward kinematics alternated with the
        statics and the cables' stiffness estimate (cdpr.stretch), from the home pose."""
        lengths = np.array(self.trust.held)
        if not np.all(np.isfinite(lengths)):
            raise CommandError("invalid_state", "no feedback from every drive yet")
        robot, solver = self.robot, self.controller.tension
        if tensions_at is None:
            tensions_at = lambda pose: static_tensions(robot, solver, pose)  # noqa: E731
        fk = self.controller.stretch.fit(lengths, tensions_at, robot.home)
        if not fk.converged:
            raise CommandError("invalid_state", f"forward kinematics failed: {fk.reason}")
        return fk.pose

    # -- state ---------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Safety state, fault and active conditions (the reply to most commands)."""
        fault = self.machine.fault
        return {
            "state": self.machine.state.value,
            "fault": None
            if fault is None
            else {"trigger": fault.trigger.value, "message": fault.message},
            "conditions": [f.message for f in self.faults],
            "drives": [
                {"state": s.state.value, "fault": s.fault, "held": s.held}
                for s in self.driver.status
            ],
            # braked: whether every drive's own answer shows its hold (None otherwise)
            "brake": hold_summary(self.driver.status)
            if self.machine.state is SafetyState.BRAKED
            else None,
            "offsets": {
                "values": self.offsets.offsets,
                "method": self.offsets.method,
                "time": self.offsets.time,
                "invalid": self.offsets.refusal(),
            },
            # the last pretension: phase, each cable's time to taut, motion seen
            "pretension": None if self.pretension is None else self.pretension.summary(),
        }

    def state(self) -> dict[str, Any]:
        """The published state: pose, twist, lengths, tensions, forces, safety, timing."""
        out = self.last_output
        feedback = self.driver.feedback
        state: dict[str, Any] = {
            "t": self.now(),
            **self.status(),
            "lengths": self.offsets.read([fb.length for fb in feedback]),
            "rates": [fb.rate for fb in feedback],
            "cycle": {
                **self.stats.summary(max_age=round(self.stats.rate_hz)),  # once a second
                "gc": self.collector.stats.summary(),
                "command_lead_us": round(self.controller.lead * 1e6, 1),
            },
            "frames": {
                "accepted": self.driver.counters.accepted,
                "rejected": dict(self.driver.counters.rejected),
                "ignored": self.port.ignored,  # on ids no drive uses
                "dropped": self.port.dropped,  # the loop fell behind the bus
            },
        }
        if out is not None and self.machine.moving:
            q = out.pose.quaternion.tolist()
            state.update(
                pose={
                    "position": out.pose.position.tolist(),
                    "quaternion": {"w": q[0], "x": q[1], "y": q[2], "z": q[3]},
                },
                twist=out.twist.tolist(),
                tensions=out.tensions.tolist(),
                forces=out.commands.tolist(),
                tracking_error=out.theta_d.tolist(),
                fk_residual=out.fk_residual,
                # the cycle these are of: "t" is when the state was taken, up to a
                # publication period later
                cycle_t=self.last_output_t,
            )
        # the cables' EA as identified, a multiple of the robot file's (cdpr.stretch)
        state["stiffness_scale"] = self.controller.stretch.stiffness_scale
        # the platform's mass and centre of mass as estimated (cdpr.payload)
        state["payload"] = payload_state(self.controller)
        # the external wrench the model does not explain (cdpr.wrench_observer)
        observer = observer_state(self.controller)
        state["external_wrench"] = None if observer is None else observer["estimate"]
        # whether that observer is held out of the loop (ParallelController.hold_observer)
        state["observer_held"] = None if observer is None else observer["held"]
        return state


# the states in which a fault condition brakes
_WATCHED = (SafetyState.IDLE, SafetyState.HOLD, SafetyState.TRACKING, SafetyState.PRETENSION)
_COMMANDS: dict[str, Callable[[Service, dict[str, Any]], Any]] = {
    "enable": Service._enable,
    "disable": Service._disable,
    "brake": Service._brake_command,
    "reset": Service._reset,
    "status": Service._status,
    "payload": lambda core, args: payload_command(core.controller, args),
    "home": home,
    "pretension": pretension,
    "observer": lambda core, args: observer_command(core.controller, args),
}
