"""Run a VirtualRobot on a python-can bus in real time, as a task of an asyncio loop.

The plant advances (in whole plant steps) on its own timerfd, every `wake_period`
(default: one plant step), and to each frame's stamp before the drives take it, so a
SYNC is answered with the state at the moment it was sent, as on a real bus, also when
this process was held up before reading it (a busy host then delays the daemon's
frames, as on a robot, but does not move the drives' clock).  Buses with a file
descriptor are drained by the loop itself; others through a Notifier thread.  Frames
the drives send pass through optional frame faults and a bus-load meter.

With a `collector` (drivers.gc_policy; the simulator's own process passes one), garbage
is collected as the core collects its own: the start-up heap frozen, young generations
after the answers to a frame or a wake-up went out, the oldest never.  Without it, at
1 kHz: a full collection of 45 ms just after the runner started, while the daemon brings
its drives up, and young ones of 0.5-1 ms, 3 a second; with it, 0.13 ms.

SYNCs are answered soonest when they come half a plant step after a step boundary: the
wake-up that steps the plant (some 0.2 ms of CPU for eight drives, up to 0.6 ms) is then
over before they arrive, never in their way.  Where a daemon's SYNCs come is set by when
it started, so once REPHASE_AFTER SYNCs in a row came within a quarter step of a
boundary, and while no cable moves (so no drive can tell), the simulator's clock is held
back by less than a step to put them there (again if they drift off later).

On several buses (given by name, one meter each): frames read from a bus are tagged with
its name (`channel`) before the drives see them, and each frame sent goes on the bus its
`channel` names (sim_bus.virtual_robot tags every drive's frames with its bus).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import can

from drivers.bus import BusWatch, FrameIO, by_channel, frame_io, gone
from drivers.clock import PeriodicTimer
from drivers.gc_policy import CollectorPolicy
from sim_bus.bus.busload import BusLoadMeter
from sim_bus.virtual_robot import VirtualRobot

log = logging.getLogger(__name__)

SYNC_PHASE = 0.5  # of a plant step after a step boundary: where SYNCs are best answered
PHASE_TOLERANCE = 0.25  # of a step either side of it: close enough
REPHASE_AFTER = 5  # SYNCs in a row outside it before the clock is held back
REST_RATE = 1e-4  # m/s: no drive's cable moves faster, so a held-back clock goes unseen
HELD_UP = 0.01  # s: a wake-up this late: the simulator was held up (see _note_lateness)


@dataclass
class Lane:
    """One bus the simulator is on: its name (None: the only bus given as a bus), frame
    I/O, reader and bus-load meter."""

    name: str | None
    bus: can.BusABC
    io: FrameIO
    meter: BusLoadMeter | None
    watch: BusWatch | None = None


class SimulatorRunner:
    """`start()` on a running loop, `close()` to stop; `t` is simulated time (s).  `bus`
    is one python-can bus, or several by name (`meter` then one per bus, by name)."""

    def __init__(
        self,
        robot: VirtualRobot,
        bus: can.BusABC | Mapping[str, can.BusABC],
        meter: BusLoadMeter | Mapping[str, BusLoadMeter] | None = None,
        wake_period: float | None = None,
        collector: CollectorPolicy | None = None,
        own_process: bool = False,
        answer_deadline: float = 0.0,
    ) -> None:
        self.robot = robot
        self.collector = collector
        # the process and its loop to itself (python -m sim_bus): a late wake-up is then
        # the host's doing, and logged; in process, the daemon's own work on the loop
        # (start-up, a late cycle) delays it, which the daemon reports itself
        self.own_process = own_process
        self.wake_period = wake_period or robot.plant.config.step
        buses = bus if isinstance(bus, Mapping) else {None: bus}
        meters = meter if isinstance(meter, Mapping) else {None: meter}
        self.lanes = {
            name: Lane(name, b, frame_io(b), meters.get(name)) for name, b in buses.items()
        }
        self._only = next(iter(self.lanes.values())) if len(self.lanes) == 1 else None
        self._schedule: list[tuple[float, Callable[[], list[can.Message]]]] = []
        self._t0 = 0.0
        self._timer: PeriodicTimer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._off_phase = 0  # SYNCs in a row that came outside SYNC_PHASE's tolerance
        self.send_errors = 0
        self.receive_errors = 0
        self._latest = 0.0  # s: the latest wake-up since take_latest_wake_up()
        # s after a SYNC went out that the host waits for its feedback (0: not counted):
        # SYNCs answered later count in `late_answers` (take_answers)
        self.answer_deadline = answer_deadline
        self._slowest_answer = 0.0  # s: since take_answers()
        self._late_answers = 0

    @property
    def t(self) -> float:
        return time.monotonic() - self._t0

    def monotonic(self, t: float) -> float:
        """Simulated time `t` on this host's monotonic clock."""
        return self._t0 + t

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._loop = loop
        if self.collector is not None:
            gc.collect()  # now, before any drive waits for an answer (or the clock runs)
            self.collector.start()
        self._t0 = time.monotonic() - self.robot.t
        self._timer = PeriodicTimer(self.wake_period)
        loop.add_reader(self._timer.fileno(), self._on_tick)
        for lane in self.lanes.values():
            lane.watch = BusWatch(
                lane.io,
                loop,
                lambda lane=lane: self._drain_lane(lane),
                lambda frames, lane=lane: self._handle(frames, lane),
            )

    def close(self) -> None:
        if self.collector is not None:
            self.collector.close()
        loop = self._loop
        if loop is not None and self._timer is not None:
            loop.remove_reader(self._timer.fileno())
            self._timer.close()
            self._timer = None
        for lane in self.lanes.values():
            if lane.watch is not None:
                lane.watch.close()
                lane.watch = None

    def _on_tick(self) -> None:
        timer = self._timer
        if timer is None:
            return
        expired = timer.expirations()
        if not expired:
            return
        self._note_lateness(timer, expired)
        t = self.t
        # frames sent before now acted when they were sent: first, at their times
        self._drain()
        self._send(self.robot.advance_to(t))
        while self._schedule and self._schedule[0][0] <= t:
            self._send(self._schedule.pop(0)[1]())
        if self.collector is not None:
            self.collector.after_cycle()

    def _note_lateness(self, timer: PeriodicTimer, expired: int) -> None:
        """How late this wake-up came (from the first of the `expired` steps it serves):
        HELD_UP or more in a process of its own is a host that did not run it (or its
        vCPU), and meanwhile no drive answered: the daemon sees missed feedback that real
        drives, on processors of their own, would not have caused.  Logged there."""
        now = time.monotonic()
        late = timer.lateness(now, expired)
        self._latest = max(self._latest, late)
        if late >= HELD_UP and self.own_process:
            log.warning(
                "simulator: woken %.1f ms late (held up: its drives answered late)", late * 1e3
            )

    def take_latest_wake_up(self) -> float:
        """The latest (s) a wake-up came since the last call (the truth log's)."""
        latest, self._latest = self._latest, 0.0
        return latest

    def take_answers(self) -> tuple[float, int]:
        """Since the last call (the truth log's): the longest a SYNC waited here for the
        drives' answers to leave (s, from its stamp: when the host sent it, or when this
        host's bus took it in), and how many SYNCs were answered after
        `answer_deadline`, too late for the host's cycle: deadline misses this process
        caused, which real drives, on processors of their own, would not have."""
        taken = self._slowest_answer, self._late_answers
        self._slowest_answer, self._late_answers = 0.0, 0
        return taken

    def _note_answers(self, stamps: list[float]) -> None:
        """The answers to the SYNCs stamped `stamps` (wall clock) have just left."""
        answered = time.time()
        for stamp in stamps:
            waited = answered - stamp
            self._slowest_answer = max(self._slowest_answer, waited)
            if 0.0 < self.answer_deadline < waited:
                self._late_answers += 1

    def _drain(self) -> None:
        """Take what every bus has queued to the drives."""
        for lane in self.lanes.values():
            self._drain_lane(lane)

    def _drain_lane(self, lane: Lane) -> None:
        try:
            frames = lane.io.drain()
        except (can.CanError, OSError) as exc:
            self.receive_errors += 1
            if gone(exc) and lane.watch is not None:  # the plant runs on, deaf
                log.warning("simulator: the bus is gone (%s); no longer reading it", exc)
                lane.watch.close()
                lane.watch = None
            return
        self._handle(frames, lane)

    def at(self, t: float, action: Callable[[], list[can.Message] | None]) -> None:
        """Run `action` (e.g. a device fault) once simulated time reaches `t`; frames it
        returns go on the bus."""
        self._schedule.append((t, lambda: action() or []))
        self._schedule.sort(key=lambda item: item[0])

    def _handle(self, frames: list[can.Message], lane: Lane) -> None:
        """Frames from a bus: to the drives, and their answers onto the bus."""
        if lane.meter is not None:
            lane.meter.add_many(frames)
        if self._only is None:  # several buses: the drives hear the frames of theirs
            for msg in frames:
                msg.channel = lane.name
        out, now = [], self.t
        # a frame's stamp (wall clock, as SocketCAN's) on the simulated clock
        offset = time.time() - time.monotonic() + self._t0
        syncs = []
        for msg in frames:
            # what a drive latches on a SYNC is the state when the SYNC was on the bus,
            # also when this process was held up before reading it; a stamp from the
            # future (a stepped clock) or none at all: now
            at = min(msg.timestamp - offset if msg.timestamp else now, now)
            out.extend(self.robot.handle(msg, at))
            if self.robot.is_sync(msg):
                self._watch_phase(at)
                if msg.timestamp:
                    syncs.append(msg.timestamp)
        self._send(out)
        if syncs:
            self._note_answers(syncs)
        if self.collector is not None:
            self.collector.after_cycle()

    def _watch_phase(self, at: float) -> None:
        """A SYNC came at simulated time `at`: after REPHASE_AFTER in a row outside
        SYNC_PHASE, while every cable is at rest, hold the clock back (less than a step)
        so that they come at SYNC_PHASE, and wake on the new steps' boundaries."""
        step = self.robot.plant.config.step
        phase = (at % step) / step
        if abs(phase - SYNC_PHASE) <= PHASE_TOLERANCE:
            self._off_phase = 0
            return
        self._off_phase += 1
        if self._off_phase < REPHASE_AFTER or self._timer is None:
            return
        if any(abs(drive.rate) > REST_RATE for drive in self.robot.drives):
            return
        self._off_phase = 0
        held = ((phase - SYNC_PHASE) % 1.0) * step
        log.debug("simulator: clock held back %.3f ms, SYNCs now half a step in", held * 1e3)
        self._t0 += held
        self._timer.restart(self._t0 + (math.floor(self.t / step) + 1) * step)

    def _send(self, frames: list[can.Message]) -> None:
        """Each frame onto its bus, the only one or the one its `channel` names: a bus's
        frames in one write where it batches (FrameIO.batches), as the drives' answers to
        one SYNC, a failed write counting once in `send_errors`; elsewhere frame by frame,
        each failure counted."""
        if not frames:
            return
        if self._only is not None:
            self._send_on(self._only, frames)
            return
        for name, sent in by_channel(frames).items():
            self._send_on(self.lanes[name], sent)

    def _send_on(self, lane: Lane, frames: list[can.Message]) -> None:
        io = lane.io
        if io.batches:
            try:
                io.send_all(frames)
            except (can.CanError, OSError):
                self.send_errors += 1
                return
            sent = frames
        else:
            sent = []
            for frame in frames:
                try:
                    io.send(frame)
                except (can.CanError, OSError):
                    self.send_errors += 1
                else:
                    sent.append(frame)
        if lane.meter is not None:
            lane.meter.add_many(sent)
