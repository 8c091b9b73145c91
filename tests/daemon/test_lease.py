"""Leases on the payload freeze and the observer hold (daemon.service.lease), in-process:
a lapsed lease lets go (state, event, warning), renewals keep the hold, a hold without a
lease stays until released, and a bad lease is refused naming the key."""

from __future__ import annotations

import asyncio
import logging
import math

import pytest

from daemon.interface.messages import decode_command
from daemon.service.api import CommandError
from daemon.service.safety import SafetyState
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(90)


def _lapses(events: list[dict]) -> list[dict]:
    return [e for e in events if e["event"] == "lease_lapsed"]


async def _enabled(stack: Stack) -> list[dict]:
    """Enable the stack's robot; the list its planner's events go to."""
    events: list[dict] = []
    stack.planner.subscribe(events.append)
    await stack.enable()
    return events


def test_a_lapsed_lease_lets_go_of_the_payload_and_the_observer(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Frozen and held on a 0.3 s lease nobody renews: the state counts the lease down,
    then the daemon unfreezes the estimate and lets the observer back in, warns, and emits
    one `lease_lapsed` per lease naming it; the robot keeps holding."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            planner, controller = stack.planner, stack.service.controller
            events = await _enabled(stack)
            await planner.command("payload", {"frozen": True, "lease": 0.3})
            await planner.command("observer", {"held": True, "lease": 0.3})
            state = planner.state()
            assert state["payload"]["frozen"] is True and state["observer_held"] is True
            assert all(0.0 < state["leases"][name] <= 0.3 for name in ("payload", "observer"))
            await stack.until(lambda: len(_lapses(events)) == 2, 10.0)
            assert controller.payload.frozen is False and controller.observer_held is False
            state = planner.state()
            assert state["payload"]["frozen"] is False and state["observer_held"] is False
            assert state["leases"] == {"payload": None, "observer": None}
            lapsed = {e["what"]: e for e in _lapses(events)}
            assert lapsed["payload"]["lease"] == 0.3 and lapsed["observer"]["lease"] == 0.3
            assert lapsed["payload"]["result"]["frozen"] is False
            assert lapsed["observer"]["result"]["held"] is False
            assert all(e["state"] == "hold" and "t" in e for e in lapsed.values())
            assert stack.service.machine.state is SafetyState.HOLD

    with caplog.at_level(logging.WARNING, logger="cdprd"):
        asyncio.run(asyncio.wait_for(scenario(), 60))
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("payload estimate's freeze lapsed" in m for m in warned), warned
    assert any("external wrench observer's hold lapsed" in m for m in warned), warned


def test_renewals_keep_the_hold_and_a_hold_without_a_lease_stays() -> None:
    """30 renewals of a 1 s lease, 0.1 s apart (3 s in all): held after every one, no
    lapse.  Then a hold without a lease ends the lease: still held well past it, until
    released."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            planner, controller = stack.planner, stack.service.controller
            events = await _enabled(stack)
            for renewals in range(1, 31):
                await planner.command("payload", {"frozen": True, "lease": 1.0})
                await planner.command("observer", {"held": True, "lease": 1.0})
                await asyncio.sleep(0.1)
                assert controller.payload.frozen and controller.observer_held, renewals
                assert _lapses(events) == [], renewals
            await planner.command("payload", {"frozen": True})
            await planner.command("observer", {"held": True})
            assert planner.state()["leases"] == {"payload": None, "observer": None}
            await asyncio.sleep(1.5)
            assert controller.payload.frozen and controller.observer_held
            assert _lapses(events) == []
            await planner.command("payload", {"frozen": False})
            await planner.command("observer", {"held": False})
            assert not controller.payload.frozen and not controller.observer_held

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_every_status_reply_carries_the_leases_as_the_status_does() -> None:
    """`hold`, `disable`, `brake`, `reset` and `enable` reply with the status: the
    leases' time left included, as `status` has it."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            planner = stack.planner
            await _enabled(stack)
            await planner.command("observer", {"held": True, "lease": 30.0})
            replies = [await planner.command("hold", {})]
            replies.append(await planner.command("disable", {}))
            replies.append(await planner.command("brake", {}))
            replies.append(await planner.command("reset", {}))
            replies.append(await planner.command("enable", {}))
            status = await planner.command("status", {})
            left = [reply["leases"]["observer"] for reply in replies]
            for reply in replies:
                assert reply.keys() == status.keys()
                assert reply["leases"]["payload"] is None
            assert 0.0 < status["leases"]["observer"] <= min(left) <= max(left) <= 30.0
            assert left == sorted(left, reverse=True)

    asyncio.run(asyncio.wait_for(scenario(), 60))


@pytest.mark.parametrize(
    ("name", "body", "message"),
    [
        ("payload", {"frozen": True, "lease": 0}, "payload.lease: 0 s: must be more than 0"),
        ("payload", {"frozen": True, "lease": -2.5}, "payload.lease: -2.5 s: must be more"),
        ("payload", {"frozen": True, "lease": 61}, "payload.lease: 61 s: at most 60"),
        ("payload", {"frozen": True, "lease": math.inf}, "payload.lease: expected a number"),
        ("payload", {"frozen": True, "lease": math.nan}, "payload.lease: expected a number"),
        ("payload", {"frozen": True, "lease": "5"}, "payload.lease: expected a number"),
        ("observer", {"held": True, "lease": True}, "observer.lease: expected a number"),
        ("observer", {"held": True, "lease": 1e9}, "observer.lease: 1000000000.0 s: at most"),
        ("payload", {"frozen": False, "lease": 5}, "payload.lease: only with frozen: true"),
        ("payload", {"lease": 5}, "payload.lease: only with frozen: true"),
        ("observer", {"held": False, "lease": 5}, "observer.lease: only with held: true"),
    ],
)
def test_a_bad_lease_is_refused_naming_the_problem(name: str, body: dict, message: str) -> None:
    with pytest.raises(CommandError) as refused:
        decode_command(name, body)
    assert refused.value.code == "bad_request" and message in refused.value.reason
    assert refused.value.details["field"] == "lease"


def test_a_lease_is_taken_in_seconds() -> None:
    assert decode_command("observer", {"held": True, "lease": 5}) == {"held": True, "lease": 5.0}
    assert decode_command("payload", {"frozen": True, "lease": 60}) == {
        "frozen": True,
        "lease": 60.0,
    }
