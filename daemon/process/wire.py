"""Messages between the real-time core and its companion process (DESIGN §16).

One SOCK_SEQPACKET socket pair: each message is one datagram (a pickled tuple, between
two processes of one daemon, never from the network), optionally with file descriptors
(SCM_RIGHTS): a planned trajectory travels as a sealed memfd holding its packed curve
(cdpr.trajectory.core.Curve), which the core maps and samples in place, so that its
size costs the core nothing.  The core's end is non-blocking and the core never waits
on it: a message that does not fit in the socket's buffer is dropped and counted.
"""

from __future__ import annotations

import fcntl
import mmap
import os
import pickle
import socket
from typing import Any

import numpy as np

from cdpr.trajectory import Trajectory
from cdpr.trajectory.core import Curve

BUFFER_BYTES = 1 << 20  # each direction's socket buffer
MAX_MESSAGE = 256 * 1024  # a datagram larger than this is a bug (trajectories go by memfd)
MAX_FDS = 1


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """(core end, companion end): the core's non-blocking, the companion's blocking
    until its event loop takes it over."""
    core, companion = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for end in (core, companion):
        end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER_BYTES)
        end.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER_BYTES)
    core.setblocking(False)
    return core, companion


def send(sock: socket.socket, message: tuple, fds: tuple[int, ...] = ()) -> bool:
    """Send one message without blocking; False if the peer's buffer is full (the
    message is dropped) or the peer is gone."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if len(data) > MAX_MESSAGE:
        raise ValueError(f"{message[0]!r} message of {len(data)} bytes (> {MAX_MESSAGE})")
    try:
        if fds:
            socket.send_fds(sock, [data], list(fds), socket.MSG_DONTWAIT)
        else:
            sock.send(data, socket.MSG_DONTWAIT)
    except (BlockingIOError, BrokenPipeError, ConnectionResetError):
        return False
    return True


def receive(sock: socket.socket, limit: int) -> tuple[list[tuple[tuple, list[int]]], bool]:
    """Up to `limit` waiting messages, each with the fds it carried, without blocking;
    and whether the peer has closed its end."""
    out: list[tuple[tuple, list[int]]] = []
    while len(out) < limit:
        try:
            data, fds, _flags, _addr = socket.recv_fds(
                sock, MAX_MESSAGE, MAX_FDS, socket.MSG_DONTWAIT
            )
        except BlockingIOError:
            return out, False
        except (ConnectionResetError, OSError):
            return out, True
        if not data:
            for fd in fds:
                os.close(fd)
            return out, True
        out.append((pickle.loads(data), fds))
    return out, False


def curve_file(trajectory: Trajectory) -> tuple[dict, int]:
    """The trajectory's packed curve in a sealed memfd: (header, fd); the caller sends
    and closes the fd."""
    header, data = trajectory.curve.packed()
    fd = os.memfd_create("cdprd-curve", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    try:
        os.ftruncate(fd, data.nbytes)
        with mmap.mmap(fd, data.nbytes) as view:
            view[:] = data.tobytes()
        # sealed: the core samples exactly what was validated, nobody can change it
        seals = fcntl.F_SEAL_SEAL | fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_WRITE
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)
    except BaseException:
        os.close(fd)
        raise
    return header, fd


def mapped_curve(header: dict, fd: int) -> Curve:
    """The curve a companion sent (curve_file), mapped read-only; the fd is closed (the
    mapping stays while the curve lives)."""
    try:
        size = os.fstat(fd).st_size
        view = mmap.mmap(fd, size, prot=mmap.PROT_READ)
    finally:
        os.close(fd)
    return Curve.unpacked(header, np.frombuffer(view, dtype=np.float64))


def error_payload(exc: Any) -> tuple[str, str, dict]:
    """A CommandError as (code, reason, details), to raise again on the other side."""
    return exc.code, exc.reason, exc.details
