"""A lost bus: the daemon brakes with the bus_lost trigger, reports it
(event, state, systemd STATUS=), logs a bounded number of lines and exits with code 69
after safety.bus_lost_exit seconds, for the service manager to restart it into IDLE.
For the in-process loop bus (its link taken down), socketcand (the simulator process
killed, or its server closing the connection) and, in tests/vcan, SocketCAN.  Starting
with no bus at all fails at once with one line and the same code."""

from __future__ import annotations

import asyncio
import io
import logging
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr import Pose
from daemon.cli.simulated import InProcessSimulator
from daemon.config import DaemonConfig
from daemon.interface.client import CdprClient
from daemon.process.app import ServiceHook
from daemon.process.logsetup import configure_logging
from daemon.service.planner import LocalLink, Planner, load_checks
from daemon.service.safety import SafetyState
from daemon.service.service import EXIT_BUS_LOST, Service
from sim_bus.bus import loopbus
from tests.daemon_stack import config_for
from tests.loopback import free_port
from tests.processes import finish, patient_watchdogs, serve_simulator
from tests.systemd_notify import NotifySocket

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/reference8"
# start-up, the enable's rest check, the failures (one line each kind), the brake, that
# the drives could not confirm it (the bus is gone), the exit
MAX_LOG_LINES = 14


@pytest.fixture
def notify(tmp_path: Path) -> Iterator[NotifySocket]:
    sock = NotifySocket(tmp_path / "notify")
    yield sock
    sock.close()


@pytest.fixture
def daemon_log() -> Iterator[io.StringIO]:
    """The daemon's own logging set-up (its flood filter included), into a string."""
    root = logging.getLogger()
    level = root.level
    stream, stderr = io.StringIO(), sys.stderr
    sys.stderr = stream  # configure_logging writes to the stderr of the moment
    try:
        handler = configure_logging("info", journald=False)
    finally:
        sys.stderr = stderr
    yield stream
    root.removeHandler(handler)
    root.setLevel(level)


def _statuses(notify: NotifySocket) -> list[str]:
    return [
        field.removeprefix("STATUS=")
        for _, batch in notify.snapshot()
        for field in batch
        if field.startswith("STATUS=")
    ]


def _serve_with_simulator(
    config: DaemonConfig,
    after_start: ServiceHook,
    link_down: bool = False,
    companion: bool = False,
) -> int:
    """The daemon against an in-process simulator (its bus down from the start if
    `link_down`; with the companion process if `companion`) until `after_start` returns
    or the daemon exits; the exit code."""

    async def scenario() -> int:
        sim = InProcessSimulator(config)
        if link_down:
            loopbus.set_link(sim.daemon_bus.channel, up=False)
        return await asyncio.wait_for(sim.serve(companion=companion, after_start=after_start), 30)

    return asyncio.run(scenario())


@pytest.mark.timeout(60)
@pytest.mark.parametrize("protocol", ["cia402", "odrive"])
def test_loop_bus_link_down_brakes_reports_and_exits(
    daemon_log: io.StringIO,
    notify: NotifySocket,
    monkeypatch: pytest.MonkeyPatch,
    protocol: str,
) -> None:
    monkeypatch.setenv("NOTIFY_SOCKET", str(notify.path))
    config = config_for(protocol, zenoh={"listen": [f"tcp/127.0.0.1:{free_port()}"]})
    load_checks(config)  # the planner's compiled checks, loaded before the cycle runs
    events: list[dict] = []
    seen: dict[str, object] = {}

    async def fly_then_lose_the_bus(service: Service) -> None:
        service.subscribe(events.append)
        await service.command("enable", {})
        home = config.robot.home
        target = Pose(home.position + np.array([0.1, 0.05, 0.1]), home.quaternion)
        await Planner(config, LocalLink(service)).command("goto", {"pose": target})
        # the goto starts a command lead after it is accepted: lose the bus in flight
        for _ in range(200):
            if service.machine.state is not SafetyState.HOLD:
                break
            await asyncio.sleep(0.005)
        seen["before"] = service.machine.state
        loopbus.set_link(service.port.bus.channel, up=False)
        await service.wait_stopped()
        seen["after"] = service.status()

    code = _serve_with_simulator(config, fly_then_lose_the_bus, companion=True)
    lines = daemon_log.getvalue().splitlines()
    assert seen["before"] is SafetyState.TRACKING, seen
    assert code == EXIT_BUS_LOST, lines
    after = seen["after"]
    assert after["state"] == "braked" and after["fault"]["trigger"] == "bus_lost", after
    assert "network is down" in after["fault"]["message"]
    brakes = [e for e in events if e.get("event") == "brake"]
    assert brakes and brakes[-1]["trigger"] == "bus_lost", events
    assert any(s.startswith("braked: BRAKE [bus_lost] CAN bus lost:") for s in _statuses(notify))
    assert len(lines) <= MAX_LOG_LINES, "\n".join(lines)
    assert any("exiting with code 69" in line for line in lines), lines
    assert not any("Traceback" in line for line in lines), lines


