"""The socket-pair bus between the demo's daemon and its simulator process: frames
whole and in order however the stream cuts them, their send stamps carried, the
peer's end and a peer that stopped reading reported as a gone bus, and the simulator's
--bus-fd refusing what is not such an end."""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from drivers.bus import BusGone, frame_io, gone
from sim_bus.bus.pairbus import FRAME, PairBus, bus_pair, encode

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"


def _pair() -> tuple[PairBus, PairBus]:
    a, b = bus_pair()
    return PairBus(a, "a"), PairBus(b, "b")


def _frames() -> list[can.Message]:
    return [
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDEF0, data=b"\x01\x02", is_extended_id=True),
        can.Message(arbitration_id=0x601, dlc=8, is_remote_frame=True, is_extended_id=False),
        can.Message(arbitration_id=0x040, data=bytes(8), is_error_frame=True),
    ]


def test_frames_cross_whole_in_order_with_their_send_stamps() -> None:
    a, b = _pair()
    try:
        before = time.time()
        for msg in _frames():
            a.send(msg)
        after = time.time()
        assert select.select([b.fileno()], [], [], 1.0)[0]  # readable while queued
        got = b.drain()
        assert [m.arbitration_id for m in got] == [m.arbitration_id for m in _frames()]
        for sent, received in zip(_frames(), got, strict=True):
            assert received.is_extended_id == sent.is_extended_id
            assert received.is_remote_frame == sent.is_remote_frame
            assert received.is_error_frame == sent.is_error_frame
            assert received.dlc == sent.dlc
            assert bytes(received.data) == (b"" if sent.is_remote_frame else bytes(sent.data))
            assert before <= received.timestamp <= after
            assert received.channel == "b"
        assert b.drain() == []
        assert isinstance(frame_io(b).drain(), list)  # the daemon reads it by drain()
    finally:
        a.shutdown()
        b.shutdown()


def test_a_record_cut_by_the_stream_waits_for_its_end() -> None:
    raw, other = bus_pair()
    bus = PairBus(other, "b")
    try:
        msg = can.Message(arbitration_id=0x281, data=b"\xaa" * 8, is_extended_id=False)
        record = encode(msg, 123.0) + encode(msg, 124.0)
        raw.sendall(record[: FRAME.size + 5])
        first = bus.drain()
        assert [m.timestamp for m in first] == [123.0]
        raw.sendall(record[FRAME.size + 5 :])
        assert [m.timestamp for m in bus.drain()] == [124.0]
        assert bus.recv(0.5) is None  # nothing queued: no frame made up
    finally:
        raw.close()
        bus.shutdown()


def test_the_peers_end_is_a_gone_bus_after_its_last_frames() -> None:
    a, b = _pair()
    a.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
    a.shutdown()
    try:
        assert [m.arbitration_id for m in b.drain()] == [0x701]
        with pytest.raises(BusGone, match="closed its end") as err:
            b.drain()
        assert gone(err.value)
        with pytest.raises(BusGone, match="closed its end"):
            b.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
    finally:
        b.shutdown()


def test_a_peer_that_stopped_reading_fails_the_send_at_once() -> None:
    a, b = _pair()
    try:
        msg = can.Message(arbitration_id=0x201, data=bytes(8), is_extended_id=False)
        sent = 0
        with pytest.raises(BusGone, match="stopped reading"):
            while sent < 1_000_000:  # bounded: the buffer holds some 10^3 records
                a.send(msg)
                sent += 1
        assert sent > 250  # 1300 with SO_SNDBUFFORCE (root), 278 with the default buffer
        frames = b.drain()
        assert len(frames) == sent  # the refused one was not sent in part
        assert all(m.arbitration_id == 0x201 for m in frames)
    finally:
        a.shutdown()
        b.shutdown()


def test_a_can_fd_frame_is_refused() -> None:
    a, b = _pair()
    try:
        with pytest.raises(ValueError, match="CAN FD"):
            a.send(can.Message(arbitration_id=0x100, data=bytes(12), is_fd=True))
    finally:
        a.shutdown()
        b.shutdown()


def _simulator(*args: str, pass_fds: tuple[int, ...] = ()) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sim_bus", "--config", str(CONFIG), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        pass_fds=pass_fds,
    )


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
def test_bus_fd_refuses_what_is_not_a_stream_pairs_end(tmp_path: Path) -> None:
    read, write = os.pipe()
    try:
        run = _simulator("--bus-fd", str(read), pass_fds=(read,))
    finally:
        os.close(read)
        os.close(write)
    assert run.returncode == 1
    assert f"--bus-fd {read}: not an open socket" in run.stderr, run.stderr
    datagram, other = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        fd = datagram.fileno()
        run = _simulator("--bus-fd", str(fd), pass_fds=(fd,))
    finally:
        datagram.close()
        other.close()
    assert run.returncode == 1
    assert f"--bus-fd {fd}: not a stream socket pair's end" in run.stderr, run.stderr
    run = _simulator("--bus-fd", "3", "--bus-fd", "4")
    assert run.returncode == 1
    assert "--bus-fd: 2 given for the config's 1 buses" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr


def test_a_cycles_frames_go_out_in_one_write_and_arrive_in_order() -> None:
    """send_all writes the frames as one record string (one system call: the reader
    wakes once for them), stamped alike; frame_io's send_all uses it."""
    raw, other = bus_pair()
    sender = PairBus(other, "a")
    try:
        frames = _frames()
        before = time.time()
        frame_io(sender).send_all(frames)
        after = time.time()
        data = raw.recv(1 << 16)
        assert len(data) == FRAME.size * len(frames)  # all of it at once
        stamps = {
            FRAME.unpack(data[k : k + FRAME.size])[0] for k in range(0, len(data), FRAME.size)
        }
        assert len(stamps) == 1 and before <= stamps.pop() <= after
        raw.sendall(data)  # back through the pair: the same frames, in order
        got = sender.drain()
        assert [m.arbitration_id for m in got] == [m.arbitration_id for m in frames]
        sender.send_all([])  # nothing to write: no record, no error
        assert select.select([raw], [], [], 0.05)[0] == []
    finally:
        raw.close()
        sender.shutdown()
