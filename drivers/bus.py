"""Bus helpers shared by the daemon and the simulator.

`frame_io(bus)` is how both move frames on the hot path.  On SocketCAN it talks to the
python-can bus's raw socket directly, non-blocking: python-can's `send` and `recv`
each add a select() (and `send` a clock read) to every frame, which doubles the
system calls per cycle; inside user-mode Linux, where every call traps, that was
40 us per frame against 10 us raw (measured with tests/vcan/uml.py).

A flood must not hold the event loop: reading frames one at a time stops after a
`limit` (the rest stays queued in the bus), BusWatch hands frames over from a Notifier
thread in batches, and frames on ids the host does not read are dropped as early as
the bus allows: by the kernel on SocketCAN (`receive_only`), else by an `IdFilter`
before any other work.
"""

from __future__ import annotations

import asyncio
import errno
import threading
from collections import deque
from collections.abc import Callable, Iterable

import can
from can.interfaces.socketcan import SocketcanBus
from can.interfaces.socketcan.socketcan import build_can_frame, capture_message

FRAMES_PER_PASS = 128  # frames a reader takes per loop pass, so a flood cannot hold the loop
THREAD_QUEUE_FRAMES = 4096  # frames a Notifier thread may queue for the loop (oldest dropped)


class IdFilter:
    """The frames a host reads: error frames, and standard (11-bit) frames on `ids`.
    `wanted` keeps those and counts the others in `ignored`: one set lookup a frame."""

    def __init__(self, ids: Iterable[int]) -> None:
        self.ids = frozenset(ids)
        self.ignored = 0

    def wanted(self, frames: list[can.Message]) -> list[can.Message]:
        ids = self.ids
        kept = [
            m
            for m in frames
            if m.is_error_frame or (m.arbitration_id in ids and not m.is_extended_id)
        ]
        self.ignored += len(frames) - len(kept)
        return kept


class FrameIO:
    """`send(frame)` and `drain()` on one python-can bus (this base: python-can's own
    send with timeout 0 and recv(0) until empty).  Both raise can.CanError on a bus
    failure; `send` never blocks, a full transmit queue is an error."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def send(self, frame: can.Message) -> None:
        self.bus.send(frame, timeout=0.0)

    def drain(self, limit: int | None = None) -> list[can.Message]:
        """The frames queued now, oldest first, without blocking: at most `limit` where
        frames are read one at a time (this base, SocketcanIO); a bus that hands over
        its whole queue in one call (DrainingIO) returns all of it."""
        frames: list[can.Message] = []
        while len(frames) != limit and (msg := self.bus.recv(0.0)) is not None:
            frames.append(msg)
        return frames

    def receive_only(self, ids: frozenset[int]) -> None:
        """Have the bus itself drop standard frames on other ids, and every extended
        frame, where it can do so below Python (error frames still come).  Here: no
        such filter, the caller filters (IdFilter)."""


class DrainingIO(FrameIO):
    """A bus with its own `drain()` (the loop bus, the fault-injecting bus): its whole
    queue in one call, bounded by the bus (the loop bus's receive queue)."""

    def drain(self, limit: int | None = None) -> list[can.Message]:
        return self.bus.drain()  # type: ignore[attr-defined]


class SocketcanIO(FrameIO):
    """The SocketCAN bus's raw socket, non-blocking: one system call per frame."""

    def __init__(self, bus: SocketcanBus) -> None:
        super().__init__(bus)
        self._socket = bus.socket
        self._socket.setblocking(False)
        self._channel = bus.channel

    def send(self, frame: can.Message) -> None:
        try:
            self._socket.send(build_can_frame(frame))
        except OSError as exc:
            raise can.CanOperationError(f"Failed to transmit: {exc.strerror}", exc.errno) from exc

    def receive_only(self, ids: frozenset[int]) -> None:
        """The kernel's CAN_RAW_FILTER (python-can's filters on a socketcan bus): frames
        on other ids never wake the daemon.  Error frames have their own filter."""
        self.bus.set_filters(
            [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(ids)]
        )

    def drain(self, limit: int | None = None) -> list[can.Message]:
        frames: list[can.Message] = []
        sock, channel = self._socket, self._channel
        while len(frames) != limit:
            try:
                msg = capture_message(sock)
            except can.CanOperationError as exc:
                if exc.error_code in (errno.EAGAIN, errno.EWOULDBLOCK):
                    return frames
                raise
            if msg is None:
                return frames
            msg.channel = channel
            frames.append(msg)
        return frames


def frame_io(bus: can.BusABC) -> FrameIO:
    """The cheapest FrameIO `bus` offers."""
    if isinstance(bus, SocketcanBus):
        return SocketcanIO(bus)
    if callable(getattr(bus, "drain", None)):
        return DrainingIO(bus)
    return FrameIO(bus)


class BusWatch:
    """Runs `on_readable()` on `loop` whenever `bus` has frames queued: through
    loop.add_reader where the bus has a file descriptor (socketcan, the loop bus), else
    through a python-can Notifier thread.  The thread passes frames through `accept`
    (if given) and queues them (at most THREAD_QUEUE_FRAMES: the oldest are dropped and
    counted in `dropped`); the loop takes them in batches of at most FRAMES_PER_PASS,
    one batch per pass, into `deliver(frames)`."""

    def __init__(
        self,
        bus: can.BusABC,
        loop: asyncio.AbstractEventLoop,
        on_readable: Callable[[], None],
        deliver: Callable[[list[can.Message]], None],
        accept: IdFilter | None = None,
    ) -> None:
        self._loop = loop
        self._fd = -1
        self._notifier: can.Notifier | None = None
        self._deliver = deliver
        self._queue: deque[can.Message] = deque()
        self._lock = threading.Lock()
        self._scheduled = False
        self.dropped = 0
        try:
            fd = bus.fileno()
        except NotImplementedError:
            fd = -1
        if isinstance(fd, int) and fd >= 0:
            self._fd = fd
            loop.add_reader(fd, on_readable)
        else:

            def from_thread(msg: can.Message) -> None:
                if accept is not None and not accept.wanted([msg]):
                    return
                with self._lock:
                    if len(self._queue) >= THREAD_QUEUE_FRAMES:
                        self._queue.popleft()
                        self.dropped += 1
                    self._queue.append(msg)
                    if self._scheduled:
                        return
                    self._scheduled = True
                if not loop.is_closed():
                    loop.call_soon_threadsafe(self._hand_over)

            self._notifier = can.Notifier(bus, [from_thread], timeout=0.1)

    def _hand_over(self) -> None:
        """(On the loop) one batch of the frames the thread queued; the rest next pass."""
        with self._lock:
            queue = self._queue
            frames = [queue.popleft() for _ in range(min(FRAMES_PER_PASS, len(queue)))]
            self._scheduled = bool(queue)
        if self._scheduled:
            self._loop.call_soon(self._hand_over)
        if frames:
            self._deliver(frames)

    @property
    def polled(self) -> bool:
        """True when the loop reads the bus itself (a file descriptor), so a caller on
        the loop may also drain it; False when a Notifier thread owns the reading."""
        return self._fd >= 0

    def close(self) -> None:
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            self._fd = -1
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
