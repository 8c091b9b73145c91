"""Bus helpers shared by the daemon and the simulator."""

from __future__ import annotations

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
