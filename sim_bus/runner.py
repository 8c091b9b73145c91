"""Run a VirtualRobot on a python-can bus in real time, as a task of an asyncio loop.

The plant advances (in whole plant steps) on its own timerfd, every `wake_period`
(default: one plant step), and whenever a frame arrives, so a SYNC is answered with the
state at the moment it was seen.  Buses with a file descriptor are drained by the loop
itself; others through a Notifier thread.  Frames the drives send pass through optional
frame faults and a bus-load meter.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import can

from drivers.bus import BusWatch, frame_io, gone
from drivers.clock import PeriodicTimer
from sim_bus.bus.busload import BusLoadMeter
from sim_bus.virtual_robot import VirtualRobot

log = logging.getLogger(__name__)


class SimulatorRunner:
    """`start()` on a running loop, `close()` to stop; `t` is simulated time (s)."""

    def __init__(
        self,
        robot: VirtualRobot,
        bus: can.BusABC,
        meter: BusLoadMeter | None = None,
        wake_period: float | None = None,
    ) -> None:
        self.robot = robot
        self.wake_period = wake_period or robot.plant.config.step
        self.bus = bus
        self._io = frame_io(bus)
        self.meter = meter  # bus-load accounting of every frame seen and sent
        self._schedule: list[tuple[float, Callable[[], list[can.Message]]]] = []
        self._t0 = 0.0
        self._timer: PeriodicTimer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._watch: BusWatch | None = None
        self.send_errors = 0
        self.receive_errors = 0
        self._delays = hasattr(bus, "tick")

    @property
    def t(self) -> float:
        return time.monotonic() - self._t0

    def start(self) -> None:
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._t0 = time.monotonic() - self.robot.t
        self._timer = PeriodicTimer(self.wake_period)
        loop.add_reader(self._timer.fileno(), self._on_tick)
        self._watch = BusWatch(self._io, loop, self._drain, self._handle)

    def close(self) -> None:
        loop = self._loop
        if loop is not None and self._timer is not None:
            loop.remove_reader(self._timer.fileno())
            self._timer.close()
            self._timer = None
        if self._watch is not None:
            self._watch.close()
            self._watch = None

    def _on_tick(self) -> None:
        if self._timer is None or not self._timer.expirations():
            return
        t = self.t
        self._send(self.robot.advance_to(t))
        while self._schedule and self._schedule[0][0] <= t:
            self._send(self._schedule.pop(0)[1]())
        if self._delays:  # a FaultyBus releases delayed frames when drained
            self._drain()

    def _drain(self) -> None:
        try:
            frames = self._io.drain()
        except (can.CanError, OSError) as exc:
            self.receive_errors += 1
            if gone(exc) and self._watch is not None:  # the plant runs on, deaf
                log.warning("simulator: the bus is gone (%s); no longer reading it", exc)
                self._watch.close()
                self._watch = None
            return
        self._handle(frames)

    def at(self, t: float, action: Callable[[], list[can.Message] | None]) -> None:
        """Run `action` (e.g. a device fault) once simulated time reaches `t`; frames it
        returns go on the bus."""
        self._schedule.append((t, lambda: action() or []))
        self._schedule.sort(key=lambda item: item[0])

    def _handle(self, frames: list[can.Message]) -> None:
        """Frames from the bus: to the drives, and their answers onto the bus."""
        if self.meter is not None:
            self.meter.add_many(frames)
        out, t = [], self.t
        for msg in frames:
            out.extend(self.robot.handle(msg, t))
        self._send(out)

    def _send(self, frames: list[can.Message]) -> None:
        for frame in frames:
            try:
                self._io.send(frame)
            except (can.CanError, OSError):
                self.send_errors += 1
            else:
                if self.meter is not None:
                    self.meter.add(frame)
