"""daemon.service.cycle_stats: the rings behind the published cycle timing."""

from __future__ import annotations

import numpy as np
import pytest

from daemon.service.cycle_stats import CycleStats, Ring


@pytest.mark.parametrize("count", [1, 2, 7, 100, 10_000, 12_345])
def test_summary_is_numpys_percentile_of_the_last_window(count: int) -> None:
    rng = np.random.default_rng(count)
    ring = Ring(10_000)
    samples = rng.exponential(1e-4, count)
    for value in samples:
        ring.add(float(value))
    window = samples[-10_000:]  # the ring keeps the latest 10^4
    np.testing.assert_array_equal(np.sort(ring.values()), np.sort(window))
    p50, p99 = np.percentile(window, [50, 99]) * 1e6
    summary = ring.summary_us()
    assert summary["p50_us"] == pytest.approx(round(p50, 1), abs=0.051)
    assert summary["p99_us"] == pytest.approx(round(p99, 1), abs=0.051)
    assert summary["max_us"] == round(window.max() * 1e6, 1)


def test_an_empty_ring_summarises_to_zeros() -> None:
    assert Ring(4).summary_us() == {"p50_us": 0.0, "p99_us": 0.0, "max_us": 0.0}


def _sorted_summary_us(values: np.ndarray) -> dict[str, float]:
    """The summary as a full sort gives it (what Ring.summary_us did before it ranked
    with np.partition)."""
    ordered = np.sort(values)

    def quantile(q: float) -> float:
        position = q * (len(ordered) - 1)
        below = int(position)
        above = min(below + 1, len(ordered) - 1)
        return float(ordered[below] + (ordered[above] - ordered[below]) * (position - below))

    return {
        "p50_us": round(quantile(0.5) * 1e6, 1),
        "p99_us": round(quantile(0.99) * 1e6, 1),
        "max_us": round(float(ordered[-1]) * 1e6, 1),
    }


@pytest.mark.parametrize("count", [1, 2, 3, 99, 101, 10_000, 12_345])
def test_summary_equals_the_full_sorts_and_leaves_the_ring_in_order(count: int) -> None:
    rng = np.random.default_rng(count)
    ring = Ring(10_000)
    for value in rng.exponential(1e-4, count):
        ring.add(float(value))
    before = ring.values().copy()
    assert ring.summary_us() == _sorted_summary_us(before)
    np.testing.assert_array_equal(ring.values(), before)


def test_the_published_summary_is_at_most_max_age_cycles_old() -> None:
    """The counters are always current; the rings' summaries are taken again once
    `max_age` cycles have passed since the last (the published state: once a second),
    and every time without it."""
    stats = CycleStats(500.0)
    stats.compute.add(1e-4)
    stats.cycles = 1
    assert stats.summary(max_age=500)["compute"]["p50_us"] == 100.0
    stats.compute.add(3e-4)
    stats.cycles, stats.deadline_misses = 501, 2
    kept = stats.summary(max_age=500)
    assert kept["compute"]["p50_us"] == 100.0 and kept["deadline_misses"] == 2
    assert kept["cycles"] == 501
    assert stats.summary()["compute"]["p50_us"] == 200.0
    stats.compute.add(5e-4)
    stats.cycles = 502
    assert stats.summary(max_age=500)["compute"]["p50_us"] == 200.0
    stats.cycles = 1002
    assert stats.summary(max_age=500)["compute"]["p50_us"] == 300.0
