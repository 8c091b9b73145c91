"""A CAN bus between two processes: one end of a Unix stream socket pair.

`cdprd demo` runs the simulator in a process of its own (so that the simulated drives,
like real ones, never take the control cycle's CPU) and this host's kernel may have no
SocketCAN.  Each frame is one fixed-size record: the frame and the wall-clock time
(time.time(), like SocketCAN's stamps) at which it was sent, which the receiver's
message carries: the simulator places a SYNC at the instant it went out, not when its
process read it.  A stream, not datagrams: a Unix datagram socket queues at most
net.unix.max_dgram_qlen (10 by default) datagrams, fewer than one SYNC's answers from
eight drives; a stream queues by bytes (SEND_BUFFER).  A full buffer is an error at
once, never a wait.

`drain()` returns every queued frame; `fileno()` is readable while any is queued (for
loop.add_reader).  `send_all` writes several frames at once (what a cycle sends: the
reader wakes once for them).  The peer's end closing, or a send it cannot take (its process
stopped reading), is `BusGone`.  Classic CAN only: an FD frame is refused (ValueError).
"""

from __future__ import annotations

import select
import socket
import struct
import time

import can

from drivers.base import bus_frame
from drivers.bus import BusGone

FRAME = struct.Struct("<dIBB8s")  # sent at (s, wall clock), id, flags, dlc, data
# bytes of send buffer a side asks for: each frame is a send, which the kernel counts at
# its buffer's true size (some 0.8 kB): the default 208 kB held 278 frames, 17 cycles of
# eight drives; this holds some 1300 (80 cycles), however briefly the reader stalls
SEND_BUFFER = 1 << 20
SO_SNDBUFFORCE = 32  # <asm-generic/socket.h>
EXTENDED, REMOTE, ERROR = 1, 2, 4


def bus_pair() -> tuple[socket.socket, socket.socket]:
    """Two connected ends for one bus (either may be handed to another process), each
    with SEND_BUFFER where permitted (SO_SNDBUFFORCE needs CAP_NET_ADMIN), else the most
    net.core.wmem_max allows."""
    ends = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    for end in ends:
        try:
            end.setsockopt(socket.SOL_SOCKET, SO_SNDBUFFORCE, SEND_BUFFER)
        except OSError:
            end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
    return ends


def encode(msg: can.Message, sent: float) -> bytes:
    if msg.is_fd:
        raise ValueError("a CAN FD frame: the pair bus carries classic CAN only")
    flags = (
        (EXTENDED if msg.is_extended_id else 0)
        | (REMOTE if msg.is_remote_frame else 0)
        | (ERROR if msg.is_error_frame else 0)
    )
    return FRAME.pack(sent, msg.arbitration_id, flags, msg.dlc, bytes(msg.data))


def decode(datagram: bytes, channel: str) -> can.Message:
    sent, arbitration_id, flags, dlc, data = FRAME.unpack(datagram)
    remote = bool(flags & REMOTE)
    return bus_frame(
        arbitration_id,
        b"" if remote else data[:dlc],
        timestamp=sent,
        channel=channel,
        extended=bool(flags & EXTENDED),
        remote=remote,
        error=bool(flags & ERROR),
        dlc=dlc,
    )


class PairBus(can.BusABC):
    """python-can bus on `sock`, one end of `bus_pair` (non-blocking from here on)."""

    def __init__(self, sock: socket.socket, channel: str = "pair", **kwargs: object) -> None:
        super().__init__(channel=channel, **kwargs)
        self.channel = channel
        self.channel_info = f"socket pair {channel}"
        self._sock = sock
        self._rest = b""  # the start of a record whose end has not come yet
        sock.setblocking(False)

    def fileno(self) -> int:
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.send_all([msg])

    def send_all(self, msgs: list[can.Message]) -> None:
        """The frames in one write, stamped alike: a cycle's frames wake the reader once."""
        if not msgs:
            return
        sent_at = time.time()
        record = b"".join([encode(msg, sent_at) for msg in msgs])
        try:
            sent = self._sock.send(record)
        except BlockingIOError:
            sent = 0
        except (BrokenPipeError, ConnectionResetError):
            raise BusGone(f"{self.channel}: the other process closed its end") from None
        if sent != len(record):  # a record in part would shift every one after it
            raise BusGone(f"{self.channel}: the other process stopped reading")

    def drain(self) -> list[can.Message]:
        """Every frame queued now, oldest first."""
        return self._read(None)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        ready, _, _ = select.select([self._sock], [], [], timeout)
        frames = self._read(1) if ready else []
        return (frames[0] if frames else None), False

    def _read(self, limit: int | None) -> list[can.Message]:
        """At most `limit` queued frames (None: all); BusGone at the peer's end once
        the frames before it are read."""
        data = self._rest
        want = FRAME.size * limit - len(data) if limit is not None else 1 << 16
        while want > 0:
            try:
                chunk = self._sock.recv(want)
            except BlockingIOError:
                break
            except ConnectionResetError:
                chunk = b""
            if not chunk:
                if len(data) < FRAME.size:
                    raise BusGone(f"{self.channel}: the other process closed its end")
                break  # the end again on the next read
            data += chunk
            if len(chunk) < want:  # all there was: another recv would only say so
                break
            want -= len(chunk)
        whole = len(data) - len(data) % FRAME.size
        self._rest = data[whole:]
        channel = self.channel
        return [decode(data[k : k + FRAME.size], channel) for k in range(0, whole, FRAME.size)]

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
