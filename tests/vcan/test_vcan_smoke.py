"""Smoke tests against a real SocketCAN ``vcan0``: python-can, can-utils, asyncio.

They run only where ``vcan0`` is usable (natively, or inside the UML guest
that ``test_vcan_suite_in_uml`` boots); see ``conftest.py``.
"""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import uml

pytestmark = [pytest.mark.vcan, pytest.mark.slow]

CHANNEL = "vcan0"
RECV_TIMEOUT = 2.0
TOOL_TIMEOUT = 10.0
# candump -L: "(1700000000.123456) vcan0 123#DEADBEEF"
CANDUMP_LINE = re.compile(r"^\((\d+\.\d+)\) (\S+) ([0-9A-F]{3}|[0-9A-F]{8})#([0-9A-F]*)$")


def open_bus(can_id: int | None = None) -> can.BusABC:
    """A socketcan bus on vcan0, receiving only ``can_id`` if given."""
    filters = (
        None
        if can_id is None
        else [{"can_id": can_id, "can_mask": 0x1FFFFFFF, "extended": can_id > 0x7FF}]
    )
    return can.Bus(interface="socketcan", channel=CHANNEL, can_filters=filters)


@pytest.fixture
def sender() -> Iterator[can.BusABC]:
    with open_bus() as bus:
        yield bus


@pytest.mark.parametrize(
    ("can_id", "extended", "data"),
    [(0x123, False, b"\x01\x02\x03\x04"), (0x1ABCDE0, True, b"\xff" * 8), (0x7FF, False, b"")],
    ids=["standard", "extended", "empty"],
)
def test_python_can_frame_crosses_vcan0(
    sender: can.BusABC, can_id: int, extended: bool, data: bytes
) -> None:
    with open_bus(can_id) as receiver:
        sender.send(can.Message(arbitration_id=can_id, is_extended_id=extended, data=data))
        got = receiver.recv(timeout=RECV_TIMEOUT)
    assert got is not None, f"no frame within {RECV_TIMEOUT} s"
    assert (got.arbitration_id, got.is_extended_id, bytes(got.data), got.channel) == (
        can_id,
        extended,
        data,
        CHANNEL,
    )


def test_candump_logs_python_can_frame(sender: can.BusABC) -> None:
    frame = can.Message(arbitration_id=0x1A5, is_extended_id=False, data=b"\xde\xad\xbe\xef")
    with subprocess.Popen(
        ["candump", "-L", "-n", "1", CHANNEL], stdout=subprocess.PIPE, text=True
    ) as dump:
        try:
            # candump may not have bound its socket yet: resend until it logs one frame.
            deadline = time.monotonic() + TOOL_TIMEOUT
            while dump.poll() is None and time.monotonic() < deadline:
                sender.send(frame)
                time.sleep(0.05)
            out, _ = dump.communicate(timeout=1)
        finally:
            dump.kill()
    assert dump.returncode == 0, f"candump did not log a frame within {TOOL_TIMEOUT} s"
    match = CANDUMP_LINE.match(out.strip())
    assert match, f"unexpected candump line: {out!r}"
    assert match.group(2, 3, 4) == (CHANNEL, "1A5", "DEADBEEF")
    assert abs(float(match.group(1)) - time.time()) < 60


def test_cansend_frame_reaches_python_can() -> None:
    with open_bus(0x123) as receiver:
        subprocess.run(["cansend", CHANNEL, "123#DEADBEEF"], check=True, timeout=TOOL_TIMEOUT)
        got = receiver.recv(timeout=RECV_TIMEOUT)
    assert got is not None, f"no frame within {RECV_TIMEOUT} s"
    assert (got.arbitration_id, got.is_extended_id, bytes(got.data)) == (
        0x123,
        False,
        b"\xde\xad\xbe\xef",
    )


def test_asyncio_reader_on_bus_fileno(sender: can.BusABC) -> None:
    """The daemon's pattern: ``loop.add_reader(bus.fileno(), ...)`` then ``recv(timeout=0)``."""

    async def receive_one(receiver: can.BusABC) -> can.Message:
        loop = asyncio.get_running_loop()
        arrived: asyncio.Future[can.Message] = loop.create_future()

        def on_readable() -> None:
            msg = receiver.recv(timeout=0)
            if msg is not None and not arrived.done():
                arrived.set_result(msg)

        loop.add_reader(receiver.fileno(), on_readable)
        try:
            loop.call_soon(
                sender.send, can.Message(arbitration_id=0x2C0, is_extended_id=False, data=b"\x2a")
            )
            return await asyncio.wait_for(arrived, RECV_TIMEOUT)
        finally:
            loop.remove_reader(receiver.fileno())

    with open_bus(0x2C0) as receiver:
        got = asyncio.run(receive_one(receiver))
    assert (got.arbitration_id, bytes(got.data)) == (0x2C0, b"\x2a")


@pytest.mark.skipif(
    os.environ.get(uml.GUEST_ENV) != "1", reason="the UML guest's setting; a host has its own"
)
def test_the_guest_s_softirq_threads_run_above_every_test_process() -> None:
    """In the UML guest, ksoftirqd (which delivers frames to sockets under load) runs at
    SCHED_FIFO uml.SOFTIRQ_PRIORITY, above the simulator and the daemon's core."""
    threads = [
        int(entry.name)
        for entry in Path("/proc").iterdir()
        if entry.name.isdigit() and (entry / "comm").read_text().startswith("ksoftirqd/")
    ]
    assert threads, "no ksoftirqd in /proc"
    for pid in threads:
        assert os.sched_getscheduler(pid) == os.SCHED_FIFO, pid
        assert os.sched_getparam(pid).sched_priority == uml.SOFTIRQ_PRIORITY, pid
