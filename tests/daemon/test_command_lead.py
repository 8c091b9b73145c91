"""The daemon's side of the command lead: the drive's force lag from the
drive profile, the measured sample-to-command latency fed to the controller as a
bounded median, and the fixed lead left alone."""

from __future__ import annotations

import asyncio

import pytest

from cdpr import ConfigError
from daemon.config import load_config
from daemon.service.command_lead import LatencyMedian
from tests.daemon_stack import DRIVER_CONFIGS, Stack

pytestmark = pytest.mark.timeout(60)


def test_latency_median_reports_each_full_window_bounded() -> None:
    median = LatencyMedian(bound=0.002, window=5)
    # a host hiccup (9 ms) in a window moves nothing; only a full window reports
    assert [median.add(x) for x in (3e-4, 2e-4, 9e-3, 4e-4, 1e-4)] == [None] * 4 + [3e-4]
    assert [median.add(x) for x in (5e-3, 6e-3, 1e-4, 7e-3, 8e-3)][-1] == 0.002  # bounded
    assert [median.add(-1e-3) for _ in range(5)][-1] == 0.0
    with pytest.raises(ValueError, match="window must be >= 1 and bound > 0"):
        LatencyMedian(bound=0.0)


@pytest.mark.parametrize("value", [-0.001, 0.2, "2ms"])
def test_force_lag_config_refuses_bad_values_by_name(value: object) -> None:
    with pytest.raises(ConfigError, match=r"drives\.force_lag: Input should be"):
        load_config(DRIVER_CONFIGS["cia402"], lambda data: data["drives"].update(force_lag=value))


def _config(protocol: str, force_lag: float, command_lead: object = "auto"):
    def edit(data: dict) -> None:
        data["drives"]["force_lag"] = force_lag
        data["controller"] = {**(data.get("controller") or {}), "command_lead": command_lead}

    return load_config(DRIVER_CONFIGS[protocol], edit)


@pytest.mark.parametrize("protocol", ["cia402", "odrive"])
def test_auto_lead_is_the_drive_lag_half_a_period_and_the_measured_latency(
    protocol: str,
) -> None:
    async def scenario() -> None:
        config = _config(protocol, force_lag=0.001)
        period = 1.0 / config.controller.rate_hz
        async with Stack(config) as stack:
            controller = stack.service.controller
            assert controller.lead == pytest.approx(0.001 + period / 2)  # none measured yet
            await stack.enable()
            # at least two windows of cycles while holding: a measured latency joins it
            await stack.until(lambda: controller.lead > 0.001 + period / 2, 5.0)
            assert controller.lead <= 0.001 + 1.5 * period
            shown = stack.service.state()["cycle"]["command_lead_us"]
            assert shown == pytest.approx(controller.lead * 1e6, abs=0.1)

    asyncio.run(asyncio.wait_for(scenario(), 45))


def test_a_configured_lead_is_not_moved_by_the_latency() -> None:
    async def scenario() -> None:
        config = _config("cia402", force_lag=0.001, command_lead=0.004)
        async with Stack(config) as stack:
            await stack.enable()
            cycles = stack.service.stats.cycles
            await stack.until(lambda: stack.service.stats.cycles > cycles + 120, 5.0)
            assert stack.service.controller.lead == 0.004

    asyncio.run(asyncio.wait_for(scenario(), 45))
