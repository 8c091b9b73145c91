"""A push on the simulated platform through the daemon: a person
leaning on it is held and published as the external wrench; a push beyond the
observer's bound brakes with external_wrench."""

from __future__ import annotations

import asyncio

import pytest

from daemon.config import DaemonConfig
from daemon.service.safety import SafetyState, Trigger
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(90)


def _config(observer: dict | None = None) -> DaemonConfig:
    return config_for(
        "cia402",
        sim={"plant": {"step": 0.001}},
        controller={"disturbance_observer": observer or {}},
    )


async def _enable_then_push(stack: Stack, push: float) -> None:
    """Enable, then lean on the platform with `push` N along x (pushed before, the
    platform would not be at rest where the tensions say: enable refuses that)."""
    await stack.enable()
    stack.plant._disturbance = lambda t: (push, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_a_50_n_push_is_held_and_published() -> None:
    async def scenario() -> None:
        async with Stack(_config()) as stack:
            service = stack.service
            await _enable_then_push(stack, 50.0)
            await stack.until(lambda: service.state()["external_wrench"][0] > 45.0, 10.0)
            await asyncio.sleep(1.0)
            assert service.machine.state is SafetyState.HOLD, service.machine.fault
            push = service.state()["external_wrench"]
            assert push[0] == pytest.approx(50.0, abs=2.5) and max(map(abs, push[1:3])) < 2.5

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_a_push_beyond_the_bound_brakes_naming_the_trigger() -> None:
    """50 N against a force_max of 30 N: the estimate crosses it long before the
    tracking error would brake."""

    async def scenario() -> None:
        async with Stack(_config({"force_max": 30.0})) as stack:
            service = stack.service
            await _enable_then_push(stack, 50.0)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 10.0)
            fault = service.machine.fault
            assert fault.trigger is Trigger.EXTERNAL_WRENCH, fault
            assert "disturbance_observer.force_max 30 N" in fault.message, fault.message

    asyncio.run(asyncio.wait_for(scenario(), 60))
