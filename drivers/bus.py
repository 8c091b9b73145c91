"""Bus helpers shared by the daemon and the simulator."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import can


def drain(bus: can.BusABC) -> list[can.Message]:
    """Every frame queued on `bus` now, without blocking: one call on buses that offer
    `drain()` (the loop bus, the fault-injecting bus), else recv(0) until empty."""
    take_all = getattr(bus, "drain", None)
    if take_all is not None:
        return take_all()
    frames = []
    while (msg := bus.recv(0.0)) is not None:
        frames.append(msg)
    return frames


class BusWatch:
    """Runs `on_readable()` on `loop` whenever `bus` has frames queued: through
    loop.add_reader where the bus has a file descriptor (socketcan, the loop bus), else
    through a python-can Notifier thread that hands each frame to `deliver(frame)` on the
    loop."""

    def __init__(
        self,
        bus: can.BusABC,
        loop: asyncio.AbstractEventLoop,
        on_readable: Callable[[], None],
        deliver: Callable[[can.Message], None],
    ) -> None:
        self._loop = loop
        self._fd = -1
        self._notifier: can.Notifier | None = None
        try:
            fd = bus.fileno()
        except NotImplementedError:
            fd = -1
        if isinstance(fd, int) and fd >= 0:
            self._fd = fd
            loop.add_reader(fd, on_readable)
        else:

            def from_thread(msg: can.Message) -> None:
                if not loop.is_closed():
                    loop.call_soon_threadsafe(deliver, msg)

            self._notifier = can.Notifier(bus, [from_thread], timeout=0.1)

    def close(self) -> None:
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            self._fd = -1
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