@pytest.mark.timeout(60)
@pytest.mark.parametrize("protocol", ["cia402", "odrive"])
def test_a_bus_down_at_start_up_is_lost_at_once(daemon_log: io.StringIO, protocol: str) -> None:
    """The drives' start-up stops at the first answer it would wait for: the fault is the
    lost bus, not a start-up timeout after seconds of waiting."""
    config = config_for(protocol)
    seen: dict[str, object] = {}

    async def look(service: Service) -> None:
        seen["status"] = service.status()
        seen["cycles"] = service.stats.cycles  # how long the start-up took, in cycles
        await service.wait_stopped()

    code = _serve_with_simulator(config, look, link_down=True)
    log = daemon_log.getvalue()
    assert code == EXIT_BUS_LOST, log
    fault = seen["status"]["fault"]  # type: ignore[index]
    assert fault["trigger"] == "bus_lost" and "network is down" in fault["message"], fault
    assert seen["cycles"] < config.controller.rate_hz * 1.0, seen  # not a second
    assert "BRAKE [bus_lost]" in log and "BRAKE [startup]" not in log, log
    assert len(log.splitlines()) <= MAX_LOG_LINES, log


# ---- socketcand, the daemon and the simulator as separate processes -----------------
def _config_file(tmp_path: Path, zenoh_port: int, can_section: dict) -> Path:
    """The example config on `can_section`; a late cycle on a loaded test machine (two
    processes over TCP) is not what these tests are about: more slack before the stale
    feedback and drive watchdog brakes."""
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{zenoh_port}"]
    data["can"] = can_section
    data["safety"]["stale_cycles"] = 25
    patient_watchdogs(data, 0.25)
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _daemon(config: Path, notify: NotifySocket | None = None) -> subprocess.Popen:
    unrelated = ("WATCHDOG_PID", "WATCHDOG_USEC", "JOURNAL_STREAM", "INVOCATION_ID")
    env = {k: v for k, v in os.environ.items() if k not in unrelated}
    if notify is not None:
        env["NOTIFY_SOCKET"] = str(notify.path)
    return subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "run", "--config", str(config)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _simulator() -> tuple[subprocess.Popen, dict]:
    """`python -m sim_bus` serving its bus over socketcand; (process, can section)."""
    proc, port, channel = serve_simulator(CONFIG)
    options = {"host": "127.0.0.1", "port": port}
    return proc, {"interface": "socketcand", "channel": channel, "options": options}


@pytest.mark.timeout(90)
@pytest.mark.parametrize("end", ["killed", "closed"])
def test_socketcand_peer_gone_brakes_reports_and_exits(
    tmp_path: Path, notify: NotifySocket, end: str
) -> None:
    """The simulator process killed (its socket reset) or stopped (its server closes
    the connection) while the daemon tracks."""
    sim, can_section = _simulator()
    port = free_port()
    daemon = _daemon(_config_file(tmp_path, port, can_section), notify)
    events: list[dict] = []
    try:
        notify.wait_for("READY=1", 30.0)
        with CdprClient(PREFIX, f"tcp/127.0.0.1:{port}", timeout=5.0) as client:
            subscriber = client.subscribe_events(events.append)
            client.enable()
            client.goto([0.1, 0.05, 1.35])
            # the goto's reference takes over a planning lead after the reply
            deadline = time.monotonic() + 2.0
            while client.status()["state"] != "tracking":
                assert time.monotonic() < deadline, "the goto never started tracking"
                time.sleep(0.01)
            sim.send_signal(signal.SIGKILL if end == "killed" else signal.SIGTERM)
            daemon.wait(30)  # exits by itself, within bus_lost_exit (+ shutting down)
            subscriber.undeclare()
    finally:
        sim.kill()
        sim.wait(10)
        out = finish(daemon)
    assert daemon.returncode == EXIT_BUS_LOST, out
    lines = out.splitlines()
    assert len(lines) <= MAX_LOG_LINES, out
    assert "Traceback" not in out, out
    assert re.search(r"BRAKE \[bus_lost\] CAN bus lost: \w+ failed: ", out), out
    assert "exiting with code 69" in out, out
    assert "brake not confirmed: drive 0: node 1: no answer" in out, out
    brakes = [e for e in events if e.get("event") == "brake"]
    assert brakes and brakes[-1]["trigger"] == "bus_lost", events
    assert any(s.startswith("braked: BRAKE [bus_lost] CAN bus lost:") for s in _statuses(notify))
    assert "STOPPING=1" in [f for _, batch in notify.snapshot() for f in batch]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("bus", ["socketcand", "socketcan"])
def test_no_bus_at_start_is_one_line_and_exit_69(tmp_path: Path, bus: str) -> None:
    """No socketcand server at the address (python-can retried for 10 s in a busy loop,
    444,621 warning lines), or no such SocketCAN interface."""
    port = free_port()  # nothing listens there
    if bus == "socketcand":
        section = {"interface": bus, "channel": "can0", "options": {"host": "127.0.0.1"}}
        section["options"]["port"] = port
        named = f"no socketcand server answers at 127.0.0.1:{port}"
    else:
        section = {"interface": bus, "channel": "nosuchcan0"}
        named = "channel=nosuchcan0"
    daemon = _daemon(_config_file(tmp_path, free_port(), section))
    out = finish(daemon, terminate=False, timeout=40)
    assert daemon.returncode == EXIT_BUS_LOST, out[-2000:]
    assert out.splitlines() == [out.strip()] and "can: cannot open the bus" in out
    assert named in out, out
