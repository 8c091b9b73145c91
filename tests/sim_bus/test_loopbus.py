"""LoopBus: the pollable in-process bus (sim_bus.bus.loopbus)."""

from __future__ import annotations

import asyncio
import errno
import os
import select
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import can
import pytest

from sim_bus.bus import loopbus
from sim_bus.bus.loopbus import LoopBus

ROOT = Path(__file__).resolve().parents[2]


def readable(bus: LoopBus) -> bool:
    return bool(select.select([bus.fileno()], [], [], 0)[0])


def frame(i: int) -> can.Message:
    return can.Message(arbitration_id=0x100 + i % 0x100, data=i.to_bytes(4, "little"))


@pytest.fixture
def pair(request: pytest.FixtureRequest):
    a = LoopBus(request.node.name)
    b = LoopBus(request.node.name)
    yield a, b
    a.shutdown()
    b.shutdown()


def test_frames_reach_the_other_buses_not_the_sender(pair) -> None:
    a, b = pair
    msg = frame(1)
    a.send(msg)
    assert b.recv(0) is msg  # the same object: no copy per send
    assert a.recv(0) is None
    assert msg.channel == a.channel
    assert msg.timestamp > 0


def test_receive_own_messages() -> None:
    with LoopBus("own", receive_own_messages=True) as a, LoopBus("own") as b:
        a.send(frame(1))
        assert a.recv(0) is not None
        assert b.recv(0) is not None


def test_channels_are_separate() -> None:
    with LoopBus("left") as a, LoopBus("right") as b:
        a.send(frame(1))
        assert b.recv(0) is None


def test_send_stamps_wall_clock_time(pair) -> None:
    import time

    a, b = pair
    before = time.time()
    a.send(frame(1))
    assert before <= b.recv(0).timestamp <= time.time()


def test_fileno_is_readable_exactly_while_frames_are_queued(pair) -> None:
    a, b = pair
    assert not readable(b)
    a.send(frame(1))
    a.send(frame(2))
    assert readable(b)
    assert b.recv(0).arbitration_id == 0x101
    assert readable(b)  # one still queued
    assert b.recv(0).arbitration_id == 0x102
    assert not readable(b)
    a.send(frame(3))
    assert readable(b)
    assert [m.arbitration_id for m in b.drain()] == [0x103]
    assert not readable(b)
    assert b.drain() == []
    assert b.recv(0) is None


def test_drain_returns_all_queued_frames_in_order(pair) -> None:
    a, b = pair
    for i in range(20):
        a.send(frame(i))
    assert b.pending == 20
    assert [int.from_bytes(m.data, "little") for m in b.drain()] == list(range(20))
    assert b.pending == 0


def test_recv_with_timeout_waits_for_a_frame_from_another_thread(pair) -> None:
    a, b = pair
    timer = threading.Timer(0.05, lambda: a.send(frame(7)))
    timer.start()
    try:
        msg = b.recv(timeout=5)
    finally:
        timer.join()
    assert msg is not None and msg.arbitration_id == 0x107
    assert b.recv(timeout=0.01) is None


def test_full_queue_drops_the_oldest_and_counts() -> None:
    with LoopBus("small") as a, LoopBus("small", rx_queue_size=4) as b:
        for i in range(10):
            a.send(frame(i))
        assert b.dropped == 6
        assert [int.from_bytes(m.data, "little") for m in b.drain()] == [6, 7, 8, 9]
        assert not readable(b)
        assert a.dropped == 0


def test_filters_apply_to_recv_and_drain() -> None:
    filters = [{"can_id": 0x105, "can_mask": 0x7FF}]
    with LoopBus("filt") as a, LoopBus("filt", can_filters=filters) as b:
        for i in range(10):
            a.send(frame(i))
        assert [m.arbitration_id for m in b.drain()] == [0x105]
        for i in range(10):
            a.send(frame(i))
        assert b.recv(0).arbitration_id == 0x105
        assert b.recv(0) is None


def test_state_and_bitrate() -> None:
    with LoopBus("state", bitrate=1_000_000) as a, LoopBus("state") as b:
        assert a.bitrate == 1_000_000
        assert a.state is can.BusState.ACTIVE
        a.state = can.BusState.ERROR  # bus-off: a controller does not transmit
        with pytest.raises(can.CanOperationError, match="ERROR"):
            a.send(frame(1))
        a.state = can.BusState.PASSIVE  # listen-only
        with pytest.raises(can.CanOperationError, match="PASSIVE"):
            a.send(frame(1))
        b.send(frame(2))
        assert a.recv(0) is not None  # receiving still works
        a.state = can.BusState.ACTIVE
        a.send(frame(3))
        assert b.recv(0) is not None


