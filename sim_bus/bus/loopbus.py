"""A pollable in-process CAN bus for python-can (interface name ``cdprd_loop``).

Like python-can's ``virtual`` bus, every LoopBus opened on the same channel name in the
same process receives the frames the others send (its own only with
``receive_own_messages=True``).  Unlike it, LoopBus is built for a single-threaded
asyncio loop at 1 kHz (PERF-FACTS, "Timing of the loop"):

- no deep copy per send: every receiver gets the SAME ``can.Message`` object.  Frames are
  immutable by convention: once sent, neither the sender nor a receiver may change it.
  ``send`` stamps ``msg.timestamp`` (``time.time()``, wall clock like SocketCAN, so code
  written against either bus sees the same time base) and ``msg.channel`` in place; a
  message object sent twice carries the second stamp in both deliveries.
- ``fileno()`` is a non-blocking eventfd that is readable exactly while frames are queued,
  so ``loop.add_reader`` wakes the loop (and ``can.Notifier(bus, ..., loop=loop)`` takes
  that path instead of a reader thread);
- ``drain()`` returns every queued frame at once, ``recv(timeout=0)`` one without blocking;
- each receiver's queue is bounded (``rx_queue_size``): when a reader is stuck the OLDEST
  frames are dropped and counted in ``dropped``, memory does not grow.

Threads: ``send`` may be called from any thread (each receive queue and its eventfd are
updated under that queue's lock, so the "readable iff queued" invariant holds).  A bus
should be read (``recv``/``drain``) by one consumer; two consumers each get a share of
the frames.  ``shutdown`` is safe while other threads send to the channel.

``state`` can be set: ``BusState.ERROR`` (bus-off) or ``BusState.PASSIVE`` (listen-only)
make ``send`` raise ``can.CanOperationError``, as a real controller in those states
would refuse to transmit; receiving is unaffected.  ``bitrate`` is recorded for bus-load
accounting (sim_bus.bus.busload); frames are delivered instantly, whatever the bitrate.

``set_link(channel, up=False)`` takes a whole channel down, as ``ip link set DEV down``
does a SocketCAN interface: every send on it fails with ENETDOWN, and every bus on it
reports ENETDOWN once, on the receive after its queued frames (the fd turns readable
for it).  A bus used after ``shutdown`` fails with EBADF, like a closed socket.
"""

from __future__ import annotations

import errno
import os
import select
import threading
import time
from collections import deque

import can

DEFAULT_RX_QUEUE_SIZE = 4096


class _Receiver:
    """One bus's receive side: bounded queue + eventfd, guarded by one lock."""

    __slots__ = ("closed", "dropped", "error", "fd", "lock", "queue")

    def __init__(self, size: int) -> None:
        self.queue: deque[can.Message] = deque(maxlen=size)
        self.lock = threading.Lock()
        self.fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self.dropped = 0
        self.closed = False
        self.error = ""  # reported by the next receive that finds the queue empty

    def put(self, msg: can.Message) -> None:
        with self.lock:
            if self.closed:
                return
            queue = self.queue
            if not queue and not self.error:
                os.eventfd_write(self.fd, 1)
            elif len(queue) == queue.maxlen:
                self.dropped += 1
            queue.append(msg)

    def fail(self, error: str) -> None:
        """Report `error` (ENETDOWN) on a receive once the queued frames are read."""
        with self.lock:
            if self.closed:
                return
            if not self.queue and not self.error:
                os.eventfd_write(self.fd, 1)
            self.error = error

    def take_all(self) -> list[can.Message]:
        with self.lock:
            queue = self.queue
            if not queue:
                self._raise_error()
                return []
            frames = list(queue)
            queue.clear()
            if not self.error:
                os.eventfd_read(self.fd)
            return frames

    def take_one(self) -> can.Message | None:
        with self.lock:
            queue = self.queue
            if not queue:
                self._raise_error()
                return None
            msg = queue.popleft()
            if not queue and not self.error:
                os.eventfd_read(self.fd)
            return msg

    def _raise_error(self) -> None:
        """Raise the pending error, if any (under the lock, queue empty)."""
        error, self.error = self.error, ""
        if error:
            os.eventfd_read(self.fd)
            raise can.CanOperationError(error, errno.ENETDOWN)

    def close(self) -> None:
        with self.lock:
            self.closed = True
            self.queue.clear()
            os.close(self.fd)


