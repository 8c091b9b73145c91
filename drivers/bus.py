"""Bus helpers shared by the daemon and the simulator.

`frame_io(bus)` is how both move frames on the hot path.  On SocketCAN it talks to the
python-can bus's raw socket directly, non-blocking: python-can's `send` and `recv`
each add a select() (and `send` a clock read) to every frame, which doubles the
system calls per cycle; inside user-mode Linux, where every call traps, that was
40 us per frame against 10 us raw (measured with tests/vcan/uml.py).  On socketcand
(a CAN bus served over TCP) it reads python-can's client socket on the event loop too.

`gone(exc)` tells a failure that means the bus itself is gone (the socket or connection
closed, the interface down or removed) from a transient one (a full transmit queue, a
bus-off the controller recovers from): the daemon brakes and exits on the first kind.

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
import time
from collections import deque
from collections.abc import Callable, Iterable

import can
from can.interfaces.socketcan import SocketcanBus
from can.interfaces.socketcan.socketcan import build_can_frame, capture_message
from can.interfaces.socketcand import SocketCanDaemonBus
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from can.interfaces.virtual import VirtualBus

# errno values of a send or receive on a bus that is gone: the connection or socket is
# closed (socketcand's server went away), the interface is down (ENETDOWN) or removed
# (ENODEV, ENXIO)
GONE_ERRNOS = frozenset(
    {
        errno.EPIPE,
        errno.ECONNRESET,
        errno.ECONNABORTED,
        errno.ENOTCONN,
        errno.ESHUTDOWN,
        errno.EBADF,
        errno.ENETDOWN,
        errno.ENODEV,
        errno.ENXIO,
    }
)
CAN_ERR_BUSOFF = 0x40  # error class bit of an error frame: the controller went bus-off
SOCKETCAND_MAX_LINE = 200  # bytes of an unfinished socketcand message kept (as python-can)
FRAMES_PER_PASS = 128  # frames a reader takes per loop pass, so a flood cannot hold the loop
MAX_FRAME_AGE = 0.1  # s: the most a frame's own stamp may set its arrival back (a bad stamp)
THREAD_QUEUE_FRAMES = 4096  # frames a Notifier thread may queue for the loop (oldest dropped)


class BusGone(can.CanOperationError):
    """The bus is gone (no error code says so): e.g. the socketcand server closed the
    connection."""


def gone(exc: BaseException) -> bool:
    """True when `exc`, raised by a send or a receive, means the bus itself is gone:
    BusGone, or an OSError / can.CanError with an errno in GONE_ERRNOS, itself or as the
    cause of one (python-can wraps OSErrors)."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, BusGone):
            return True
        code = seen.errno if isinstance(seen, OSError) else getattr(seen, "error_code", None)
        if code in GONE_ERRNOS:
            return True
        seen = seen.__cause__
    return False


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


def by_channel(frames: Iterable[can.Message]) -> dict[str, list[can.Message]]:
    """`frames` grouped by the bus their `channel` names, in order within each bus: what
    goes out together on each bus (FrameIO.send_all where the bus batches)."""
    groups: dict[str, list[can.Message]] = {}
    for frame in frames:
        groups.setdefault(frame.channel, []).append(frame)  # type: ignore[arg-type]
    return groups


def stamp_age(stamp: float, wall: float) -> float:
    """How long before the wall-clock time `wall` a frame stamped `stamp` (wall clock)
    arrived: never negative (a stamp from the future), at most MAX_FRAME_AGE (a bad one)."""
    return min(max(wall - stamp, 0.0), MAX_FRAME_AGE)


