"""sd_notify and the service watchdog, against a stand-in NOTIFY_SOCKET."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon.process.systemd import Notifier, Progress, run_watchdog


def _listener(address: str | bytes) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(address)
    sock.settimeout(5.0)
    return sock


@pytest.fixture
def path_socket(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    address = str(tmp_path / "notify")
    sock = _listener(address)
    yield sock, address
    sock.close()


def _fields(sock: socket.socket) -> list[str]:
    return sock.recv(4096).decode().split("\n")


def _drain(sock: socket.socket) -> list[str]:
    """Every datagram waiting on `sock`, without blocking."""
    out = []
    sock.setblocking(False)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        pass
    finally:
        sock.settimeout(5.0)
    return out


def test_ready_status_watchdog_stopping_reach_a_path_socket(path_socket):
    sock, address = path_socket
    notifier = Notifier({"NOTIFY_SOCKET": address})
    assert notifier.enabled
    assert notifier.ready()
    assert _fields(sock) == ["READY=1"]
    assert notifier.ready(status="IDLE, brakes on")
    assert _fields(sock) == ["READY=1", "STATUS=IDLE, brakes on"]
    assert notifier.status("TRACKING\ntrajectory 3")
    assert _fields(sock) == ["STATUS=TRACKING trajectory 3"]
    assert notifier.watchdog()
    assert _fields(sock) == ["WATCHDOG=1"]
    assert notifier.stopping()
    assert _fields(sock) == ["STOPPING=1"]
    notifier.close()
    assert not notifier.enabled and not notifier.watchdog()


def test_status_from_untrusted_text_is_one_printable_utf8_line(path_socket):
    """A brake reason arrives over zenoh: a lone surrogate (JSON "\\ud800") cannot be
    encoded, control characters would break or forge KEY=VALUE lines."""
    sock, address = path_socket
    notifier = Notifier({"NOTIFY_SOCKET": address})
    assert notifier.status("braked: BRAKE [command] stop \ud800 now\r\nREADY=1\x00\x1b[2J")
    data = sock.recv(4096)
    assert data.decode("utf-8").split("\n") == [
        "STATUS=braked: BRAKE [command] stop \ufffd now READY=1 [2J"
    ]
    notifier.close()


def test_abstract_namespace_address():
    name = f"cdprd-test-{uuid.uuid4().hex}"
    sock = _listener(b"\0" + name.encode())
    try:
        notifier = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert notifier.ready()
        assert _fields(sock) == ["READY=1"]
        notifier.close()
    finally:
        sock.close()


def test_without_notify_socket_everything_is_a_noop():
    notifier = Notifier({})
    assert not notifier.enabled
    assert not notifier.ready() and not notifier.status("x")
    assert not notifier.watchdog() and not notifier.stopping()
    assert notifier.watchdog_interval() is None
    # no socket: the watchdog task has nothing to do and returns at once
    asyncio.run(asyncio.wait_for(run_watchdog(notifier, lambda: True, interval=0.01), 5))


def test_environment_is_read_by_default(monkeypatch, path_socket):
    sock, address = path_socket
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    monkeypatch.setenv("WATCHDOG_USEC", "3000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    notifier = Notifier()
    assert notifier.ready() and _fields(sock) == ["READY=1"]
    assert notifier.watchdog_interval() == pytest.approx(1.5)


@pytest.mark.parametrize("value", ["relative/path", "@", "vsock:2:1234"])
def test_unsupported_notify_socket_is_a_clear_error(value):
    with pytest.raises(ValueError, match="NOTIFY_SOCKET"):
        Notifier({"NOTIFY_SOCKET": value})


def test_bad_field_is_rejected(path_socket):
    _, address = path_socket
    notifier = Notifier({"NOTIFY_SOCKET": address})
    with pytest.raises(ValueError, match="KEY=VALUE"):
        notifier.notify("READY")


def test_send_failure_is_logged_not_raised(tmp_path, caplog):
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    with caplog.at_level(logging.WARNING, logger="daemon.process.systemd"):
        assert notifier.watchdog() is False
    assert "sd_notify WATCHDOG failed" in caplog.text


def test_watchdog_interval_is_half_of_watchdog_usec():
    pid = str(os.getpid())
    assert Notifier({"WATCHDOG_USEC": "2000000"}).watchdog_interval() == pytest.approx(1.0)
    env = {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": pid}
    assert Notifier(env).watchdog_interval() == pytest.approx(1.0)
    other = {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid() + 1)}
    assert Notifier(other).watchdog_interval() is None
    for bad in ("abc", "0", "-5"):
        with pytest.raises(ValueError, match="WATCHDOG_USEC"):
            Notifier({"WATCHDOG_USEC": bad}).watchdog_interval()
    with pytest.raises(ValueError, match="WATCHDOG_PID"):
        Notifier({"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "x"}).watchdog_interval()


def test_progress_reports_cycles_completed_since_last_check():
    cycles = [0]
    progress = Progress(lambda: cycles[0])
    assert progress()  # grace before the first cycle
    assert not progress()
    cycles[0] += 2
    assert progress()
    assert not progress()


class _StopError(Exception):
    pass


def test_watchdog_pings_only_while_the_cycle_progresses(path_socket, caplog):
    """Fake clock: each sleep of the watchdog task is one step of a liveness script."""
    sock, address = path_socket
    notifier = Notifier(
        {"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "40000", "WATCHDOG_PID": str(os.getpid())}
    )
    script = [True, True, False, False, True, "raise", True, False]
    steps = iter(script)
    sleeps: list[float] = []
    received: list[list[str]] = []

    def alive() -> bool:
        step = next(steps)
        if step == "raise":
            raise RuntimeError("cycle state unreadable")
        return step

    async def fake_sleep(delay: float) -> None:
        sleeps.append(delay)
        received.append(_drain(sock))
        if len(sleeps) == len(script):
            raise _StopError

    logger = "daemon.process.systemd"
    with caplog.at_level(logging.WARNING, logger=logger), pytest.raises(_StopError):
        asyncio.run(run_watchdog(notifier, alive, sleep=fake_sleep))
    pinged = [batch == ["WATCHDOG=1"] for batch in received]
    assert all(batch in ([], ["WATCHDOG=1"]) for batch in received)
    assert pinged == [step is True for step in script]
    assert sleeps == [pytest.approx(0.02)] * len(script)  # half of WATCHDOG_USEC
    assert "no progress" in caplog.text and "liveness check raised" in caplog.text


def test_watchdog_cadence_in_real_time(path_socket):
    """A short real interval: the number of pings over a bounded run (generous bounds)."""
    sock, address = path_socket
    notifier = Notifier({"NOTIFY_SOCKET": address})
    pings: list[str] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        sock.setblocking(False)
        loop.add_reader(sock, lambda: pings.append(sock.recv(4096).decode()))
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(run_watchdog(notifier, lambda: True, interval=0.02), 0.5)
        await asyncio.sleep(0.05)  # let the last datagrams arrive
        loop.remove_reader(sock)

    asyncio.run(main())
    assert set(pings) == {"WATCHDOG=1"}
    assert 5 <= len(pings) <= 30  # 0.5 s / 0.02 s = 25 in an ideal world


def test_watchdog_rejects_a_non_positive_interval(path_socket):
    _, address = path_socket
    with pytest.raises(ValueError, match="interval"):
        asyncio.run(run_watchdog(Notifier({"NOTIFY_SOCKET": address}), lambda: True, interval=0))


def test_run_extends_the_start_timeout_before_a_cold_cache_compiles(path_socket, monkeypatch):
    """`cdprd run` on a cold numba cache (first start after an install or upgrade): the
    robot's kernels compile while its config loads, before the companion exists to extend
    systemd's start timeout, so the core extends it itself and says why in STATUS=; on a
    warm cache it sends nothing."""
    from daemon.cli import run_cmd
    from daemon.process import warm_up, wire

    sock, address = path_socket
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    monkeypatch.setattr(warm_up, "is_warm", lambda: False)
    run_cmd._announce_cold_cache()
    extend, status = _fields(sock)
    assert extend == f"EXTEND_TIMEOUT_USEC={int(wire.STARTING_LIMIT * 1e6)}"
    assert status.startswith("STATUS=") and "kernels may compile now" in status
    monkeypatch.setattr(warm_up, "is_warm", lambda: True)
    run_cmd._announce_cold_cache()
    assert _drain(sock) == []
