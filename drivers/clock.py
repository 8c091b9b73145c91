"""Wake-ups for cyclic CAN traffic: Linux timerfds an event loop can poll.  The periodic
one opens every control cycle; the one-shot one ends a cycle's wait for its feedback.

asyncio.sleep and loop.call_at wake with about 1 ms granularity (epoll timeouts are
whole milliseconds, rounded up); a timerfd registered with `loop.add_reader` wakes within
about 0.1 ms (PERF-FACTS).  A deadline 0.2 ms before the next tick set with call_at
fires with that tick instead: the cycle then stays open from tick to tick.  Python 3.11
has no os.timerfd_create, so this goes through libc with ctypes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
import struct
import time
from typing import Self

CLOCK_MONOTONIC = 1
TFD_NONBLOCK = os.O_NONBLOCK
TFD_CLOEXEC = os.O_CLOEXEC
TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


_libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
_libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
_libc.timerfd_settime.argtypes = [
    ctypes.c_int,
    ctypes.c_int,
    ctypes.POINTER(_Itimerspec),
    ctypes.POINTER(_Itimerspec),
]
_EXPIRATIONS = struct.Struct("=Q")


def _put(spec: _Timespec, seconds: float) -> None:
    whole = int(seconds)
    spec.tv_sec = whole
    spec.tv_nsec = round((seconds - whole) * 1e9)


class _TimerFd:
    """A CLOCK_MONOTONIC timerfd (non-blocking, closed on exec).  Its itimerspec is
    made once and rewritten in place: the deadline is set twice a cycle, and building
    the ctypes structures each time cost more than the system call."""

    def __init__(self) -> None:
        fd = _libc.timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
        self._fd = fd
        self._spec = _Itimerspec()
        self._spec_ref = ctypes.byref(self._spec)

    def _set(self, first: float, interval: float = 0.0) -> None:
        """Fire at monotonic time `first` (0: disarmed), then every `interval` s (0:
        once); expiries not yet read are forgotten."""
        spec = self._spec
        _put(spec.it_interval, interval)
        _put(spec.it_value, first)
        if _libc.timerfd_settime(self._fd, TFD_TIMER_ABSTIME, self._spec_ref, None) < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")

    def fileno(self) -> int:
        return self._fd

    def expirations(self) -> int:
        """Expiries since the last read (0 if woken spuriously)."""
        try:
            return _EXPIRATIONS.unpack(os.read(self._fd, 8))[0]
        except BlockingIOError:
            return 0

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PeriodicTimer(_TimerFd):
    """A timerfd firing every `period` seconds from `start` (default: one period from
    now).  `fileno()` becomes readable at each expiry; `expirations()` reads and returns
    how many periods elapsed since the last read (more than 1 = overrun)."""

    def __init__(self, period: float, start: float | None = None) -> None:
        if not period > 0.0:
            raise ValueError(f"timer period must be positive, not {period}")
        super().__init__()
        self.period = period
        try:
            self.restart(time.monotonic() + period if start is None else start)
        except OSError:
            self.close()
            raise

    def restart(self, start: float) -> None:
        """Fire at monotonic time `start`, then every period from there."""
        self._set(start, self.period)
        self.start = start

    def last_expiry(self, now: float) -> float:
        """The monotonic time of the latest expiry at or before `now` (a wake-up's
        lateness is `now` minus this); `start` while the first is still ahead."""
        if now < self.start:
            return self.start
        return self.start + math.floor((now - self.start) / self.period + 1e-9) * self.period

    def lateness(self, now: float, expired: int) -> float:
        """How late (s) a wake-up at `now` that read `expired` expirations takes the
        first of them: its own lateness plus the whole periods it let pass."""
        return now - self.last_expiry(now) + (expired - 1) * self.period

    def next_expiry(self) -> float:
        """The monotonic time of the next expiry."""
        now = time.monotonic()
        if now < self.start:
            return self.start
        return self.last_expiry(now) + self.period


class DeadlineTimer(_TimerFd):
    """A one-shot timerfd: `arm(at)` makes `fileno()` readable at monotonic time `at`
    and forgets an expiry not yet read, so `expired()` (read by the fd's reader) is True
    only for the deadline last armed, never for one that fired just before it was
    re-armed.  Not cancelled once its wait is over: a cancel reprograms the host's timer
    (~15 us in the core's cycle, a virtual machine's exit), and the wake-up it would
    save costs no more CPU (the core reads the expiry and ignores it)."""

    def arm(self, at: float) -> None:
        self._set(max(at, 1e-9))  # 0 would disarm: a deadline already past fires at once

    def expired(self) -> bool:
        return self.expirations() > 0