class FrameIO:
    """`send(frame)` and `drain()` on one python-can bus (this base: python-can's own
    send with timeout 0 and recv(0) until empty).  Both raise can.CanError or OSError on
    a bus failure (`gone` tells which failures end the bus); `send` never blocks, a full
    transmit queue is an error."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        # python-can's virtual bus: a Notifier thread reads it (a frame may reach the loop
        # only after the next SYNC went out), and it stamps each frame when it is sent,
        # in this process (see arrival())
        self.read_late_with_stamps = isinstance(bus, VirtualBus)

    def arrival(self, message: can.Message, now: float) -> float:
        """When `message` reached this host, on the monotonic clock.  Where the loop reads
        the bus itself (SocketCAN, socketcand, the loop bus), `now`, when it was
        delivered: the daemon's cycle takes what is queued before each SYNC goes out, so
        a frame delivered after a SYNC came after it.  (Not the kernel's stamp: in a
        virtual machine the stamps and the monotonic clock disagreed by milliseconds, and
        real answers looked older than their SYNC.)  Where a Notifier thread reads it
        (python-can's virtual bus), the frame's own stamp, moved onto the monotonic
        clock by both clocks read now: never later than now, at most MAX_FRAME_AGE
        before it (stamp_age)."""
        stamp = message.timestamp
        if not self.read_late_with_stamps or not stamp:
            return now
        wall = time.time()  # first: a pause between the reads can only make it look newer
        return time.monotonic() - stamp_age(stamp, wall)

    def fileno(self) -> int:
        """A file descriptor readable while frames are queued, or -1 (none: a Notifier
        thread must read the bus)."""
        try:
            fd = self.bus.fileno()
        except NotImplementedError:
            return -1
        return fd if isinstance(fd, int) else -1

    # whether `send_all` writes a cycle's frames at once (one system call, one wake-up of
    # the reader); where not, the callers send frame by frame, each failure on its own
    batches = False

    def send(self, frame: can.Message) -> None:
        self.bus.send(frame, timeout=0.0)

    def drain(self, limit: int | None = None) -> list[can.Message]:
        """The frames queued now, oldest first, without blocking: at most `limit` where
        frames are read one at a time (this base, SocketcanIO); a bus that hands over
        its whole queue in one call (DrainingIO, SocketcandIO) returns all of it."""
        frames: list[can.Message] = []
        while len(frames) != limit and (msg := self.bus.recv(0.0)) is not None:
            frames.append(msg)
        return frames

    def receive_only(self, ids: frozenset[int]) -> None:
        """Have the bus itself drop standard frames on other ids, and every extended
        frame, where it can do so below Python (error frames still come).  Here: no
        such filter, the caller filters (IdFilter)."""


class DrainingIO(FrameIO):
    """A bus with its own `drain()` (the loop bus, the fault-injecting bus, the pair
    bus): its whole queue in one call, bounded by the bus (the loop bus's receive
    queue); and its own `send_all` where it has one (the pair bus: one system call and
    one wake-up of the reader for a cycle's frames, where a frame each woke it for each)."""

    def __init__(self, bus: can.BusABC) -> None:
        super().__init__(bus)
        self.batches = callable(getattr(bus, "send_all", None))

    def send_all(self, frames: list[can.Message]) -> None:
        """`frames` in one write (only where `batches`); a failure raises as `send` does."""
        self.bus.send_all(frames)  # type: ignore[attr-defined]

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


class SocketcandIO(FrameIO):
    """python-can's socketcand client through its TCP socket, read on the event loop.

    python-can's own client reads from a Notifier thread, one frame per call (a thread
    hop and a loop wake-up per frame: feedback came late enough to count as missing),
    logs a warning whenever a TCP read ends inside a message, and cannot tell a closed
    connection from a quiet one.  Here `drain` parses every complete message queued
    (frames and error frames; replies and malformed messages are skipped), and the end
    of the stream is BusGone.  The socket is non-blocking: a server that stopped
    reading fails a send (BusGone: a line may have gone out in part) instead of stalling
    the loop.  Relies on python-can keeping the socket in its private attribute
    (python-can 4.x; tests/sim_bus/test_socketcand.py checks it)."""

    def __init__(self, bus: SocketCanDaemonBus) -> None:
        super().__init__(bus)
        self._socket = bus._SocketCanDaemonBus__socket  # type: ignore[attr-defined]
        self._socket.setblocking(False)
        self._channel = bus.channel
        self._buffer = b""
        self._closed = False

    def fileno(self) -> int:
        return self._socket.fileno()

    batches = True

    def send(self, frame: can.Message) -> None:
        self.send_all([frame])

    def send_all(self, frames: list[can.Message]) -> None:
        """The frames' messages in one write (one system call and one TCP segment)."""
        lines = b"".join(
            convert_can_message_to_ascii_message(frame).encode("ascii") for frame in frames
        )
        try:
            self._socket.sendall(lines)
        except BlockingIOError:
            raise BusGone("the socketcand server stopped reading (send buffer full)") from None
        except OSError as exc:
            raise can.CanOperationError(exc.strerror or str(exc), exc.errno) from exc

    def drain(self, limit: int | None = None) -> list[can.Message]:
        """Every complete message read (whatever `limit`: what the socket gave up is
        parsed now, since the socket will not wake the loop for it again)."""
        if self._closed:
            raise BusGone("the socketcand server closed the connection")
        data = self._buffer
        while True:
            try:
                chunk = self._socket.recv(65536)
            except BlockingIOError:
                break
            except OSError as exc:
                raise can.CanOperationError(exc.strerror or str(exc), exc.errno) from exc
            if not chunk:
                self._closed = True  # the frames read before the end still count
                break
            data += chunk
        frames = []
        start = data.find(b"<")
        while start >= 0:
            end = data.find(b">", start)
            if end < 0:
                break
            line = data[start : end + 1]
            if line.startswith((b"< frame ", b"< error ")):
                try:
                    msg = convert_ascii_message_to_can_message(line.decode("ascii", "replace"))
                except (ValueError, IndexError):
                    msg = None  # malformed: skipped, as python-can's client does
                if msg is not None:
                    msg.channel = self._channel
                    frames.append(msg)
            start = data.find(b"<", end + 1)
        rest = b"" if start < 0 else data[start:]
        self._buffer = rest if len(rest) <= SOCKETCAND_MAX_LINE else b""
        if self._closed and not frames:
            raise BusGone("the socketcand server closed the connection")
        return frames


def frame_io(bus: can.BusABC) -> FrameIO:
    """The cheapest FrameIO `bus` offers."""
    if isinstance(bus, SocketcanBus):
        return SocketcanIO(bus)
    if isinstance(bus, SocketCanDaemonBus):
        return SocketcandIO(bus)
    if callable(getattr(bus, "drain", None)):
        return DrainingIO(bus)
    return FrameIO(bus)


class BusWatch:
    """Runs `on_readable()` on `loop` whenever the bus of `io` has frames queued:
    through loop.add_reader where it has a file descriptor (socketcan, socketcand, the
    loop bus), else through a python-can Notifier thread.  The thread passes frames
    through `accept` (if given) and queues them (at most THREAD_QUEUE_FRAMES: the oldest
    are dropped and counted in `dropped`); the loop takes them in batches of at most
    FRAMES_PER_PASS, one batch per pass, into `deliver(frames)`.  Receive errors on the
    thread go to `failed(exc)` on the loop (the thread goes on reading: close the watch
    when the bus is gone)."""

    def __init__(
        self,
        io: FrameIO,
        loop: asyncio.AbstractEventLoop,
        on_readable: Callable[[], None],
        deliver: Callable[[list[can.Message]], None],
        failed: Callable[[Exception], None] | None = None,
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
        fd = io.fileno()
        if fd >= 0:
            self._fd = fd
            loop.add_reader(fd, on_readable)
        else:
            listener = _ThreadListener(self, loop, accept, failed)
            self._notifier = can.Notifier(io.bus, [listener], timeout=0.1)

    def queue_from_thread(self, msg: can.Message) -> None:
        """(On the Notifier's thread) queue `msg`; the loop takes it with the next batch."""
        with self._lock:
            if len(self._queue) >= THREAD_QUEUE_FRAMES:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(msg)
            if self._scheduled:
                return
            self._scheduled = True
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self.hand_over)

    def hand_over(self) -> None:
        """(On the loop) one batch of the frames the thread queued; the rest next pass."""
        with self._lock:
            queue = self._queue
            frames = [queue.popleft() for _ in range(min(FRAMES_PER_PASS, len(queue)))]
            self._scheduled = bool(queue)
        if self._scheduled:
            self._loop.call_soon(self.hand_over)
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


class _ThreadListener(can.Listener):
    """A Notifier's listener: frames `accept` wants into the watch's queue, receive
    errors to `failed` on the loop when given."""

    def __init__(
        self,
        watch: BusWatch,
        loop: asyncio.AbstractEventLoop,
        accept: IdFilter | None,
        failed: Callable[[Exception], None] | None,
    ) -> None:
        self._watch = watch
        self._loop = loop
        self._accept = accept
        self._failed = failed

    def on_message_received(self, msg: can.Message) -> None:
        if self._accept is None or self._accept.wanted([msg]):
            self._watch.queue_from_thread(msg)

    def on_error(self, exc: Exception) -> None:
        if self._failed is None:
            raise NotImplementedError  # unhandled: the Notifier's thread ends with it
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._failed, exc)
