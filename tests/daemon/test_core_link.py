"""The planner driving the service through the real link, in one process: the core's
end (CompanionHost) and the companion's (RemoteLink) on a socket pair, the curve ring
mapped twice; what the companion process does, minus zenoh."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import can
import numpy as np
import pytest

from cdpr import Pose
from daemon.process import wire
from daemon.process.companion_host import MAX_BATCH, CompanionHost
from daemon.process.companion_link import OtherCodeError, RemoteLink, greeted
from daemon.process.curve_ring import CurveRing
from daemon.service.api import CommandError
from daemon.service.planner import Planner
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(60)


@asynccontextmanager
async def linked(
    ring_bytes: int | None = None,
) -> AsyncIterator[tuple[Stack, CompanionHost, Planner, RemoteLink]]:
    async with Stack(config_for("cia402")) as stack:
        host = CompanionHost(stack.service, stack.config)
        if ring_bytes is not None:
            host.ring = CurveRing.create(ring_bytes)
        core_end, companion_end = wire.socket_pair()
        host.connect(core_end)
        config, _level, link = await asyncio.to_thread(greeted, companion_end, host.ring.fd, 5.0)
        link.start()
        try:
            yield stack, host, Planner(config, link), link
        finally:
            link.close()
            await host.close()


def test_a_companion_of_other_code_refuses_the_hello_before_reading_it() -> None:
    """The core's code fingerprint comes first, in builtins any version reads: a
    different one is refused naming both, and what follows (a hello this code might not
    unpickle: here, bytes that are no pickle) is never read."""
    core_end, companion_end = wire.socket_pair()
    with core_end, companion_end:
        assert wire.send(core_end, ("code", "0" * 24))
        core_end.send(b"not a pickle")
        named = rf"code \({wire.code_fingerprint()}\) is not the core's \(0{{24}}\)"
        with pytest.raises(OtherCodeError, match=named):
            greeted(companion_end, -1, 1.0)


def _target(stack: Stack, dx: float) -> Pose:
    home = stack.config.robot.home
    return Pose(home.position + np.array([dx, 0.0, 0.0]), home.quaternion)


async def _until(condition, timeout: float) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met"
        await asyncio.sleep(0.01)


def test_gotos_through_the_link_fly_and_hand_their_ring_ranges_back() -> None:
    async def scenario() -> None:
        async with linked() as (stack, host, planner, link):
            status = await planner.command("enable", {})
            assert status["state"] == "hold"
            for dx in (0.05, -0.05):
                reply = await planner.command("goto", {"pose": _target(stack, dx)})
                assert reply["accepted"] and reply["what"] == "goto", reply
                await _until(lambda: link.safety_state == "hold", 10.0)
            await asyncio.sleep(0.3)
            position = stack.plant.pose.position
            assert np.linalg.norm(position - _target(stack, -0.05).position) < 2e-3
            # the first goto's curve was dropped when the second took over: only the
            # second's range is still in use, on both sides
            await _until(lambda: len(host._in_ring) == 1, 2.0)
            (in_use,) = host._in_ring.values()
            await _until(lambda: link._ring.free_bytes >= link._ring.size - in_use - 64, 2.0)
            assert link._ring.free_bytes <= link._ring.size - in_use
            assert stack.service.machine.fault is None

    asyncio.run(scenario())


def test_a_trajectory_larger_than_the_free_ring_is_refused_busy_and_nothing_moves() -> None:
    async def scenario() -> None:
        # a goto's curve takes 912 bytes
        async with linked(ring_bytes=512) as (stack, _host, planner, link):
            await planner.command("enable", {})
            before = stack.plant.pose.position.copy()
            with pytest.raises(CommandError) as refused:
                await planner.command("goto", {"pose": _target(stack, 0.05)})
            assert refused.value.code == "busy" and "trajectory ring" in refused.value.reason
            assert link.safety_state == "hold"
            await asyncio.sleep(0.2)
            assert np.linalg.norm(stack.plant.pose.position - before) < 1e-3

    asyncio.run(scenario())


def test_core_refusals_reach_the_planner_with_their_code() -> None:
    async def scenario() -> None:
        async with linked() as (stack, _host, planner, _link):
            with pytest.raises(CommandError) as refused:
                await planner.command("reset", {})
            assert refused.value.code == "invalid_state" and "while idle" in refused.value.reason
            with pytest.raises(CommandError) as refused:
                await planner.command("goto", {"pose": _target(stack, 0.05)})
            assert refused.value.code == "invalid_state"

    asyncio.run(scenario())


def test_a_held_up_batch_of_can_frames_reaches_the_companion_whole() -> None:
    """Between two hand-overs the core holds MAX_BATCH cycles' records; the CAN frames
    of as many cycles (a SYNC and 3 PDOs per drive: 25 frames a cycle with 8 drives)
    must fit beside them and reach the companion whole, in datagrams within the size
    limit.  The core used to hold 16 x MAX_BATCH frames: 128 such cycles, so a hand-over
    held up 130 cycles lost the last frames of a recording whose cycles were all kept."""

    async def scenario() -> None:
        config = config_for("cia402", recording={"can_log": "bus.log"})
        async with Stack(config) as stack:
            host = CompanionHost(stack.service, stack.config)
            core_end, companion_end = wire.socket_pair()
            host.connect(core_end)
            cycles, per_cycle = MAX_BATCH - 1, 1 + 3 * stack.service.n
            frames = [
                can.Message(arbitration_id=0x180 + k % 8, data=bytes(8), is_extended_id=False)
                for k in range(per_cycle)
            ]
            for _ in range(cycles):
                for frame in frames:
                    host._record_frame(frame, True)
            host._flush_batches()
            got, _ = wire.receive(companion_end, 1000)
            batches = [m[1] for m in got if m[0] == "frames"]
            assert sum(map(len, batches)) == cycles * per_cycle
            assert len(batches) > 1 and host.dropped == host.unrecorded == 0
            companion_end.close()
            host._disconnect()

    asyncio.run(scenario())


@pytest.mark.parametrize("says_starting", [True, False])
def test_a_companion_compiling_its_start_up_check_is_waited_for(
    monkeypatch: pytest.MonkeyPatch, says_starting: bool
) -> None:
    """A companion that said ("starting",) compiles its workspace check, minutes on a cold
    numba cache on a small computer: the core waits for its "ready" up to
    wire.STARTING_LIMIT, silent meanwhile; one that says nothing is given up on after
    START_TIMEOUT (the daemon then exits 1)."""
    start_timeout = 1.0
    monkeypatch.setattr("daemon.process.companion_host.START_TIMEOUT", start_timeout)

    async def scenario() -> int | None:
        async with Stack(config_for("cia402")) as stack:
            host = CompanionHost(stack.service, stack.config)
            core_end, companion_end = wire.socket_pair()
            host.connect(core_end)
            with companion_end:
                await asyncio.to_thread(greeted, companion_end, host.ring.fd, 5.0)
                if says_starting:
                    assert wire.send(companion_end, ("starting",))
                waiting = asyncio.create_task(host.wait_ready())
                await asyncio.sleep(3 * start_timeout)  # silent: compiling
                if waiting.done():
                    await host.close()
                    return waiting.result()
                assert wire.send(companion_end, ("ready",))
                result = await asyncio.wait_for(waiting, 10.0)
                await host.close()
                return result

    assert asyncio.run(scenario()) == (None if says_starting else 1)
