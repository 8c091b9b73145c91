"""The shared ring planned curves cross into the core in (daemon/process/curve_ring.py),
and the messages beside it (daemon/process/wire.py)."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import Pose
from cdpr.trajectory import Trajectory, Waypoint
from daemon.process import wire
from daemon.process.curve_ring import ALIGN, CurveRing, RingFullError


def _trajectory(n: int) -> Trajectory:
    rng = np.random.default_rng(n)
    waypoints = [
        Waypoint(0.5 * k, Pose.from_rotvec(rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)))
        for k in range(n)
    ]
    return Trajectory(waypoints)


def test_a_curve_written_by_one_mapping_samples_the_same_through_another() -> None:
    """The companion writes, the core reads the same memfd mapped twice: in place, the
    reference equal at every time."""
    core = CurveRing.create(1 << 20)
    companion = CurveRing.attach(core.fd)
    trajectory = _trajectory(12).shifted(3.0)
    header, offset, count = companion.write(trajectory)
    curve = core.curve(header, offset, count)
    for t in np.linspace(trajectory.start_time - 1, trajectory.end_time + 1, 300):
        assert curve.sample(float(t)).same_as(trajectory.sample(float(t)))
    with pytest.raises(ValueError, match="outside the ring"):
        core.curve(header, core.size - 8, count)


def test_ranges_are_first_fit_and_merge_when_released() -> None:
    ring = CurveRing.create(16 * ALIGN)
    a = ring.allocate(3 * ALIGN)
    b = ring.allocate(ALIGN + 1)  # rounded up to two lines
    c = ring.allocate(4 * ALIGN)
    assert (a, b, c) == (0, 3 * ALIGN, 5 * ALIGN)
    ring.release(b, ALIGN + 1)
    assert ring.allocate(2 * ALIGN) == b  # the hole is reused first
    ring.release(a, 3 * ALIGN)
    ring.release(b, 2 * ALIGN)
    ring.release(c, 4 * ALIGN)
    assert ring.free_bytes == ring.size
    assert ring.allocate(16 * ALIGN) == 0  # merged back into one range
    with pytest.raises(RingFullError, match="largest free range 0 bytes"):
        ring.allocate(1)


def test_a_new_companion_keeps_off_the_ranges_the_core_still_reads() -> None:
    ring = CurveRing.create(16 * ALIGN)
    ring.reserve([(2 * ALIGN, 3 * ALIGN), (10 * ALIGN, ALIGN)])
    assert ring.free_bytes == 12 * ALIGN
    taken = sorted(ring.allocate(ALIGN) for _ in range(12))
    assert not set(taken) & {2 * ALIGN, 3 * ALIGN, 4 * ALIGN, 10 * ALIGN}
    with pytest.raises(RingFullError):
        ring.allocate(1)


def test_the_core_never_blocks_on_a_full_socket_and_sees_its_peer_go() -> None:
    core, companion = wire.socket_pair()
    sent = 0
    while wire.send(core, ("state", {"pad": "x" * 10_000})) and sent < 10_000:
        sent += 1
    assert 0 < sent < 10_000  # the buffer filled, and send said so instead of waiting
    companion.setblocking(False)
    messages, closed = wire.receive(companion, 3)
    assert len(messages) == 3 and messages[0][0] == "state" and not closed
    with pytest.raises(ValueError, match="bytes"):
        wire.send(core, ("state", "x" * wire.MAX_MESSAGE))
    companion.close()
    assert not wire.send(core, ("event", {}))
    core.setblocking(False)
    assert wire.receive(core, 10) == ([], True)