@pytest.mark.parametrize(
    ("kwargs", "problem"),
    [
        ({"channel": ""}, "channel"),
        ({"channel": 3}, "channel"),
        ({"rx_queue_size": 0}, "rx_queue_size"),
        ({"bitrate": -1}, "bitrate"),
    ],
)
def test_bad_arguments_are_named(kwargs: dict, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        LoopBus(**kwargs)


def test_shutdown_leaves_the_channel() -> None:
    a = LoopBus("gone")
    b = LoopBus("gone")
    fd = b.fileno()
    b.shutdown()
    b.shutdown()  # idempotent
    a.send(frame(1))  # delivered to nobody, no error
    with pytest.raises(can.CanOperationError, match="shut down") as error:
        b.send(frame(1))
    assert error.value.error_code == errno.EBADF  # like a closed socket
    with pytest.raises(can.CanOperationError, match="shut down"):
        b.fileno()
    with pytest.raises(OSError):
        os.fstat(fd)  # the eventfd is closed
    a.shutdown()
    assert "gone" not in loopbus._channels


def test_a_channel_taken_down_fails_like_a_socketcan_interface() -> None:
    """`ip link set DEV down`: sends fail with ENETDOWN; each bus reports ENETDOWN once,
    after the frames it had queued, and its fd is readable until it has; up again, the
    channel carries frames as before."""
    with LoopBus("link") as a, LoopBus("link") as b, LoopBus("link") as c:
        a.send(frame(1))
        loopbus.set_link("link", up=False)
        for bus in (a, b, c):
            with pytest.raises(can.CanOperationError, match="network is down") as error:
                bus.send(frame(2))
            assert error.value.error_code == errno.ENETDOWN
        assert readable(a) and readable(b)
        assert [m.data for m in b.drain()] == [frame(1).data]  # queued before: delivered
        assert readable(b)
        with pytest.raises(can.CanOperationError, match="network is down") as error:
            b.drain()
        assert error.value.error_code == errno.ENETDOWN
        assert not readable(b) and b.drain() == []  # reported once
        assert c.recv(0).data == frame(1).data
        with pytest.raises(can.CanOperationError, match="network is down"):
            c.recv(0)
        assert c.recv(0) is None
        loopbus.set_link("link", up=True)
        with pytest.raises(can.CanOperationError, match="network is down"):
            a.recv(0)  # still reported once, after coming back up
        a.send(frame(3))
        assert b.recv(0).data == frame(3).data and c.recv(0).data == frame(3).data
        assert not readable(a) and not readable(b) and not readable(c)
    with pytest.raises(ValueError, match="no LoopBus is open on channel 'link'"):
        loopbus.set_link("link", up=False)


def test_a_sender_thread_loses_nothing_and_leaves_no_stale_wakeup() -> None:
    n = 20_000
    with LoopBus("threads") as a, LoopBus("threads", rx_queue_size=n) as b:

        def produce() -> None:
            for i in range(n):
                a.send(frame(i))

        sender = threading.Thread(target=produce)
        sender.start()
        got: list[int] = []
        while len(got) < n:
            assert select.select([b.fileno()], [], [], 10)[0], "no wakeup while frames pending"
            got.extend(int.from_bytes(m.data, "little") for m in b.drain())
        sender.join(10)
        assert got == list(range(n))
        assert b.dropped == 0
        assert not readable(b)


def test_notifier_with_a_loop_reads_through_the_file_descriptor() -> None:
    async def main() -> list[int]:
        with LoopBus("notify") as a, LoopBus("notify") as b:
            reader = can.AsyncBufferedReader()
            notifier = can.Notifier(b, [reader], loop=asyncio.get_running_loop())
            try:
                assert notifier._readers == [b.fileno()]  # add_reader, no thread
                for i in range(5):
                    a.send(frame(i))
                return [
                    (await asyncio.wait_for(reader.get_message(), 5)).arbitration_id
                    for _ in range(5)
                ]
            finally:
                notifier.stop()

    assert asyncio.run(main()) == [0x100, 0x101, 0x102, 0x103, 0x104]


def test_notifier_without_a_loop_uses_a_thread_and_recv() -> None:
    with LoopBus("notify_thread") as a, LoopBus("notify_thread") as b:
        reader = can.BufferedReader()
        notifier = can.Notifier(b, [reader], timeout=0.05)
        try:
            for i in range(5):
                a.send(frame(i))
            got = [reader.get_message(5) for _ in range(5)]
        finally:
            notifier.stop()
        assert [m.arbitration_id for m in got] == [0x100, 0x101, 0x102, 0x103, 0x104]


def test_can_bus_opens_it_by_interface_name(monkeypatch: pytest.MonkeyPatch) -> None:
    """In this process the entry point may not be installed: register the backend for
    this test only (python-can looks interfaces up in can.interfaces.BACKENDS)."""
    monkeypatch.setitem(can.interfaces.BACKENDS, "cdprd_loop", ("sim_bus.bus.loopbus", "LoopBus"))
    with (
        can.Bus(interface="cdprd_loop", channel="byname", ignore_config=True) as a,
        can.Bus(interface="cdprd_loop", channel="byname", ignore_config=True, bitrate=500_000) as b,
    ):
        assert isinstance(a, LoopBus) and b.bitrate == 500_000
        a.send(frame(1))
        assert b.recv(0) is not None


ENTRY_POINT_CHECK = textwrap.dedent(
    """
    import can
    a = can.Bus(interface="cdprd_loop", channel="ep")
    b = can.Bus(interface="cdprd_loop", channel="ep")
    a.send(can.Message(arbitration_id=0x42, data=b"ok"))
    msg = b.recv(0)
    print(type(a).__module__, type(a).__name__, bytes(msg.data).decode())
    a.shutdown(); b.shutdown()
    """
)


def test_the_entry_point_lines_register_the_interface(tmp_path: Path) -> None:
    """The `can.interface` entry point the pyproject declares (same text as a
    dist-info entry_points.txt), seen by a fresh python-can through importlib.metadata
    exactly as an installed distribution's would be."""
    dist = tmp_path / "cdprd_loop_entry_point-0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: cdprd-loop-entry-point\nVersion: 0\n"
    )
    (dist / "entry_points.txt").write_text(
        "[can.interface]\ncdprd_loop = sim_bus.bus.loopbus:LoopBus\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    out = subprocess.run(
        [sys.executable, "-c", ENTRY_POINT_CHECK],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["sim_bus.bus.loopbus", "LoopBus", "ok"]
