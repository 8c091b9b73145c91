"""The socketcand-protocol server (sim_bus.bus.socketcand), against python-can's own
socketcand client, raw sockets, and a server in another process."""

from __future__ import annotations

import asyncio
import errno
import os
import select
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from hypothesis import given
from hypothesis import strategies as st

from drivers.bus import BusGone, SocketcandIO, frame_io, gone
from sim_bus.bus.loopbus import LoopBus
from sim_bus.bus.socketcand import SocketcandServer, encode_frame, parse_send

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 10.0


class LoopThread:
    """An asyncio loop in a background thread, so the blocking python-can client can run
    in the test's thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(TIMEOUT)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(TIMEOUT)
        self.loop.close()


@contextmanager
def serving(bus: can.BusABC, **kwargs) -> Iterator[SocketcandServer]:
    loop = LoopThread()
    server = SocketcandServer(bus, **kwargs)
    try:
        loop.run(server.start())
        yield server
    finally:
        loop.run(server.stop())
        loop.close()


def client(server: SocketcandServer, **kwargs) -> can.BusABC:
    return can.Bus(
        interface="socketcand", host="127.0.0.1", port=server.port, channel="vcan0", **kwargs
    )


def _open_rawmode(raw: socket.socket) -> None:
    """The client's side of socketcand's greeting: open vcan0 and enter raw mode."""
    assert raw.recv(64) == b"< hi >"
    raw.sendall(b"< open vcan0 >")
    assert raw.recv(64) == b"< ok >"
    raw.sendall(b"< rawmode >")
    assert raw.recv(64) == b"< ok >"


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def std(ident: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=ident, data=data, is_extended_id=False)


def ext(ident: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=ident, data=data, is_extended_id=True)


def same_frame(a: can.Message, b: can.Message) -> bool:
    return (a.arbitration_id, a.is_extended_id, bytes(a.data)) == (
        b.arbitration_id,
        b.is_extended_id,
        bytes(b.data),
    )


FRAMES = [std(0x123, b"\x01\x02\xab"), std(0x7FF, bytes(range(8))), std(0, b""), ext(0x1ABCDEF0)]


# ---- the line format against python-can's own converters --------------------------
frames = st.builds(
    lambda e, ident, data: can.Message(
        timestamp=1_700_000_000.123456,
        arbitration_id=ident if e else ident & 0x7FF,
        is_extended_id=e,
        data=data,
    ),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
    st.binary(max_size=8),
)


@given(frames)
def test_frame_lines_parse_with_python_can_and_send_lines_parse_here(msg: can.Message) -> None:
    back = convert_ascii_message_to_can_message(encode_frame(msg).decode())
    assert same_frame(back, msg) and back.timestamp == pytest.approx(msg.timestamp)
    line = convert_can_message_to_ascii_message(msg)
    assert same_frame(parse_send(line[1:-1].split()[1:]), msg)


def test_error_frames_are_forwarded_as_error_lines() -> None:
    err = can.Message(timestamp=12.5, arbitration_id=0x88, is_error_frame=True)
    assert encode_frame(err) == b"< error 088 12.500000 >"
    back = convert_ascii_message_to_can_message(encode_frame(err).decode())
    assert back.is_error_frame and back.arbitration_id == 0x88
    assert encode_frame(can.Message(arbitration_id=1, is_remote_frame=True)) is None


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        ([], "needs an id and a DLC"),
        (["12G", "0"], "hexadecimal"),
        (["800", "0"], "above 7FF"),
        (["3FFFFFFF", "0"], "above 1FFFFFFF"),
        (["123", "9"], "0..8"),
        (["123", "x"], "0..8"),
        (["123", "2", "11"], "DLC 2 but 1"),
        (["123", "1", "123"], "hexadecimal 0..FF"),
        (["123", "1", "+1"], "hexadecimal 0..FF"),
    ],
)
def test_bad_send_commands_are_named(args: list[str], problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        parse_send(args)


# ---- python-can's socketcand client in this process --------------------------------
def test_python_can_client_exchanges_frames_with_a_loop_bus() -> None:
    with LoopBus("sc1") as served, LoopBus("sc1") as device, serving(served) as server:
        remote = client(server)
        try:
            for msg in FRAMES:
                remote.send(msg)
            got = [device.recv(TIMEOUT) for _ in FRAMES]
            assert all(same_frame(g, m) for g, m in zip(got, FRAMES, strict=True))
            for msg in FRAMES:
                device.send(msg)
            device.send(can.Message(arbitration_id=0x88, is_error_frame=True))
            back = [remote.recv(TIMEOUT) for _ in FRAMES]
            assert all(same_frame(g, m) for g, m in zip(back, FRAMES, strict=True))
            assert back[0].timestamp == pytest.approx(FRAMES[0].timestamp, abs=1e-6)
            error = remote.recv(TIMEOUT)
            assert error.is_error_frame and error.arbitration_id == 0x88
        finally:
            remote.shutdown()
        assert server.stats["frames_from_clients"] == len(FRAMES)


def test_frames_from_one_client_reach_the_others_not_itself() -> None:
    with LoopBus("sc2") as served, LoopBus("sc2") as device, serving(served) as server:
        a, b = client(server), client(server)
        try:
            b.send(std(0x100))  # ends b's rawmode grace; a's ends on its own timer
            assert device.recv(TIMEOUT).arbitration_id == 0x100
            assert a.recv(TIMEOUT).arbitration_id == 0x100
            a.send(std(0x200, b"\x05"))
            assert b.recv(TIMEOUT).arbitration_id == 0x200
            assert device.recv(TIMEOUT).arbitration_id == 0x200
            assert a.recv(0.2) is None  # not echoed to the sender
        finally:
            a.shutdown()
            b.shutdown()


def test_frames_sent_right_after_rawmode_are_held_not_lost() -> None:
    """Bus frames that follow the "< ok >" of rawmode at once are held back until the
    client speaks (python-can compares that "< ok >" with one recv), then delivered."""
    with (
        LoopBus("sc3") as served,
        LoopBus("sc3") as device,
        serving(served, rawmode_grace=5.0) as server,
    ):
        raw = socket.create_connection(("127.0.0.1", server.port), timeout=TIMEOUT)
        try:
            _open_rawmode(raw)
            device.send(std(0x111, b"\x01"))
            device.send(std(0x112))
            assert not select.select([raw], [], [], 0.2)[0]  # held
            raw.sendall(b"< echo >")
            text = read_until(raw, b"< echo >")
            assert text.startswith(b"< frame 111 ") and b"< frame 112 " in text
        finally:
            raw.close()


def read_until(sock: socket.socket, end: bytes) -> bytes:
    data = b""
    deadline = time.monotonic() + TIMEOUT
    while not data.endswith(end):
        assert time.monotonic() < deadline, f"no {end!r} in {data!r}"
        chunk = sock.recv(4096)
        assert chunk, f"connection closed after {data!r}"
        data += chunk
    return data


def test_protocol_replies_like_socketcand() -> None:
    with LoopBus("sc4") as served, LoopBus("sc4") as device, serving(served) as server:
        raw = socket.create_connection(("127.0.0.1", server.port), timeout=TIMEOUT)
        try:
            assert raw.recv(64) == b"< hi >"
            raw.sendall(b"< rawmode >")  # no bus opened yet
            assert raw.recv(64) == b"< error unknown command >"
            raw.sendall(b"< open vc")  # split across segments
            time.sleep(0.05)
            raw.sendall(b"an0 >")
            assert raw.recv(64) == b"< ok >"
            # two sends in one segment, one malformed (ignored without reply, as by socketcand)
            raw.sendall(b"< send 123 2 a b >< send 123 3 1 >< send 1FFFFFFF 0 >< echo >")
            assert read_until(raw, b"< echo >") == b"< echo >"
            got = [device.recv(TIMEOUT), device.recv(TIMEOUT)]
            assert bytes(got[0].data) == b"\x0a\x0b" and not got[0].is_extended_id
            assert got[1].arbitration_id == 0x1FFFFFFF and got[1].is_extended_id
            assert server.stats["bad_commands"] == 2
            raw.sendall(b"< subscribe 0 0 123 >")
            assert read_until(raw, b">") == b"< error unknown command >"
            raw.sendall(b"< rawmode >")
            assert read_until(raw, b">") == b"< ok >"
            raw.sendall(b"< bcmmode >")  # before the grace ends: nothing streamed
            assert read_until(raw, b">") == b"< ok >"
            device.send(std(0x321))
            raw.sendall(b"< echo >")
            assert read_until(raw, b">") == b"< echo >"
        finally:
            raw.close()


def test_wrong_bus_name_is_refused_and_the_connection_closed() -> None:
    with LoopBus("sc5") as served, serving(served, channel="can7") as server:
        raw = socket.create_connection(("127.0.0.1", server.port), timeout=TIMEOUT)
        try:
            assert raw.recv(64) == b"< hi >"
            raw.sendall(b"< open vcan0 >")
            assert read_until(raw, b">") == b"< error could not open bus >"
            assert raw.recv(64) == b""  # closed
        finally:
            raw.close()
        with pytest.raises(can.CanError, match="could not open bus"):
            client(server)


def test_a_client_that_stops_reading_is_disconnected(caplog: pytest.LogCaptureFixture) -> None:
    with (
        LoopBus("sc6") as served,
        LoopBus("sc6") as device,
        serving(served, max_client_buffer=64 * 1024, rawmode_grace=0.0) as server,
    ):
        raw = socket.socket()
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        raw.settimeout(TIMEOUT)
        raw.connect(("127.0.0.1", server.port))
        try:
            _open_rawmode(raw)
            batch = [std(0x100 + i % 256, bytes(8)) for i in range(1000)]

            def flood() -> bool:
                for msg in batch:
                    device.send(msg)
                return server.stats["clients_dropped"] == 1

            wait_for(flood, "the slow client to be dropped")
            wait_for(lambda: server.clients == 0, "the connection to close")
            assert "the client is not reading" in caplog.text
        finally:
            raw.close()


def test_only_loopback_unless_allowed() -> None:
    with LoopBus("sc7") as bus:
        for host in ("0.0.0.0", "192.0.2.1", "::"):
            with pytest.raises(ValueError, match=r"not a loopback address.*allow_remote=True"):
                SocketcandServer(bus, host=host)
        assert SocketcandServer(bus, host="localhost").host in ("127.0.0.1", "::1")
        assert SocketcandServer(bus, host="::1").host == "::1"
        # constructing is allowed; this test never binds a non-loopback address
        assert SocketcandServer(bus, host="0.0.0.0", allow_remote=True).host == "0.0.0.0"
        for kwargs, problem in [
            ({"port": 70000}, "port"),
            ({"channel": "two words"}, "channel"),
            ({"max_client_buffer": 10}, "max_client_buffer"),
            ({"rawmode_grace": -1.0}, "rawmode_grace"),
        ]:
            with pytest.raises(ValueError, match=problem):
                SocketcandServer(bus, **kwargs)


def test_any_python_can_bus_through_a_notifier() -> None:
    """A bus without drain()/fileno (python-can's virtual bus) is read by a can.Notifier."""
    served = can.Bus(interface="virtual", channel="sc8", ignore_config=True)
    device = can.Bus(interface="virtual", channel="sc8", ignore_config=True)
    try:
        with serving(served) as server:
            remote = client(server)
            try:
                remote.send(std(0x42, b"hi"))
                assert bytes(device.recv(TIMEOUT).data) == b"hi"
                for i in range(50):
                    device.send(std(0x43, bytes([i])))
                got = [remote.recv(TIMEOUT) for _ in range(50)]
                assert [g.data[0] for g in got] == list(range(50))
            finally:
                remote.shutdown()
    finally:
        served.shutdown()
        device.shutdown()


# ---- the daemon's reading of python-can's client ----------------------------------
@contextmanager
def raw_server() -> Iterator[tuple[can.BusABC, socket.socket]]:
    """python-can's client connected to a bare TCP server that answers its handshake as
    socketcand does; yields (client bus, the server's end of the connection)."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        ends: list[socket.socket] = []

        def handshake() -> None:
            conn, _ = listener.accept()
            conn.sendall(b"< hi >")
            for _ in ("open", "rawmode"):
                conn.recv(256)
                conn.sendall(b"< ok >")
            ends.append(conn)

        thread = threading.Thread(target=handshake)
        thread.start()
        bus = client_at(listener.getsockname()[1])
        thread.join(TIMEOUT)
        try:
            with ends[0] as end:
                yield bus, end
        finally:
            bus.shutdown()


def client_at(port: int) -> can.BusABC:
    return can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")


def drained(io: SocketcandIO) -> list[can.Message]:
    assert select.select([io.fileno()], [], [], TIMEOUT)[0], "socket never readable"
    return io.drain()


def test_the_daemon_reads_the_socketcand_socket_itself() -> None:
    """On the event loop through the socket's fd (python-can's Notifier thread tripled
    the SYNC-to-feedback time), every complete message per read, however TCP splits
    them, and the end of the connection is the bus gone."""
    with raw_server() as (bus, end):
        io = frame_io(bus)
        assert isinstance(io, SocketcandIO) and io.fileno() >= 0
        end.sendall(b"< frame 181 1.500000 0102 >< ok >< frame 18")
        assert [(m.arbitration_id, bytes(m.data)) for m in drained(io)] == [(0x181, b"\1\2")]
        end.sendall(b"2 1.500000 03 >< error 004 1.600000 >< frame 9 >< frame 1234ABCD 1.7  >")
        got = drained(io)
        assert [(m.arbitration_id, bytes(m.data), m.is_error_frame) for m in got] == [
            (0x182, b"\3", False),
            (0x004, b"\0", True),
            (0x1234ABCD, b"", False),
        ]
        assert got[2].is_extended_id and all(m.channel == "vcan0" for m in got)
        io.send(std(0x080))
        io.send(std(0x201, b"\x10\xff"))
        expected = b"< send 080 0  >< send 201 2 10 ff >"
        received = b""
        while len(received) < len(expected):
            received += end.recv(256)
        assert received == expected
        end.sendall(b"< frame 185 2.0 05 >")
        end.shutdown(socket.SHUT_WR)
        assert [m.arbitration_id for m in drained(io)] == [0x185]  # before the end
        with pytest.raises(BusGone, match="closed the connection") as error:
            drained(io)
        assert gone(error.value)
        end.close()
        with pytest.raises(can.CanError) as error:  # RST: the next send or the one after
            for _ in range(3):
                io.send(std(0x080))
                time.sleep(0.05)
        assert gone(error.value), error.value


def test_a_refused_or_reset_connection_is_the_bus_gone() -> None:
    assert gone(can.CanOperationError("Network is down", errno.ENETDOWN))
    assert not gone(can.CanOperationError("Failed to receive: bad data"))
    wrapped = can.CanError("Failed to receive")
    wrapped.__cause__ = ConnectionResetError(errno.ECONNRESET, "Connection reset by peer")
    assert gone(wrapped)
    assert gone(BrokenPipeError(errno.EPIPE, "Broken pipe"))
    assert not gone(can.CanOperationError("No buffer space available", errno.ENOBUFS))
    assert not gone(OSError(errno.EAGAIN, "Resource temporarily unavailable"))


# ---- a server in another process ---------------------------------------------------
def test_python_can_client_and_a_server_in_another_process() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    peer = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "socketcand_peer.py"), "--lifetime", "60"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
    )
    try:
        assert select.select([peer.stdout], [], [], 30)[0], "peer printed no port"
        words = peer.stdout.readline().split()
        assert words[0] == b"PORT", words
        remote = can.Bus(
            interface="socketcand", host="127.0.0.1", port=int(words[1]), channel="vcan0"
        )
        try:
            sent = [std(0x200 + i, bytes([i, 255 - i])) for i in range(40)] + [ext(0x1000, b"x")]
            for msg in sent:
                remote.send(msg)
            answers = [remote.recv(TIMEOUT) for _ in sent]
            assert all(a is not None for a in answers)
            assert [(a.arbitration_id, bytes(a.data)) for a in answers] == [
                (m.arbitration_id + 1, bytes(m.data)) for m in sent
            ]
            assert answers[-1].is_extended_id
        finally:
            remote.shutdown()
        peer.stdin.close()
        assert peer.wait(TIMEOUT) == 0
    finally:
        if peer.poll() is None:
            peer.kill()
            peer.wait(TIMEOUT)
