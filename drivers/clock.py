"""A periodic wake-up for cyclic CAN traffic: a Linux timerfd an event loop can poll.

asyncio.sleep wakes with about 1 ms granularity (epoll timeouts are whole milliseconds);
a timerfd registered with `loop.add_reader` wakes within about 0.1 ms (PERF-FACTS).
Python 3.11 has no os.timerfd_create, so this goes through libc with ctypes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
import struct
import time

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


def _timespec(seconds: float) -> _Timespec:
    whole = int(seconds)
    return _Timespec(whole, round((seconds - whole) * 1e9))


class PeriodicTimer:
    """A CLOCK_MONOTONIC timerfd firing every `period` seconds from `start` (default: one
    period from now).  `fileno()` becomes readable at each expiry; `expirations()` reads
    and returns how many periods elapsed since the last read (more than 1 = overrun)."""

    def __init__(self, period: float, start: float | None = None) -> None:
        if not period > 0.0:
            raise ValueError(f"timer period must be positive, not {period}")
        fd = _libc.timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
        self._fd = fd
        self.period = period
        first = time.monotonic() + period if start is None else start
        spec = _Itimerspec(_timespec(period), _timespec(first))
        if _libc.timerfd_settime(fd, TFD_TIMER_ABSTIME, ctypes.byref(spec), None) < 0:
            err = ctypes.get_errno()
            os.close(fd)
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")
        self.start = first

    def fileno(self) -> int:
        return self._fd

    def last_expiry(self, now: float) -> float:
        """The monotonic time of the latest expiry at or before `now` (a wake-up's
        lateness is `now` minus this); `start` while the first is still ahead."""
        if now < self.start:
            return self.start
        return self.start + math.floor((now - self.start) / self.period + 1e-9) * self.period

    def next_expiry(self) -> float:
        """The monotonic time of the next expiry."""
        now = time.monotonic()
        if now < self.start:
            return self.start
        return self.last_expiry(now) + self.period

    def expirations(self) -> int:
        """Periods elapsed since the last call (0 if woken spuriously)."""
        try:
            return _EXPIRATIONS.unpack(os.read(self._fd, 8))[0]
        except BlockingIOError:
            return 0

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> PeriodicTimer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
