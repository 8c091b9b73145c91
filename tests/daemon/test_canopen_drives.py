"""The daemon with eight drives our code did not write (issue 15): canopen LocalNode
slaves with a vendor-style EDS and default mapping (tests/canopen_drive.py).  In this
process (the service on a python-can virtual bus) and as separate processes (`cdprd run`
over socketcand to tests/canopen_drives_process.py), the daemon configures them at
start-up, enables them into a hold and keeps them under torque; a stop (SIGTERM) leaves
them holding in position; a daemon that vanishes (kill -9: no frame, no heartbeat any
more) leaves each of them holding in QUICK STOP ACTIVE by the consumer heartbeat
reaction the host configured (0x1016 on the host's heartbeat, 0x6007 = 3, 0x605A = 6).
The slaves have no physics: their positions stay put, so no trajectory is flown."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import can
import canopen
import pytest
import yaml

from daemon.config import DaemonConfig, load_config
from daemon.service.safety import SafetyState
from daemon.service.service import Service
from tests.canopen_drive import ENABLED, QUICK_STOP, VENDOR_EDS, drives_for
from tests.daemon_stack import DRIVER_CONFIGS
from tests.loopback import free_port
from tests.processes import (
    ROOT,
    connect,
    daemon_config,
    finish,
    simulator_configs,
    start_daemon,
    wait_status,
)

pytestmark = pytest.mark.timeout(90)
CHANNELS = itertools.count()
CONSUMER = 0.5  # s: the drives' consumer heartbeat time (heartbeat_timeout)


RATE_HZ = 100  # canopen answers each SYNC from one thread
DRIVES = {  # the drives: the vendor EDS, its rated torque 0x6076 = 1000 mN·m
    "rated_torque": 1.0,
    "watchdog_timeout": 0.2,
    "heartbeat_timeout": CONSUMER,
    "profile": {"eds": str(VENDOR_EDS)},
}


def canopen_config(channel: str) -> DaemonConfig:
    def edit(data: dict) -> None:
        data["can"] = {"interface": "virtual", "channel": channel}
        data["controller"]["rate_hz"] = RATE_HZ
        data["drives"].update(DRIVES)
        data["safety"]["stale_cycles"] = 10

    return load_config(DRIVER_CONFIGS["cia402"], edit)


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
    drives = drives_for(config, network)
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


# -- as separate processes: `cdprd run` and the drives over socketcand --------------------


def _drives_process(config: Path) -> tuple[subprocess.Popen, int]:
    """tests/canopen_drives_process.py for `config`: (process, its socketcand port)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.canopen_drives_process", "--config", str(config)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    line = proc.stdout.readline()
    if not line.startswith("PORT "):
        proc.kill()
        raise AssertionError(f"the drives process announced no port: {line!r}")
    return proc, int(line.split()[1])


def _status(proc: subprocess.Popen) -> list[dict]:
    proc.stdin.write("status\n")
    proc.stdin.flush()
    return json.loads(proc.stdout.readline())


def _wait_drives(proc: subprocess.Popen, condition, what: str, polls: int = 200) -> list[dict]:
    for _ in range(polls):  # 50 ms apart
        drives = _status(proc)
        if condition(drives):
            return drives
        time.sleep(0.05)
    raise AssertionError(f"never {what}: {drives}")


@pytest.mark.timeout(120)
@pytest.mark.parametrize("end", ["sigterm", "kill"])
def test_cdprd_run_brings_up_canopen_drives_in_another_process(tmp_path: Path, end: str) -> None:
    zenoh_port = free_port()
    _, data = simulator_configs(tmp_path, zenoh_port)
    # three processes and TCP relays on a busy host: a patient consumer heartbeat
    data["drives"].update(DRIVES, heartbeat_timeout=1.0)
    data["controller"]["rate_hz"] = RATE_HZ
    (tmp_path / "drives.yaml").write_text(yaml.safe_dump(data))
    drives, port = _drives_process(tmp_path / "drives.yaml")
    daemon = None
    try:
        config = daemon_config(tmp_path, data, port, "vcan0")
        daemon = start_daemon(config)
        with connect(zenoh_port, daemon) as client:
            wait_status(client, "idle", 20.0)
            client.enable()
            wait_status(client, "hold", 5.0)
        held = _wait_drives(
            drives,
            lambda ds: all(d["statusword"] == ENABLED and any(d["torques"]) for d in ds),
            "every drive enabled under torque",
        )
        assert all(d["mode"] == 10 for d in held)
        if end == "sigterm":
            out = finish(daemon)
            assert daemon.returncode == 0, out
            after = _wait_drives(
                drives, lambda ds: all(d["mode"] == 8 for d in ds), "every drive in mode 8"
            )
            assert all(d["statusword"] == ENABLED for d in after), after
            assert all(d["target"] == d["position"] for d in after), after
        else:
            daemon.kill()
            daemon.wait(10)
            _wait_drives(
                drives,
                lambda ds: all(d["statusword"] == QUICK_STOP for d in ds),
                "every drive in QUICK STOP ACTIVE",
            )
    finally:
        if daemon is not None and daemon.poll() is None:
            finish(daemon)
        drives.stdin.close()
        drives.wait(10)
