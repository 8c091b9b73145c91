"""The daemon's end of the CAN bus: frames in on the event loop, frames out, and the
`Link` that drivers' start-up sequences use to wait for answers.

Buses with a file descriptor (socketcan, socketcand, the simulator's loop bus) are read
by the event loop itself, many queued frames per wake-up (PERF-FACTS: one frame per
wake-up costs a loop pass each).  Other buses go through a python-can Notifier thread
that hands frames to the loop.  Either way the sink gets at most FRAMES_PER_PASS frames
per loop pass, so that a flood cannot hold the loop: the control cycle's timer and
deadline run between batches, and a flood the loop cannot keep up with ends in stale
feedback, which brakes, rather than in a loop that no longer runs.

Given the ids the drivers read, the port drops every other frame first, before the
batches: on SocketCAN the kernel does (receive filters), elsewhere an IdFilter (a set
lookup a frame), counted in `ignored`.  So a flood on ids no drive uses costs next to
nothing, and the feedback behind it is not delayed by batches of junk.  Frames lost
because the loop fell behind a Notifier thread are counted in `dropped`.

A failed send or receive is never raised: it is logged (one line per kind of failure
and a count every few seconds: daemon.process.logsetup limits this logger) and reported to
`on_error`, or to `on_lost` when it means the bus is gone (drivers.bus.gone).  A lost
bus stays lost: the port stops reading it, and `expect` fails at once.

Drives on several buses (drivers.multibus) get a `MultiBusPort`: one BusPort per bus,
each frame sent on the bus its `channel` names, each frame received tagged with the name
of the bus it came on before the driver sees it; a failure on any bus is reported (and a
lost one ends the port) as on a single bus, naming the bus.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping

import can

from drivers.base import ActuatorDriver, DriverError
from drivers.bus import FRAMES_PER_PASS, BusWatch, IdFilter, by_channel, frame_io, gone
from drivers.multibus import MultiBusDriver

log = logging.getLogger(__name__)

FrameSink = Callable[[list[can.Message], float], None]
Buses = can.BusABC | Mapping[str, can.BusABC]  # one bus, or several by name
Waiter = tuple[Callable[[can.Message], bool], asyncio.Future]


def open_port(buses: Buses, sink: FrameSink, driver: ActuatorDriver) -> BusPort | MultiBusPort:
    """The port for `driver`'s drives: a BusPort on one bus, a MultiBusPort on several
    (a MultiBusDriver, whose bus names `buses` must map to python-can buses); only the
    ids the driver reads are read."""
    if not isinstance(driver, MultiBusDriver):
        if isinstance(buses, Mapping):
            raise ValueError(f"the drives are on one bus, got buses {', '.join(buses)}")
        return BusPort(buses, sink, driver.receive_ids())
    if not isinstance(buses, Mapping) or set(buses) != set(driver.bus_names):
        got = ", ".join(buses) if isinstance(buses, Mapping) else "one bus"
        raise ValueError(f"the drives are on buses {', '.join(driver.bus_names)}, got {got}")
    return MultiBusPort(buses, sink, {name: driver.receive_ids_on(name) for name in buses})


class BusPort:
    """Reads frames into `sink(frames, now)` and sends frames; also a drivers.base.Link.
    With `ids`, only error frames and standard frames on those ids are read."""

    def __init__(self, bus: can.BusABC, sink: FrameSink, ids: Iterable[int] | None = None) -> None:
        self.bus = bus
        self._io = frame_io(bus)
        self._sink = sink
        self._filter = None if ids is None else IdFilter(ids)
        self._pending: deque[can.Message] = deque()  # read and wanted, not yet delivered
        self._loop: asyncio.AbstractEventLoop | None = None
        self._watch: BusWatch | None = None
        self._waiters: list[Waiter] = []
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
            if self._filter is not None:
                self._io.receive_only(self._filter.ids)
            self._watch = BusWatch(
                self._io,
                loop,
                self._drain,
                self._deliver,
                lambda exc: self._failed("receive", exc),
                self._filter,
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
        socket (or, where a Notifier thread reads the bus, in its queue) when a timer
        fires."""
        if self._watch is None:
            return
        if self._watch.polled:
            self._drain()
        else:
            self._watch.hand_over()

    def arrival(self, message: can.Message, now: float) -> float:
        """When a frame delivered at `now` reached this host (FrameIO.arrival)."""
        return self._io.arrival(message, now)

    @property
    def ignored(self) -> int:
        """Frames read and dropped for their id (the kernel's drops are not counted)."""
        return 0 if self._filter is None else self._filter.ignored

    @property
    def dropped(self) -> int:
        """Frames lost because the loop fell behind the bus's Notifier thread."""
        return 0 if self._watch is None else self._watch.dropped

    def _drain(self) -> None:
        if self.lost is not None:
            return
        try:
            frames = self._io.drain(FRAMES_PER_PASS)
        except (can.CanError, OSError) as exc:
            self._failed("receive", exc)
            return
        if self._filter is not None:
            frames = self._filter.wanted(frames)
        pending = self._pending
        if not pending and len(frames) <= FRAMES_PER_PASS:
            if frames:
                self._deliver(frames)
            return
        pending.extend(frames)
        batch = [pending.popleft() for _ in range(min(FRAMES_PER_PASS, len(pending)))]
        if pending and self._loop is not None:  # the rest next pass, after the others
            self._loop.call_soon(self._drain)
        self._deliver(batch)

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

    def send_all(self, frames: list[can.Message]) -> None:
        """Send `frames` in order: in one write where the bus takes a cycle's frames at
        once (FrameIO.batches), a failure then counted and reported once and none of them
        reported sent (`on_sent`); elsewhere frame by frame as `send`, each failure its own
        (SocketCAN: a full transmit queue refuses one frame, the next may go)."""
        if not self._io.batches:
            for frame in frames:
                self.send(frame)
            return
        if not frames:
            return
        try:
            self._io.send_all(frames)
        except (can.CanError, OSError) as exc:
            self._failed("send", exc)
            return
        if self.on_sent is not None:
            for frame in frames:
                self.on_sent(frame)

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
        return await expect_on([self], self._loop, match, timeout, what)


