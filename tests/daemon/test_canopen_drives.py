"""The daemon's service with eight drives our code did not write (issue 15): canopen
LocalNode slaves with a vendor-style EDS and default mapping (tests/canopen_drive.py)
on a python-can virtual bus in this process.  The service configures them at start-up,
enables them into a hold and keeps them under torque; a stop leaves them holding in
position; a daemon that vanishes from the bus (kill -9: no frame, no heartbeat any more)
leaves each of them holding by the consumer heartbeat reaction the host configured
(0x1016 on the host's heartbeat, 0x6007 = 3, 0x605A = 6).  The slaves have no
physics: their positions stay put."""

from __future__ import annotations

import asyncio
import itertools
import os
import time

import can
import canopen
import pytest

from cdpr.controller import static_tensions, tension_solver
from daemon.config import DaemonConfig, load_config
from daemon.service.safety import SafetyState
from daemon.service.service import Service
from tests.canopen_drive import ENABLED, QUICK_STOP, VENDOR_EDS, CanopenDrive
from tests.daemon_stack import DRIVER_CONFIGS

pytestmark = pytest.mark.timeout(90)
CHANNELS = itertools.count()
CONSUMER = 0.5  # s: the drives' consumer heartbeat time (heartbeat_timeout)


def canopen_config(channel: str) -> DaemonConfig:
    def edit(data: dict) -> None:
        data["can"] = {"interface": "virtual", "channel": channel}
        data["controller"]["rate_hz"] = 100  # canopen answers each SYNC from one thread
        data["drives"].update(
            rated_torque=1.0,  # 0x6076 = 1000 mN·m in the vendor EDS
            watchdog_timeout=0.2,
            heartbeat_timeout=CONSUMER,
            profile={"eds": str(VENDOR_EDS)},
        )
        data["safety"]["stale_cycles"] = 10

    return load_config(DRIVER_CONFIGS["cia402"], edit)


def _slaves(config: DaemonConfig, network: canopen.Network) -> list[CanopenDrive]:
    """One drive per cable, at the position of the cable its drum paid out with the
    platform resting at home (elastic cables stretch under the holding tensions)."""
    robot = config.robot
    tensions = static_tensions(robot, tension_solver(robot, config.controller), robot.home)
    lengths = robot.drum_lengths(robot.cable_lengths(robot.home), tensions)
    scalings = config.drives.scalings_for(robot)
    return [
        CanopenDrive(network, node, round(s.position(length)))
        for node, s, length in zip(config.drives.nodes, scalings, lengths, strict=True)
    ]


async def _until(condition, what: str, seconds: float) -> None:
    """Poll `condition` every 5 ms, at most `seconds` (a bound, not a measurement)."""
    for _ in range(round(seconds / 0.005)):
        if condition():
            return
        await asyncio.sleep(0.005)
    raise AssertionError(f"not within {seconds} s: {what}")


@pytest.mark.parametrize("end", ["stop", "vanish"])
def test_eight_canopen_drives_come_up_enable_hold_and_end_holding(end: str) -> None:
    channel = f"cdprd-canopen-{os.getpid()}-{next(CHANNELS)}"
    config = canopen_config(channel)
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    drives = _slaves(config, network)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

    async def scenario() -> None:
        service = Service(config, bus)
        service.driver.sdo_timeout = 2.0  # canopen answers from its one thread, maybe late
        try:
            await service.start()
            assert service.machine.state is SafetyState.IDLE, service.machine.fault
            for drive in drives:
                assert drive.node.nmt.state == "OPERATIONAL"
                assert [v.index for v in drive.node.tpdo[1].map] == [0x6041, 0x6064, 0x6061]
            await service.command("enable", {})
            assert service.machine.state is SafetyState.HOLD, service.machine.fault
            cycles = service.stats.cycles
            await _until(lambda: service.stats.cycles > cycles + 50, "50 cycles in HOLD", 30)
            assert service.machine.state is SafetyState.HOLD, service.machine.fault
            assert all(d.value(0x6041) == ENABLED and d.value(0x6061) == 10 for d in drives)
            assert all(any(t != 0 for t in d.torques) for d in drives), "torque commanded"
            if end == "stop":
                service.stop()
                await _until(lambda: all(d.value(0x6061) == 8 for d in drives), "hold in mode 8", 5)
                assert all(d.value(0x6041) == ENABLED for d in drives)
                assert all(d.value(0x607A) == d.value(0x6064) for d in drives)
                return
            bus.shutdown()  # the daemon is gone: no frame, no heartbeat from now on

            def all_holding() -> bool:
                now = time.monotonic()
                for drive in drives:
                    drive.check_heartbeat(now)
                return all(d.value(0x6041) == QUICK_STOP for d in drives)

            await _until(all_holding, "every drive in QUICK STOP ACTIVE", 10)
            # each reacted by the consumer time the host set (no wall-clock bound here:
            # a drive reacts CONSUMER after the last heartbeat it heard)
            for drive in drives:
                assert drive.value(0x1016, 1) == 127 << 16 | round(CONSUMER * 1000)
                assert drive.heard is not None and drive.lost - drive.heard >= CONSUMER
        finally:
            service.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 80))
    finally:
        bus.shutdown()
        network.disconnect()
