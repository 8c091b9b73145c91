"""tests.host_steal: the share of CPU time stolen, and how a real-time figure is judged."""

from __future__ import annotations

import pytest

from tests import host_steal
from tests.host_steal import StealMeter


def metered(monkeypatch: pytest.MonkeyPatch, steal: int, total: int) -> StealMeter:
    """A meter over a block in which `steal` of `total` jiffies were stolen."""
    readings = iter([(100, 10_000), (100 + steal, 10_000 + total)])
    monkeypatch.setattr(host_steal, "_times", lambda: next(readings))
    with StealMeter() as meter:
        pass
    return meter


def test_the_stolen_share_is_that_of_the_block(monkeypatch: pytest.MonkeyPatch) -> None:
    assert metered(monkeypatch, 50, 1000).fraction == pytest.approx(0.05)


def test_a_figure_within_its_bound_passes_whatever_was_stolen(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    metered(monkeypatch, 500, 1000).check(True, "the lag", "fine")


def test_a_missed_bound_fails_on_a_quiet_host(monkeypatch: pytest.MonkeyPatch) -> None:
    meter = metered(monkeypatch, 10, 1000)  # 1 %
    with pytest.raises(AssertionError, match=r"the lag: 4\.5 ms"):
        meter.check(False, "the lag", "4.5 ms")


def test_a_missed_bound_skips_saying_why_on_a_robbed_host(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    meter = metered(monkeypatch, 80, 1000)  # 8 %
    with pytest.raises(pytest.skip.Exception, match=r"the lag: 4.5 ms, with 8.0% .*over 2%"):
        meter.check(False, "the lag", "4.5 ms")


def test_this_host_s_counters_are_read() -> None:
    steal, total = host_steal._times()
    assert 0 <= steal <= total and total > 0  # Linux: /proc/stat's first line
