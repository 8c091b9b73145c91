"""drivers.clock: the timerfds that open every control cycle and end its wait for feedback."""

from __future__ import annotations

import math
import time

import pytest

from drivers.clock import DeadlineTimer, PeriodicTimer


def test_expiries_lie_on_the_grid_from_start() -> None:
    period = 0.01
    start = time.monotonic() + 0.02
    with PeriodicTimer(period, start) as timer:
        assert timer.next_expiry() == start  # before the first expiry
        assert timer.expirations() == 0  # nothing elapsed yet, never blocks
        time.sleep(0.02 + 3.5 * period)  # at least 3 expiries after start
        now = time.monotonic()
        following = timer.next_expiry()
        assert now < following <= now + period
        k = (following - start) / period
        assert math.isclose(k, round(k), abs_tol=1e-6)
        assert timer.expirations() >= 4  # start, then 3 more periods at least


def test_a_period_must_be_positive() -> None:
    for period in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="period must be positive"):
            PeriodicTimer(period)


def test_the_last_expiry_is_the_grid_point_at_or_before_now() -> None:
    period, start = 0.01, 100.0
    with PeriodicTimer(period, time.monotonic() + 60.0) as timer:
        timer.start = start  # the grid arithmetic only; the fd never fires here
        assert timer.last_expiry(99.0) == start  # the first one is still ahead
        assert timer.last_expiry(100.0) == start
        assert timer.last_expiry(100.0349) == pytest.approx(100.03)
        assert timer.last_expiry(100.03) == pytest.approx(100.03)  # on a tick: that one


def test_a_wake_up_s_lateness_counts_the_periods_it_let_pass() -> None:
    """From the first expiry a wake-up reads: 4.9 ms after the latest, 3 expirations
    read: the first was two periods before it."""
    period, start = 0.01, 100.0
    with PeriodicTimer(period, time.monotonic() + 60.0) as timer:
        timer.start = start
        assert timer.lateness(100.0349, 1) == pytest.approx(0.0049)
        assert timer.lateness(100.0349, 3) == pytest.approx(0.0249)


def test_a_deadline_fires_once_and_rearming_forgets_an_unread_expiry() -> None:
    with DeadlineTimer() as deadline:
        assert not deadline.expired()  # never armed
        deadline.arm(time.monotonic() + 0.005)
        assert not deadline.expired()  # not yet
        time.sleep(0.02)
        assert deadline.expired()
        assert not deadline.expired()  # once
        deadline.arm(time.monotonic() - 1.0)  # already past: fires at once
        time.sleep(0.002)
        deadline.arm(time.monotonic() + 60.0)  # re-armed before the expiry was read
        assert not deadline.expired()
        time.sleep(0.01)
        assert not deadline.expired()

