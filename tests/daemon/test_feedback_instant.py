"""A cycle's lengths describe the cables at the cycle's instant (DESIGN §8): a SYNC
drive whose answer to this cycle's SYNC has not come enters with its last answer carried
from the SYNC that latched it at its rate.  Left a period old while the platform moves,
it put FK a period's motion off and failed the trusted-lengths own-rate check (the
canopen drives' flights braked on implausible_feedback when one answer came late)."""

from __future__ import annotations

import itertools
import os

import can
import pytest

from daemon.service.service import Service
from tests.daemon_stack import config_for

CHANNELS = itertools.count()


@pytest.fixture
def service():
    config = config_for("cia402")
    channel = f"cdprd-instant-{os.getpid()}-{next(CHANNELS)}"
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    service = Service(config, bus)
    yield service
    service.close()
    bus.shutdown()


def _cycle(service: Service, instant: float, answered: dict[int, float], rate: float):
    """Open a cycle at `instant` in which the drives in `answered` (drive: length) answered
    its SYNC, each at `rate`; the others stay silent.  Its feedback as the cycle takes it."""
    service._opened = instant
    service._counts = [fb.count for fb in service.driver.feedback]
    for k, length in answered.items():
        fb = service.driver.feedback[k]
        fb.length, fb.rate, fb.count = length, rate, fb.count + 1
        fb.stamp, fb.latched = instant + 1e-3, instant  # the driver's: this cycle's SYNC
    return service._take_feedback(service.driver.feedback)


def test_a_drive_that_missed_a_sync_is_carried_to_the_cycle_at_its_rate(service) -> None:
    n, period, rate = service.n, service.period, 0.5
    fresh, lengths, _ = _cycle(service, 10.0, dict.fromkeys(range(n), 1.0), rate)
    assert all(fresh) and lengths == [1.0] * n
    moved = 1.0 + rate * period
    fresh, lengths, _ = _cycle(service, 10.0 + period, dict.fromkeys(range(n - 1), moved), rate)
    assert fresh == [True] * (n - 1) + [False]
    assert lengths[: n - 1] == [moved] * (n - 1)
    assert lengths[n - 1] == pytest.approx(moved, abs=1e-12)  # before: 1.0, a period old
    # two SYNCs without an answer: two periods' motion
    fresh, lengths, _ = _cycle(service, 10.0 + 2 * period, {}, rate)
    assert not any(fresh) and lengths[n - 1] == pytest.approx(1.0 + 2 * rate * period)
    # answered again: its own length, from then on carried from there
    fresh, lengths, _ = _cycle(service, 10.0 + 3 * period, {n - 1: 1.2}, rate)
    assert fresh[n - 1] and lengths[n - 1] == 1.2
    assert lengths[0] == pytest.approx(moved + 2 * rate * period)


def test_a_silent_drive_is_carried_no_further_than_the_cycles_it_may_miss(service) -> None:
    n, period, rate = service.n, service.period, 0.5
    _cycle(service, 10.0, dict.fromkeys(range(n), 1.0), rate)
    _, lengths, _ = _cycle(service, 10.0 + 100 * period, {}, rate)
    limit = service.config.safety.stale_cycles * period
    assert lengths == pytest.approx([1.0 + rate * limit] * n)


def test_a_drive_never_heard_from_carries_nothing(service) -> None:
    n = service.n
    fresh, lengths, _ = _cycle(service, 10.0, {0: 1.0}, 0.0)
    assert fresh == [True] + [False] * (n - 1)
    assert lengths[0] == 1.0 and all(x != x for x in lengths[1:])  # NaN: no length yet


def test_an_answer_after_its_deadline_is_carried_from_its_own_sync(service) -> None:
    """A drive whose answer to the last SYNC came after that cycle's deadline (so it is
    not fresh in this one) was latched a period ago, not when it was last fresh: it is
    carried one period, however many cycles it has been late."""
    n, period, rate = service.n, service.period, 0.5
    _cycle(service, 10.0, dict.fromkeys(range(n), 1.0), rate)
    for k in range(1, 6):  # drive 0 answers each SYNC after the cycle ran
        instant = 10.0 + k * period
        fresh, lengths, _ = _cycle(service, instant, dict.fromkeys(range(1, n), 1.0), rate)
        late = service.driver.feedback[0]
        late.length, late.latched = 1.0 + rate * (k - 1) * period, instant - period
        late.count += 1  # in before the next tick: not fresh there either
        service._counts[0] = late.count
        assert not fresh[0]
    fresh, lengths, _ = _cycle(service, 10.0 + 6 * period, dict.fromkeys(range(1, n), 1.0), rate)
    assert not fresh[0]
    assert lengths[0] == pytest.approx(1.0 + rate * 5 * period + rate * period)