class _Channel:
    """The buses sharing one channel name; `receivers` is replaced, never mutated, so a
    sender iterates a consistent snapshot without taking the registry lock."""

    __slots__ = ("down", "receivers")

    def __init__(self) -> None:
        self.receivers: tuple[_Receiver, ...] = ()
        self.down = False


_channels: dict[str, _Channel] = {}
_channels_lock = threading.Lock()


def set_link(channel: str, up: bool) -> None:
    """Take the channel's link down (every send fails with ENETDOWN, every bus on it
    reports ENETDOWN once on receive) or bring it up again, like `ip link set DEV
    down|up` on SocketCAN.  ValueError if no bus is open on `channel`."""
    with _channels_lock:
        chan = _channels.get(channel)
    if chan is None:
        raise ValueError(f"no LoopBus is open on channel {channel!r}")
    was_down, chan.down = chan.down, not up
    if chan.down and not was_down:
        for rx in chan.receivers:
            rx.fail(f"loop bus channel {channel!r}: network is down")


class LoopBus(can.BusABC):
    """In-process CAN bus with a pollable file descriptor; see the module docstring."""

    def __init__(
        self,
        channel: str = "cdprd_loop",
        *,
        receive_own_messages: bool = False,
        rx_queue_size: int = DEFAULT_RX_QUEUE_SIZE,
        bitrate: int | None = None,
        state: can.BusState = can.BusState.ACTIVE,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: object,
    ) -> None:
        if not isinstance(channel, str) or not channel:
            raise ValueError(f"LoopBus channel must be a non-empty string, got {channel!r}")
        if not isinstance(rx_queue_size, int) or rx_queue_size < 1:
            raise ValueError(
                f"LoopBus rx_queue_size must be an integer >= 1, got {rx_queue_size!r}"
            )
        if bitrate is not None and (not isinstance(bitrate, int) or bitrate <= 0):
            raise ValueError(f"LoopBus bitrate must be a positive integer, got {bitrate!r}")
        self.channel = channel
        self.channel_info = f"cdprd loop bus {channel!r}"
        self.receive_own_messages = receive_own_messages
        self.bitrate = bitrate
        self._state = can.BusState(state)
        self._rx = _Receiver(rx_queue_size)
        with _channels_lock:
            self._channel = _channels.setdefault(channel, _Channel())
            self._channel.receivers = (*self._channel.receivers, self._rx)
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    @property
    def state(self) -> can.BusState:
        return self._state

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        self._state = can.BusState(new_state)

    @property
    def dropped(self) -> int:
        """Frames this bus lost because its receive queue was full."""
        return self._rx.dropped

    @property
    def pending(self) -> int:
        """Frames queued for this bus and not read yet."""
        return len(self._rx.queue)

    def fileno(self) -> int:
        """An eventfd that is readable while frames are queued for this bus."""
        self._check_open()
        return self._rx.fd

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Deliver `msg` (not a copy) to every other bus on the channel, stamped now."""
        self._check_open()
        if self._channel.down:
            raise can.CanOperationError(
                f"{self.channel_info}: network is down", errno.ENETDOWN
            )
        if self._state is not can.BusState.ACTIVE:
            raise can.CanOperationError(
                f"{self.channel_info}: cannot send in state {self._state.name}"
            )
        msg.timestamp = time.time()
        msg.channel = self.channel
        own = None if self.receive_own_messages else self._rx
        for rx in self._channel.receivers:
            if rx is not own:
                rx.put(msg)

    def drain(self) -> list[can.Message]:
        """Every queued frame (oldest first) that passes the filters; never blocks."""
        self._check_open()
        frames = self._rx.take_all()
        if self._filters is None:
            return frames
        return [m for m in frames if self._matches_filters(m)]

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_open()
        msg = self._take_matching()
        if msg is None and timeout != 0:
            select.select([self._rx.fd], [], [], timeout)
            msg = self._take_matching()
        return msg, True

    def _take_matching(self) -> can.Message | None:
        """The oldest queued frame that passes the filters (others are discarded), so
        recv(0) finds a match queued behind non-matching frames."""
        while (msg := self._rx.take_one()) is not None:
            if self._filters is None or self._matches_filters(msg):
                return msg
        return None

    def flush_tx_buffer(self) -> None:
        """Nothing to flush: send delivers immediately."""

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        with _channels_lock:
            self._channel.receivers = tuple(r for r in self._channel.receivers if r is not self._rx)
            if not self._channel.receivers and _channels.get(self.channel) is self._channel:
                del _channels[self.channel]
        self._rx.close()

    def _check_open(self) -> None:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down", errno.EBADF)
