"""Logging set-up: journald-friendly under systemd, timestamped on a terminal.

journald stamps every line itself and reads a line's priority from an sd-daemon prefix
("<3>" = error, see sd-daemon(3)), so under systemd lines carry that prefix and no
timestamp; elsewhere they carry a timestamp and the level name.

The loggers that can flood (python-can's, which logs a warning per failed connection
attempt in a busy loop: 444,621 lines in 11 s without a socketcand server; the daemon's
bus port, which logs every failed send) pass through a FloodFilter.
"""

from __future__ import annotations

import logging
import os
import stat
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import TextIO

from cdpr.description import ConfigError

LEVELS = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
    "critical": logging.CRITICAL,
}

PLAIN_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
PLAIN_DATEFMT = "%Y-%m-%d %H:%M:%S"
FLOOD_LOGGERS = ("can", "daemon.service.bus_port")  # python-can's loggers and the daemon's bus port
FLOOD_INTERVAL = 5.0  # s: one line per distinct message per interval from those loggers


def parse_level(name: str) -> int:
    """The logging level for a name such as 'info' (any case); ConfigError otherwise."""
    level = LEVELS.get(name.strip().lower()) if isinstance(name, str) else None
    if level is None:
        raise ConfigError(f"logging level {name!r} is unknown; use one of: {', '.join(LEVELS)}")
    return level


def syslog_priority(levelno: int) -> int:
    """The syslog priority (0 emerg … 7 debug) for a Python logging level."""
    if levelno >= logging.CRITICAL:
        return 2
    if levelno >= logging.ERROR:
        return 3
    if levelno >= logging.WARNING:
        return 4
    if levelno >= logging.INFO:
        return 6
    return 7


class JournaldFormatter(logging.Formatter):
    """'<p>logger: message' with the priority prefix on EVERY line, so the lines of a
    traceback keep the record's priority (journald splits a stream at newlines)."""

    def __init__(self) -> None:
        super().__init__("%(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def journald_detected(
    stream: TextIO | None = None, environ: Mapping[str, str] | None = None
) -> bool:
    """True when `stream` (default stderr) is connected to the journal.

    JOURNAL_STREAM ("device:inode", set by systemd when stdout or stderr goes to the
    journal) is authoritative: it must match the stream's file.  Without it, INVOCATION_ID
    (set for every systemd service) counts only if the stream is a socket, the way journald
    and syslog receive output; a service writing to a file (StandardError=file:…) or a
    terminal keeps timestamps.
    """
    env = os.environ if environ is None else environ
    target = sys.stderr if stream is None else stream
    try:
        info = os.fstat(target.fileno())
    except (AttributeError, OSError, ValueError):
        return False  # no real file behind it (e.g. captured by a test runner)
    journal_stream = env.get("JOURNAL_STREAM")
    if journal_stream is not None:
        return journal_stream == f"{info.st_dev}:{info.st_ino}"
    return "INVOCATION_ID" in env and stat.S_ISSOCK(info.st_mode)


class FloodFilter(logging.Filter):
    """Passes the first record of each distinct message (logger and text) from the
    loggers named in `loggers` (and their children), then holds that message back for
    `interval` seconds, counting it; the next one to pass after that says how many were
    held back ("[123 more in the last 5 s]").  Other loggers pass untouched.  At most
    `max_messages` messages are tracked (the expired ones are forgotten first; beyond
    that, new messages pass).  Thread-safe: python-can logs from its Notifier thread."""

    def __init__(
        self,
        loggers: Iterable[str] = FLOOD_LOGGERS,
        interval: float = FLOOD_INTERVAL,
        clock: Callable[[], float] = time.monotonic,
        max_messages: int = 256,
    ) -> None:
        super().__init__()
        self._loggers = tuple(loggers)
        self.interval = interval
        self._clock = clock
        self._max = max_messages
        self._lock = threading.Lock()
        self._seen: dict[tuple[str, str], list] = {}  # -> [passed at, held back since]

    def filter(self, record: logging.LogRecord) -> bool:
        name = record.name
        if not any(name == n or name.startswith(n + ".") for n in self._loggers):
            return True
        text = record.getMessage()
        key = (name, text)
        with self._lock:
            now = self._clock()
            seen = self._seen.get(key)
            if seen is not None and now - seen[0] < self.interval:
                seen[1] += 1
                return False
            if seen is None and len(self._seen) >= self._max:
                self._seen = {k: v for k, v in self._seen.items() if now - v[0] < self.interval}
            if seen is not None or len(self._seen) < self._max:
                self._seen[key] = [now, 0]
        if seen is not None and seen[1]:
            record.msg = f"{text} [{seen[1]} more in the last {now - seen[0]:.0f} s]"
            record.args = None
        return True


def configure_logging(level: str, journald: bool | None = None) -> logging.Handler:
    """Send log records at `level` and above to stderr, in the journald format when
    `journald` is true (None: detect it), through a FloodFilter.  Idempotent: a second
    call replaces the handler installed by the first and leaves other handlers alone.
    Returns the new handler."""
    levelno = parse_level(level)
    use_journald = journald_detected() if journald is None else journald
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(FloodFilter())
    if use_journald:
        handler.setFormatter(JournaldFormatter())
    else:
        handler.setFormatter(logging.Formatter(PLAIN_FORMAT, PLAIN_DATEFMT))
    handler.set_name("cdprd")
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == "cdprd"]:
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(levelno)
    return handler
