"""systemd integration without a dependency: sd_notify and the service watchdog.

The unit runs the daemon as Type=notify with WatchdogSec (config/cdprd.service).  systemd
passes a unix datagram socket in NOTIFY_SOCKET (a path, or '@name' in the abstract
namespace) and the watchdog timeout in WATCHDOG_USEC.  Each notification is one datagram of
newline-separated KEY=VALUE lines.  Without NOTIFY_SOCKET (run from a shell, in tests)
every call is a no-op, so the daemon needs no "am I under systemd" switch.

The watchdog is fed from the event loop and only while the control cycle makes progress:
a stalled loop or a stuck cycle stops the pings, systemd kills the daemon, the drives'
own watchdogs brake, and the restarted daemon starts in IDLE (DESIGN §9).
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import Awaitable, Callable, Mapping

log = logging.getLogger(__name__)


def _socket_address(value: str) -> str | bytes:
    """The sendto() address for a NOTIFY_SOCKET value (path or '@abstract')."""
    if value.startswith("/"):
        return value
    if value.startswith("@") and len(value) > 1:
        return b"\0" + value[1:].encode()
    raise ValueError(
        f"NOTIFY_SOCKET={value!r} is not supported: expected an absolute path or '@name' "
        "(an abstract unix socket)"
    )


class Notifier:
    """Sends sd_notify messages to the service manager; a no-op without NOTIFY_SOCKET.

    `environ` defaults to os.environ and is read once, at construction.  Sending never
    blocks (non-blocking socket); a failed send is logged and reported as False, never
    raised, because a lost notification must not stop the control cycle.
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._environ = dict(env)
        value = env.get("NOTIFY_SOCKET", "")
        self._address = _socket_address(value) if value else None
        self._socket: socket.socket | None = None
        if self._address is not None:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._socket.setblocking(False)

    @property
    def enabled(self) -> bool:
        """True when a service manager listens (NOTIFY_SOCKET was set)."""
        return self._socket is not None

    def notify(self, *assignments: str) -> bool:
        """Send KEY=VALUE lines as one datagram; True if sent, False if disabled or failed."""
        if self._socket is None or self._address is None:
            return False
        for line in assignments:
            if "=" not in line or "\n" in line:
                raise ValueError(f"sd_notify field {line!r} must be one KEY=VALUE line")
        try:
            self._socket.sendto("\n".join(assignments).encode(), self._address)
        except OSError as exc:
            log.warning("sd_notify %s failed: %s", assignments[0].split("=", 1)[0], exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """Start-up finished (Type=notify: systemd now considers the service started)."""
        fields = ["READY=1"] if status is None else ["READY=1", _status_field(status)]
        return self.notify(*fields)

    def status(self, text: str) -> bool:
        """A one-line human-readable status shown by `systemctl status`."""
        return self.notify(_status_field(text))

    def stopping(self) -> bool:
        """Shutdown has begun (sent before braking and closing the bus on SIGTERM)."""
        return self.notify("STOPPING=1")

    def watchdog(self) -> bool:
        """Feed the service watchdog once."""
        return self.notify("WATCHDOG=1")

    def watchdog_interval(self) -> float | None:
        """Seconds between watchdog pings: half of WATCHDOG_USEC, as sd_watchdog_enabled(3)
        recommends.  None when no watchdog is configured for this process (WATCHDOG_USEC
        unset, or WATCHDOG_PID names another process)."""
        usec = self._environ.get("WATCHDOG_USEC")
        if usec is None:
            return None
        pid = self._environ.get("WATCHDOG_PID")
        if pid is not None:
            if not pid.isdigit():
                raise ValueError(f"WATCHDOG_PID={pid!r} is not a process id")
            if int(pid) != os.getpid():
                return None
        if not usec.isdigit() or int(usec) == 0:
            raise ValueError(f"WATCHDOG_USEC={usec!r} is not a positive number of microseconds")
        return int(usec) / 2e6

    def close(self) -> None:
        """Close the socket; later calls are no-ops."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def _status_field(text: str) -> str:
    """STATUS=<text> as one printable line of valid UTF-8.  The text may carry a brake
    reason from the network: a line break would end the field, and a lone surrogate (a
    JSON "\\ud800" escape) cannot be encoded at all; so characters that are not printable
    become spaces, surrogates U+FFFD."""
    return "STATUS=" + " ".join("".join(map(_printable, text)).split())


def _printable(char: str) -> str:
    if char.isprintable():
        return char
    return "\ufffd" if "\ud800" <= char <= "\udfff" else " "


class Progress:
    """Liveness of the control cycle for `run_watchdog`: `count()` is the number of
    completed cycles; calling the object answers "did a cycle complete since the last
    call?"  A stuck cycle (or a blocked event loop) therefore stops the watchdog pings.
    The first call answers true: a grace period while the first cycle starts."""

    def __init__(self, count: Callable[[], int]) -> None:
        self._count = count
        self._seen: int | None = None

    def __call__(self) -> bool:
        count = self._count()
        alive = count != self._seen
        self._seen = count
        return alive


async def run_watchdog(
    notifier: Notifier,
    alive: Callable[[], bool],
    interval: float | None = None,
    sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
) -> None:
    """Feed the service watchdog from the event loop every `interval` seconds (default
    `notifier.watchdog_interval()`) while `alive()` is true; returns at once when there
    is no watchdog.  An `alive` that raises counts as not alive.  Runs until cancelled;
    `sleep` is injectable so tests can drive it without wall-clock time."""
    period = notifier.watchdog_interval() if interval is None else interval
    if period is None or not notifier.enabled:
        return
    if not period > 0:
        raise ValueError(f"watchdog interval must be positive, not {period}")
    missed = False
    while True:
        try:
            ok = bool(alive())
        except Exception:
            log.exception("watchdog liveness check raised; not feeding the watchdog")
            ok = False
        if ok:
            notifier.watchdog()
            if missed:
                log.warning("control cycle progressing again; watchdog fed")
        elif not missed:
            log.error("control cycle made no progress; withholding the systemd watchdog ping")
        missed = not ok
        await sleep(period)
