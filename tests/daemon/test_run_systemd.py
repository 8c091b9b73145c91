"""`cdprd run --sim` as its own process under a stand-in systemd: NOTIFY_SOCKET is a
datagram socket this test owns and WATCHDOG_USEC is set.  READY=1 once, only when zenoh
answers; STATUS= progress before it; WATCHDOG=1 at half of WATCHDOG_USEC; on SIGTERM
STOPPING=1, the moving robot brakes and the exit code is 0 (more SIGTERMs during the
clean-up change nothing); a restarted daemon (a second process, same config) comes up
IDLE and held, never moving."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml

from daemon.interface.client import CdprClient, RequestError
from daemon.process import wire
from tests.loopback import free_port
from tests.processes import finish, stop_impatiently
from tests.systemd_notify import NotifySocket

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/reference8"
WATCHDOG_USEC = 200_000  # the daemon pings every 0.1 s
QUAT = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}


@pytest.fixture
def notify(tmp_path: Path) -> Iterator[NotifySocket]:
    sock = NotifySocket(tmp_path / "notify")
    yield sock
    sock.close()


def _config(tmp_path: Path, port: int) -> Path:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _start(config: Path, notify: NotifySocket) -> subprocess.Popen:
    unrelated = ("WATCHDOG_PID", "JOURNAL_STREAM", "INVOCATION_ID")  # if pytest runs under systemd
    env = {k: v for k, v in os.environ.items() if k not in unrelated}
    env.update(NOTIFY_SOCKET=str(notify.path), WATCHDOG_USEC=str(WATCHDOG_USEC))
    return subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "run", "--config", str(config), "--sim"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _listening(pid: int, port: int) -> bool:
    """The daemon (its companion process, which owns zenoh) listens on `port`."""
    daemon = psutil.Process(pid)
    return any(
        c.status == psutil.CONN_LISTEN and c.laddr.port == port
        for process in (daemon, *daemon.children(recursive=True))
        for c in process.net_connections(kind="tcp")
    )


def _wait_state(client: CdprClient, state: str, timeout: float) -> None:
    end = time.monotonic() + timeout
    while (now := client.status()["state"]) != state:
        assert time.monotonic() < end, f"still {now}, never {state}"
        time.sleep(0.05)


def _ready_client(
    notify: NotifySocket, proc: subprocess.Popen, port: int, after: int = 0
) -> CdprClient:
    """Wait for READY=1 (in messages from `after` on), then at once: zenoh listens and the
    first status query answers (no retry: units started after us may query right away)."""
    try:
        notify.wait_for("READY=1", 30.0, after)
    except AssertionError:
        pytest.fail(f"no READY=1 from the daemon: {finish(proc)}")
    assert _listening(proc.pid, port), "READY=1 before zenoh listens"
    client = CdprClient(PREFIX, f"tcp/127.0.0.1:{port}", timeout=5.0)
    status = client.status()
    assert status["state"] == "idle" and status["fault"] is None, status
    assert all(d["state"] == "holding" for d in status["drives"]), status
    return client


def _trajectory(end: list[float], duration: float) -> dict:
    return {
        "waypoints": [
            {"t": 0.0, "position": [0.0, 0.0, 1.25], "quaternion": QUAT},
            {"t": duration, "position": end, "quaternion": QUAT},
        ]
    }


@pytest.mark.timeout(60)
def test_notifications_over_a_run_and_sigterm(tmp_path: Path, notify: NotifySocket) -> None:
    port = free_port()
    proc = _start(_config(tmp_path, port), notify)
    events: list[dict] = []
    try:
        with _ready_client(notify, proc, port) as client:
            subscriber = client.subscribe_events(events.append)
            client.enable()
            client.send_trajectory(_trajectory([0.1, 0.0, 1.3], 2.0))
            _wait_state(client, "tracking", 5.0)
            time.sleep(1.0)  # mid-flight
            assert client.status()["state"] == "tracking"
            sigterm_at = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            stopping = notify.wait_for("STOPPING=1", 10.0)
            stop_impatiently(proc)  # more SIGTERMs must not cut the clean-up short
            end = time.monotonic() + 2.0  # the interface publishes queued events as it closes
            while not any(e.get("event") == "brake" for e in events) and time.monotonic() < end:
                time.sleep(0.02)
            subscriber.undeclare()
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert "BRAKE [sigterm]" in out, out
    assert "Traceback" not in out and "sd_notify" not in out, out  # no failed notification
    brakes = [(e["trigger"], e["state"]) for e in events if e.get("event") == "brake"]
    assert brakes == [("sigterm", "braked")], events

    messages = notify.snapshot()
    fields = [f for _, batch in messages for f in batch]
    assert all("=" in f and f.split("=", 1)[1] for f in fields), fields
    assert fields.count("READY=1") == 1 and fields.count("STOPPING=1") == 1
    ready = notify.wait_for("READY=1", 0)
    assert ready < stopping and messages[stopping][0] >= sigterm_at
    statuses = [
        (i, field.removeprefix("STATUS="))
        for i, (_, batch) in enumerate(messages)
        for field in batch
        if field.startswith("STATUS=")
    ]
    assert any(i < ready for i, _ in statuses), "no STATUS= progress before READY=1"
    # the start-up check (numba compiling on a cold cache) gets more than TimeoutStartSec:
    # from the companion, and from the core too when the cache's warm-up marker is missing
    extend = [i for i, (_, batch) in enumerate(messages) if batch[0].startswith("EXTEND_")]
    assert 1 <= len(extend) <= 2 and extend[-1] < ready, messages
    assert all(
        messages[i][1][0] == f"EXTEND_TIMEOUT_USEC={int(wire.STARTING_LIMIT * 1e6)}"
        for i in extend
    ), messages
    assert any("idle" in text and "reference8" in text for _, text in statuses), statuses
    # STATUS= follows the safety state while running, the braking fault included
    after_ready = [text.split(";")[0] for i, text in statuses if ready <= i]
    assert after_ready[:3] == ["idle", "hold", "tracking"], statuses
    assert any(t.startswith("braked: BRAKE [sigterm]") for t in after_ready), statuses
    assert all(text.isprintable() for _, text in statuses)
    # the watchdog, fed every WATCHDOG_USEC / 2 between READY=1 and STOPPING=1 (loosely)
    pings = [t for t, batch in messages[ready:stopping] if batch == ["WATCHDOG=1"]]
    expected = (messages[stopping][0] - messages[ready][0]) / (WATCHDOG_USEC / 2e6)
    assert 0.4 * expected <= len(pings) <= 1.5 * expected + 2, (len(pings), expected)
    assert all(b == ["WATCHDOG=1"] for _, b in messages if "WATCHDOG=1" in b)


@pytest.mark.timeout(60)
def test_a_restarted_daemon_comes_up_idle_and_never_moves(
    tmp_path: Path, notify: NotifySocket
) -> None:
    port = free_port()
    config = _config(tmp_path, port)
    first = _start(config, notify)
    try:
        with _ready_client(notify, first, port) as client:
            client.enable()
            client.send_trajectory(_trajectory([-0.1, 0.05, 1.3], 3.0))
            _wait_state(client, "tracking", 5.0)
    finally:
        out = finish(first)  # stopped mid-flight
    assert first.returncode == 0 and "BRAKE [sigterm]" in out, out

    done = len(notify.snapshot())
    second = _start(config, notify)
    states: list[dict] = []
    try:
        with _ready_client(notify, second, port, after=done) as client:
            subscriber = client.subscribe_state(states.append)
            end = time.monotonic() + 10.0
            while len(states) < 25:  # half a second of published state
                assert time.monotonic() < end, "no state published"
                time.sleep(0.05)
            for refused in (
                lambda: client.goto([0.1, 0.0, 1.3]),
                lambda: client.send_trajectory(_trajectory([0.1, 0.0, 1.3], 1.0)),
                client.hold,
            ):
                with pytest.raises(RequestError) as error:
                    refused()
                assert error.value.code == "invalid_state", error.value
            time.sleep(0.2)
            subscriber.undeclare()
            assert client.status()["state"] == "idle"
    finally:
        out = finish(second)
    assert second.returncode == 0, out
    assert "BRAKE" not in out, out  # nothing moved, nothing to brake
    assert {s["state"] for s in states} == {"idle"}
    assert all(s["fault"] is None and "pose" not in s for s in states)  # no flight, no target
    lengths = np.array([s["lengths"] for s in states])
    assert np.all(np.isfinite(lengths))
    # every cable held: the plant settles by ~50 um after start-up (3 encoder counts);
    # a flight would move cables by centimetres
    assert np.ptp(lengths, axis=0).max() < 2e-4
    fields = [f for _, batch in notify.snapshot()[done:] for f in batch]
    assert fields.count("READY=1") == 1 and fields.count("STOPPING=1") == 1, fields


@pytest.mark.timeout(60)
def test_a_brake_reason_that_is_not_text_brakes_and_reaches_status_as_one_line(
    tmp_path: Path, notify: NotifySocket
) -> None:
    """A JSON "\\ud800" escape (a lone surrogate) and a line break in a brake reason:
    the brake is acknowledged, STATUS= carries the reason as one printable line."""
    port = free_port()
    proc = _start(_config(tmp_path, port), notify)
    try:
        with _ready_client(notify, proc, port) as client:
            status = client.brake("stop \ud800 now\nplease")
            assert status["state"] == "braked", status
            expected = "STATUS=braked: BRAKE [command] stop \ufffd now please; reference8"
            end = time.monotonic() + 5.0
            while not any(
                field.startswith(expected) for _, batch in notify.snapshot() for field in batch
            ):
                assert time.monotonic() < end, notify.snapshot()
                time.sleep(0.02)
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "sd_notify" not in out, out
