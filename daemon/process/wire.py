"""Messages between the real-time core and its companion process (DESIGN §16).

One SOCK_SEQPACKET socket pair: each message is one datagram (a pickled tuple, between
two processes of one daemon, never from the network).  A planned trajectory's curve
does not travel here: it lies in the shared ring (daemon.process.curve_ring) and the
message names where.  The core's end is non-blocking and the core never waits on it: a
message that does not fit in the socket's buffer is dropped and counted.

Both ends must run the same code: the messages carry its classes (the config, references,
curves' headers).  A package upgraded under a running service breaks that for the next
companion the core starts, which imports the new code: so the core's first message is its
`code_fingerprint()` (builtins only, readable by any version), checked before the hello.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import pickle
import socket
from pathlib import Path

from daemon.service.api import CommandError

BUFFER_BYTES = 1 << 20  # each direction's socket buffer
MAX_MESSAGE = 256 * 1024  # a datagram larger than this is a bug (trajectories go by the ring)
PACKAGES = ("cdpr", "daemon", "drivers", "sim_bus", "tuning")  # the project's (pyproject)
OTHER_CODE = 3  # the companion's exit code when its code is not the core's
# s the core and systemd wait for a companion that said ("starting",): its start-up check
# compiles numba kernels, 12 s on a cold cache on this 2-vCPU host and over 30 s in the
# UML guest, minutes on a small computer (first start after an install or upgrade)
STARTING_LIMIT = 300.0


@functools.cache
def code_fingerprint() -> str:
    """A digest of the project's Python sources as installed now (each package's files,
    by their paths inside it, and contents): equal in the core and its companion unless
    the installation changed between their starts.  A few milliseconds, once."""
    digest = hashlib.blake2b(digest_size=12)
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        digest.update(name.encode())
        if spec is None or not spec.submodule_search_locations:
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        for path in sorted(root.rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """(core end, companion end): the core's non-blocking, the companion's blocking
    until its event loop takes it over."""
    core, companion = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for end in (core, companion):
        end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, BUFFER_BYTES)
        end.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BUFFER_BYTES)
    core.setblocking(False)
    return core, companion


def send(sock: socket.socket, message: tuple) -> bool:
    """Send one message without blocking; False if the peer's buffer is full (the
    message is dropped) or the peer is gone."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if len(data) > MAX_MESSAGE:
        raise ValueError(f"{message[0]!r} message of {len(data)} bytes (> {MAX_MESSAGE})")
    try:
        sock.send(data, socket.MSG_DONTWAIT)
    except (BlockingIOError, BrokenPipeError, ConnectionResetError):
        return False
    return True


def receive(sock: socket.socket, limit: int) -> tuple[list[tuple], bool]:
    """Up to `limit` waiting messages without blocking, and whether the peer has closed
    its end."""
    out: list[tuple] = []
    while len(out) < limit:
        try:
            data = sock.recv(MAX_MESSAGE, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return out, False
        except OSError:  # reset, or closed here
            return out, True
        if not data:
            return out, True
        out.append(pickle.loads(data))
    return out, False


def error_payload(exc: BaseException) -> tuple[str, str, dict]:
    """(code, reason, details) for the other side to raise again as a CommandError: a
    refusal's own, or "internal" naming anything else (a bug)."""
    if isinstance(exc, CommandError):
        return exc.code, exc.reason, exc.details
    return "internal", f"{type(exc).__name__}: {exc}", {}
