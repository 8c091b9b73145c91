"""Cycle records as fixed-size rows (daemon/process/cycle_rows.py): what the core writes
the companion reads back, value for value."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from cdpr import Pose
from daemon.process.cycle_rows import CycleRows, Throttle, records, row_width
from daemon.service.safety import SafetyState


def _output(k: int, n: int) -> SimpleNamespace:
    rng = np.random.default_rng(k)
    pose = Pose.from_rotvec(rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3))
    reference = Pose.from_rotvec(rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3))
    return SimpleNamespace(
        pose=pose,
        reference=SimpleNamespace(pose=reference),
        twist=rng.uniform(-1, 1, 6),
        tensions=rng.uniform(0, 600, n),
        commands=rng.uniform(-600, 0, n),
    )


def test_rows_read_back_as_the_cycles_written() -> None:
    n = 8
    rows = CycleRows(n, capacity=3)
    written = []
    for k, state in enumerate((SafetyState.HOLD, SafetyState.TRACKING, SafetyState.BRAKED)):
        out, lengths = _output(k, n), [2.0 + 0.1 * j for j in range(n)]
        rows.add(0.002 * k, out, lengths, state)
        written.append((0.002 * k, out, lengths, state))
    assert rows.full
    data = rows.take()
    assert len(data) == 3 * row_width(n) * 8 and rows.filled == 0 and not rows.full
    for record, (t, out, lengths, state) in zip(records(data, n), written, strict=True):
        assert record.t == t and record.safety == state.value
        assert record.position == list(out.pose.position_tuple)
        assert record.quaternion == list(out.pose.quaternion_tuple)
        assert record.twist == out.twist.tolist()
        assert record.lengths == lengths
        assert record.tensions == out.tensions.tolist()
        assert record.forces == out.commands.tolist()
        ref = out.reference.pose
        assert record.reference == (list(ref.position_tuple), list(ref.quaternion_tuple))


def test_the_throttle_lets_one_cycle_through_per_period() -> None:
    throttle = Throttle(30.0)
    times = [k / 500.0 for k in range(5000)]  # 10 s of a 500 Hz cycle
    passed = [t for t in times if throttle.due(t)]
    assert len(passed) == 300  # on a fixed grid: no drift from the 2 ms steps
    gaps = np.diff(passed)
    assert np.all(np.abs(gaps - 1 / 30) <= 2e-3 + 1e-9)  # within one cycle of the period
    # a pause restarts the grid instead of letting a burst through
    assert throttle.due(100.0) and not throttle.due(100.002)
    resampled = Throttle(30.0)  # the companion throttles the core's throttled rows again
    assert [t for t in passed if resampled.due(t)] == passed