async def expect_on(
    ports: Iterable[BusPort],
    loop: asyncio.AbstractEventLoop,
    match: Callable[[can.Message], bool],
    timeout: float,
    what: str,
) -> can.Message:
    """The next frame received on any of `ports` that matches `match`; DriverError naming
    `what` on timeout, or at once (or as it happens) when one of them is lost."""
    ports = list(ports)
    for port in ports:
        if port.lost is not None:
            raise DriverError(f"CAN bus lost: {port.lost}; expected {what}")
    future: asyncio.Future = loop.create_future()
    for port in ports:
        port._waiters.append((match, future))
    try:
        return await asyncio.wait_for(future, timeout)
    except TimeoutError:
        raise DriverError(f"no answer within {timeout * 1e3:.0f} ms: {what}") from None


class MultiBusPort:
    """BusPort's interface over several buses by name (module docstring).  `ports` are
    the buses' own BusPorts; received frames reach `sink` tagged with their bus's name."""

    def __init__(
        self,
        buses: Mapping[str, can.BusABC],
        sink: FrameSink,
        ids: Mapping[str, Iterable[int]],
    ) -> None:
        self.ports = {
            name: BusPort(bus, self._tagging(name, sink), ids[name]) for name, bus in buses.items()
        }
        for name, port in self.ports.items():
            port.on_error = lambda what, name=name: self._report(self.on_error, name, what)
            port.on_lost = lambda what, name=name: self._report(self.on_lost, name, what)
            port.on_sent = lambda msg: self.on_sent(msg) if self.on_sent is not None else None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.on_error: Callable[[str], None] | None = None
        self.on_lost: Callable[[str], None] | None = None
        self.on_sent: Callable[[can.Message], None] | None = None

    @staticmethod
    def _tagging(name: str, sink: FrameSink) -> FrameSink:
        def tagged(frames: list[can.Message], now: float) -> None:
            for msg in frames:
                msg.channel = name
            sink(frames, now)

        return tagged

    @staticmethod
    def _report(callback: Callable[[str], None] | None, name: str, what: str) -> None:
        if callback is not None:
            callback(f"bus {name}: {what}")

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        for port in self.ports.values():
            port.open(loop)

    def close(self) -> None:
        for port in self.ports.values():
            port.close()

    def poll(self) -> None:
        for port in self.ports.values():
            port.poll()

    def arrival(self, message: can.Message, now: float) -> float:
        """When a frame delivered at `now` reached this host, by its bus's port."""
        return self.ports[message.channel].arrival(message, now)  # type: ignore[index]

    def send(self, message: can.Message) -> None:
        """Send one frame on the bus its `channel` names."""
        self.ports[message.channel].send(message)  # type: ignore[index]

    def send_all(self, frames: list[can.Message]) -> None:
        """Send `frames`, each on the bus its `channel` names, in order on each bus: one
        BusPort.send_all per bus."""
        for name, sent in by_channel(frames).items():
            self.ports[name].send_all(sent)

    @property
    def lost(self) -> str | None:
        """What ended the first bus lost, naming it."""
        for name, port in self.ports.items():
            if port.lost is not None:
                return f"bus {name}: {port.lost}"
        return None

    @property
    def failures(self) -> int:
        return sum(port.failures for port in self.ports.values())

    @property
    def ignored(self) -> int:
        return sum(port.ignored for port in self.ports.values())

    @property
    def dropped(self) -> int:
        return sum(port.dropped for port in self.ports.values())

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        """The next frame received on any bus matching `match` (its `channel` names the
        bus: drivers.multibus.BusLink expects on one)."""
        assert self._loop is not None, "open() the port first"
        return await expect_on(self.ports.values(), self._loop, match, timeout, what)
