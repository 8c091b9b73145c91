"""The daemon's end of the CAN bus: frames in on the event loop, frames out, and the
`Link` that drivers' start-up sequences use to wait for answers.

Buses with a file descriptor (socketcan, socketcand, the simulator's loop bus) are read
by the event loop itself, draining every queued frame per wake-up (PERF-FACTS: one frame
per wake-up costs a loop pass each).  Other buses go through a python-can Notifier thread
that hands frames to the loop.

A failed send or receive is never raised: it is logged (one line per kind of failure
and a count every few seconds: daemon.logsetup limits this logger) and reported to
`on_error`, or to `on_lost` when it means the bus is gone (drivers.bus.gone).  A lost
bus stays lost: the port stops reading it, and `expect` fails at once.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import can

from drivers.base import DriverError
from drivers.bus import BusWatch, frame_io, gone

log = logging.getLogger(__name__)

FrameSink = Callable[[list[can.Message], float], None]


class BusPort:
    """Reads frames into `sink(frames, now)` and sends frames; also a drivers.base.Link."""

    def __init__(self, bus: can.BusABC, sink: FrameSink) -> None:
        self.bus = bus
        self._io = frame_io(bus)
        self._sink = sink
        self._loop: asyncio.AbstractEventLoop | None = None
        self._watch: BusWatch | None = None
        self._waiters: list[tuple[Callable[[can.Message], bool], asyncio.Future]] = []
        self.on_error: Callable[[str], None] | None = None  # a transient failure
        self.on_lost: Callable[[str], None] | None = None  # the bus is gone
        self.on_sent: Callable[[can.Message], None] | None = None
        self.lost: str | None = None  # what ended the bus
        self.failures = 0  # sends and receives that failed

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start delivering received frames on `loop`; frames queued before this are
        stale and dropped (a drive streaming at 500 Hz fills the socket's queue while the
        daemon starts, and handing that backlog over in one go stalled the start-up
        long enough to trip the drives' watchdogs)."""
        self._loop = loop
        try:
            stale = len(self._io.drain())
        except (can.CanError, OSError) as exc:
            self._failed("receive", exc)
        else:
            if stale:
                log.debug("dropped %d frames queued before the daemon opened the bus", stale)
        if self.lost is None:
            self._watch = BusWatch(
                self._io,
                loop,
                self._drain,
                lambda msg: self._deliver([msg]),
                lambda exc: self._failed("receive", exc),
            )

    def close(self) -> None:
        self._stop_reading()
        for _, future in self._waiters:
            if not future.done():
                future.cancel()
        self._waiters.clear()

    def _stop_reading(self) -> None:
        if self._watch is not None:
            self._watch.close()
            self._watch = None

    # -- input --------------------------------------------------------------------

    def poll(self) -> None:
        """Deliver the frames queued now, without waiting for the loop to notice them:
        after the loop was held up, frames that arrived in time may still sit in the
        socket when a timer fires.  A no-op where a Notifier thread reads the bus."""
        if self._watch is not None and self._watch.polled:
            self._drain()

    def _drain(self) -> None:
        try:
            frames = self._io.drain()
        except (can.CanError, OSError) as exc:
            self._failed("receive", exc)
            return
        if frames:
            self._deliver(frames)

    def _deliver(self, frames: list[can.Message]) -> None:
        now = time.monotonic()
        self._sink(frames, now)
        if self._waiters:
            for msg in frames:
                self._wake(msg)

    def _wake(self, msg: can.Message) -> None:
        keep = []
        for match, future in self._waiters:
            if future.done():
                continue
            if match(msg):
                future.set_result(msg)
            else:
                keep.append((match, future))
        self._waiters = keep

    # -- output -------------------------------------------------------------------

    def send(self, message: can.Message) -> None:
        """Send one frame; a failure is counted and reported, never raised."""
        try:
            self._io.send(message)
        except (can.CanError, OSError) as exc:
            self._failed("send", exc)
            return
        if self.on_sent is not None:
            self.on_sent(message)

    def _failed(self, action: str, exc: Exception) -> None:
        """A send or receive raised `exc`: log it, then report it as lost or transient."""
        self.failures += 1
        what = f"{action} failed: {exc}"
        log.warning("CAN %s", what)  # the same text again is counted, not repeated
        if not gone(exc):
            if self.on_error is not None:
                self.on_error(what)
            return
        if self.lost is not None:
            return
        self.lost = what
        self._stop_reading()
        for _, future in self._waiters:
            if not future.done():
                future.set_exception(DriverError(f"CAN bus lost: {what}"))
        self._waiters.clear()
        if self.on_lost is not None:
            self.on_lost(what)

    # -- Link ----------------------------------------------------------------------

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        """The next received frame matching `match`; DriverError naming `what` on timeout."""
        assert self._loop is not None, "open() the port first"
        if self.lost is not None:
            raise DriverError(f"CAN bus lost: {self.lost}; expected {what}")
        future: asyncio.Future = self._loop.create_future()
        self._waiters.append((match, future))
        try:
            return await asyncio.wait_for(future, timeout)
        except TimeoutError:
            raise DriverError(f"no answer within {timeout * 1e3:.0f} ms: {what}") from None
