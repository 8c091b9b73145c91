"""A socketcand-protocol server on the simulator's bus, so that other processes and stock
python-can tools (``can.Bus(interface="socketcand", ...)``, can.logger, cantools monitor)
attach where the kernel has no CAN.

The subset of the socketcand protocol (linux-can/socketcand doc/protocol.md) that
python-can's socketcand client speaks, with socketcand's replies:

    server: < hi >                      on connect
    client: < open vcan0 >              server: < ok >   (another name: < error could
                                                          not open bus >, then closes)
    client: < rawmode >                 server: < ok >, then every bus frame:
    server: < frame 123 1712345678.123456 11223344 >   (3 hex digits: standard id,
                                                        8: extended; data hex, unspaced)
    server: < error 088 1712345678.123456 >            (an error frame, class in the id)
    client: < send 123 4 11 22 33 44 >  a frame onto the bus (id 8 hex digits: extended)
    client: < echo >                    server: < echo >
    client: < bcmmode >                 server: < ok >  (stops the frame stream)

Any other command gets ``< error unknown command >``; a malformed ``send`` is logged and
dropped without a reply, as socketcand does.  Remote and CAN FD frames are not forwarded
(socketcand's raw mode does not forward RTR either; python-can's client parses neither).

Frames a client sends go onto the bus and to the other rawmode clients (not back to the
sender, like a SocketCAN raw socket).  The server must be the only reader of the bus it
is given, opened without receive_own_messages.  Writes are batched: all frames drained
in one loop pass go to a client in one write.  A client whose unsent output exceeds
`max_client_buffer` bytes (it stopped reading) is disconnected with a logged reason.

python-can's client reads the ``< ok >`` of rawmode with a single recv(256) and compares
it exactly, so frames must not arrive in the same read.  After rawmode the server holds a
client's frames until the client sends anything (python-can's client can send only once
its handshake has returned) or `rawmode_grace` seconds have passed, then sends them all:
no frame from the rawmode command on is lost, the first ones may come late.

Loopback only unless ``allow_remote=True`` (DESIGN §14).
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import re
import socket
import time
from collections import Counter
from typing import Any

import can

log = logging.getLogger(__name__)

MAX_COMMAND_BYTES = 1024
_HEX_ID = re.compile(r"[0-9A-Fa-f]{1,8}")
_HEX_BYTE = re.compile(r"[0-9A-Fa-f]{1,2}")
_QUICKACK = getattr(socket, "TCP_QUICKACK", None)


def encode_frame(msg: can.Message) -> bytes | None:
    """The socketcand rawmode line for `msg`, or None for frames it does not carry."""
    us = round(msg.timestamp * 1e6)
    secs, usecs = divmod(us, 1_000_000)
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & 0x1FFFFFFF:03X} {secs}.{usecs:06d} >".encode()
    if msg.is_remote_frame or msg.is_fd:
        return None
    if msg.is_extended_id:
        ident = f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
    else:
        ident = f"{msg.arbitration_id & 0x7FF:03X}"
    return f"< frame {ident} {secs}.{usecs:06d} {msg.data[: msg.dlc].hex().upper()} >".encode()


def parse_send(args: list[str]) -> can.Message:
    """A frame from the arguments of ``< send id dlc b0 b1 ... >`` (ValueError naming
    the problem).  As in socketcand, an 8-digit id is extended, the DLC is decimal 0..8
    and there must be exactly DLC data bytes in hex."""
    if len(args) < 2:
        raise ValueError("send needs an id and a DLC")
    ident, dlc_text, *byte_texts = args
    if not _HEX_ID.fullmatch(ident):
        raise ValueError(f"id {ident!r} is not 1..8 hexadecimal digits")
    can_id = int(ident, 16)
    extended = len(ident) == 8
    if not extended and can_id > 0x7FF:
        raise ValueError(f"standard id {ident!r} is above 7FF (extended ids have 8 digits)")
    if extended and can_id > 0x1FFFFFFF:
        raise ValueError(f"extended id {ident!r} is above 1FFFFFFF")
    if not dlc_text.isdecimal() or int(dlc_text) > 8:
        raise ValueError(f"DLC {dlc_text!r} is not a number 0..8")
    dlc = int(dlc_text)
    if len(byte_texts) != dlc:
        raise ValueError(f"DLC {dlc} but {len(byte_texts)} data bytes")
    bad = [b for b in byte_texts if not _HEX_BYTE.fullmatch(b)]
    if bad:
        raise ValueError(f"data bytes {bad} are not hexadecimal 0..FF")
    data = bytes(int(b, 16) for b in byte_texts)
    return can.Message(
        timestamp=time.time(), arbitration_id=can_id, is_extended_id=extended, dlc=dlc, data=data
    )


def _listen_address(host: str, allow_remote: bool) -> str:
    """The address to bind: `host` resolved; a ValueError unless it is loopback or
    allow_remote is set."""
    try:
        addresses = [ipaddress.ip_address(host)]
    except ValueError:
        try:
            infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
        except socket.gaierror as exc:
            raise ValueError(f"SocketcandServer: cannot resolve host {host!r}: {exc}") from None
        addresses = [ipaddress.ip_address(info[4][0]) for info in infos]
    if not allow_remote and not all(a.is_loopback for a in addresses):
        raise ValueError(
            f"SocketcandServer refuses to listen on {host!r}: not a loopback address "
            "(DESIGN §14); pass allow_remote=True to expose the simulated bus on a network"
        )
    if not all(a.is_loopback for a in addresses):
        log.warning("socketcand server listening on %s: reachable from the network", host)
    return str(addresses[0])


def _drainable_fd(bus: can.BusABC) -> int:
    """The bus's file descriptor if it also has drain() (LoopBus, FaultyBus over one),
    else -1 (the bus is then read through a can.Notifier)."""
    if not callable(getattr(bus, "drain", None)):
        return -1
    try:
        return bus.fileno()
    except NotImplementedError:
        return -1


class _Client(asyncio.Protocol):
    """One TCP connection: its protocol state and its output."""

    def __init__(self, server: SocketcandServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.peer = "?"
        self.mode = "nobus"  # nobus -> bcm (after open) <-> raw
        self._held: list[bytes] | None = None  # frames kept back during the rawmode grace
        self._held_bytes = 0
        self._grace_timer: asyncio.TimerHandle | None = None
        self._buf = bytearray()
        self._sock: Any = None

    # asyncio callbacks
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        peer = transport.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if peer else "?"
        self._sock = transport.get_extra_info("socket")
        self.server._clients.add(self)
        self.server.stats["clients_accepted"] += 1
        log.info("socketcand client %s connected", self.peer)
        transport.write(b"< hi >")

    def connection_lost(self, exc: Exception | None) -> None:
        self.server._clients.discard(self)
        self._stop_holding()
        log.info("socketcand client %s disconnected%s", self.peer, f": {exc}" if exc else "")

    def data_received(self, data: bytes) -> None:
        if self._held is not None:
            self._end_grace()  # it sent something: it has read the "< ok >" of rawmode
        buf = self._buf
        buf += data
        frames: list[can.Message] = []
        pos = 0
        while True:
            start = buf.find(b"<", pos)
            if start < 0:
                pos = len(buf)  # text outside < > is ignored, as by socketcand
                break
            end = buf.find(b">", start)
            if end < 0:
                pos = start
                if len(buf) - start > MAX_COMMAND_BYTES:
                    self.disconnect(f"a command is longer than {MAX_COMMAND_BYTES} bytes")
                    return
                break
            self._command(buf[start + 1 : end].decode("ascii", "replace").split(), frames)
            pos = end + 1
            if self.transport is None or self.transport.is_closing():
                return
        del buf[:pos]
        if frames:
            self.server._forward(frames, origin=self)
        if _QUICKACK is not None and self._sock is not None:
            # like socketcand: ACK at once, so a client with Nagle on does not stall
            self._sock.setsockopt(socket.IPPROTO_TCP, _QUICKACK, 1)

    # protocol
    def _command(self, tokens: list[str], frames: list[can.Message]) -> None:
        server = self.server
        cmd = tokens[0] if tokens else ""
        if cmd == "echo":
            self.write(b"< echo >")
        elif self.mode == "nobus":
            if cmd == "open" and len(tokens) == 2:
                if tokens[1] == server.channel:
                    self.mode = "bcm"
                    self.write(b"< ok >")
                else:
                    log.warning(
                        "socketcand client %s asked for bus %r; this server has %r",
                        self.peer,
                        tokens[1],
                        server.channel,
                    )
                    self.write(b"< error could not open bus >")
                    if self.transport is not None:
                        self.transport.close()
            else:
                self._unknown(tokens)
        elif cmd == "send":
            try:
                msg = parse_send(tokens[1:])
            except ValueError as exc:
                server.stats["bad_commands"] += 1
                log.warning("socketcand client %s: bad send %r: %s", self.peer, tokens, exc)
                return
            try:
                server.bus.send(msg)
            except can.CanError as exc:
                server.stats["send_failures"] += 1
                log.warning("socketcand client %s: bus refused a frame: %s", self.peer, exc)
                return
            server.stats["frames_from_clients"] += 1
            frames.append(msg)
        elif cmd == "rawmode":
            self.write(b"< ok >")
            if self.mode != "raw":
                self.mode = "raw"
                self._held, self._held_bytes = [], 0
                loop = asyncio.get_running_loop()
                self._grace_timer = loop.call_later(server.rawmode_grace, self._end_grace)
        elif cmd == "bcmmode":
            self.mode = "bcm"
            self._stop_holding()
            self.write(b"< ok >")
        else:
            self._unknown(tokens)

    def _unknown(self, tokens: list[str]) -> None:
        self.server.stats["bad_commands"] += 1
        log.warning(
            "socketcand client %s: unknown command %r in %s mode", self.peer, tokens, self.mode
        )
        self.write(b"< error unknown command >")

    def deliver(self, payload: bytes) -> None:
        """Frames for a rawmode client: sent now, or held during its rawmode grace."""
        if self._held is None:
            self.write(payload)
            return
        self._held.append(payload)
        self._held_bytes += len(payload)
        if self._held_bytes > self.server.max_client_buffer:
            self.disconnect(
                f"{self._held_bytes} bytes held after rawmode exceed max_client_buffer="
                f"{self.server.max_client_buffer}"
            )

    def _end_grace(self) -> None:
        held = self._held
        self._stop_holding()
        if held:
            self.write(b"".join(held))

    def _stop_holding(self) -> None:
        self._held, self._held_bytes = None, 0
        if self._grace_timer is not None:
            self._grace_timer.cancel()
            self._grace_timer = None

    def write(self, payload: bytes) -> None:
        transport = self.transport
        if transport is None or transport.is_closing():
            return
        transport.write(payload)
        size = transport.get_write_buffer_size()
        if size > self.server.max_client_buffer:
            self.disconnect(
                f"{size} bytes not yet sent exceed max_client_buffer="
                f"{self.server.max_client_buffer} (the client is not reading)"
            )

    def disconnect(self, reason: str) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        log.warning("socketcand client %s disconnected by the server: %s", self.peer, reason)
        self.server.stats["clients_dropped"] += 1
        self._stop_holding()
        self.transport.abort()


class SocketcandServer:
    """Serves `bus` over the socketcand protocol on host:port (see the module docstring).

    ``await start()`` binds (``port`` then holds the bound port), ``await stop()`` closes
    the listener and every client; the bus stays open (the caller owns it).  A bus with
    drain() and fileno() is read from the loop directly; any other python-can bus through
    a can.Notifier (its reader thread, if it uses one, stops within 50 ms on stop()).

    `stats` counts clients_accepted, clients_dropped (by the server), frames_from_bus,
    frames_from_clients, frames_to_clients (frames x clients), bad_commands,
    send_failures (the bus refused a client's frame) and not_forwarded (RTR/FD frames)."""

    def __init__(
        self,
        bus: can.BusABC,
        host: str = "127.0.0.1",
        port: int = 0,
        channel: str = "vcan0",
        *,
        allow_remote: bool = False,
        max_client_buffer: int = 1 << 20,
        rawmode_grace: float = 0.05,
    ) -> None:
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"SocketcandServer port must be 0..65535, got {port!r}")
        if not channel or any(c.isspace() or c in "<>" for c in channel):
            raise ValueError(f"SocketcandServer channel {channel!r} must be one word")
        if max_client_buffer < 1024:
            raise ValueError(f"max_client_buffer must be >= 1024 bytes, got {max_client_buffer}")
        if not rawmode_grace >= 0:
            raise ValueError(f"rawmode_grace must be >= 0 seconds, got {rawmode_grace!r}")
        self.bus = bus
        self.host = _listen_address(host, allow_remote)
        self.requested_port = port
        self.channel = channel
        self.max_client_buffer = max_client_buffer
        self.rawmode_grace = rawmode_grace
        self.port: int | None = None
        self.stats: Counter[str] = Counter()
        self._clients: set[_Client] = set()
        self._server: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reader_fd: int | None = None
        self._notifier: can.Notifier | None = None
        self._pending: list[can.Message] = []

    @property
    def clients(self) -> int:
        return len(self._clients)

    async def start(self) -> None:
        if self._server is not None:
            raise RuntimeError("SocketcandServer is already started")
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._server = await loop.create_server(
            lambda: _Client(self), self.host, self.requested_port
        )
        self.port = self._server.sockets[0].getsockname()[1]
        fd = _drainable_fd(self.bus)
        if fd >= 0:
            loop.add_reader(fd, self._on_bus_readable)
            self._reader_fd = fd
        else:
            self._notifier = can.Notifier(self.bus, [self._on_bus_frame], timeout=0.05, loop=loop)
        log.info(
            "socketcand server for %s on %s:%d (channel %s)",
            self.bus.channel_info,
            self.host,
            self.port,
            self.channel,
        )

    async def stop(self) -> None:
        if self._server is None:
            return
        if self._reader_fd is not None and self._loop is not None:
            self._loop.remove_reader(self._reader_fd)
            self._reader_fd = None
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        self._server.close()
        for client in list(self._clients):
            if client.transport is not None:
                client.transport.close()
        await self._server.wait_closed()
        self._server = None

    async def __aenter__(self) -> SocketcandServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # bus -> clients
    def _on_bus_readable(self) -> None:
        frames = self.bus.drain()  # type: ignore[attr-defined]
        if frames:
            self.stats["frames_from_bus"] += len(frames)
            self._forward(frames, origin=None)

    def _on_bus_frame(self, msg: can.Message) -> None:
        """Notifier listener (in the loop): collect, forward once per loop pass."""
        self.stats["frames_from_bus"] += 1
        if not self._pending:
            self._loop.call_soon(self._flush_pending)
        self._pending.append(msg)

    def _flush_pending(self) -> None:
        frames, self._pending = self._pending, []
        self._forward(frames, origin=None)

    def _forward(self, frames: list[can.Message], origin: _Client | None) -> None:
        """One write per rawmode client (except `origin`) carrying all `frames`."""
        targets = [c for c in self._clients if c is not origin and c.mode == "raw"]
        if not targets:
            return
        lines = []
        for msg in frames:
            line = encode_frame(msg)
            if line is None:
                self.stats["not_forwarded"] += 1
            else:
                lines.append(line)
        if not lines:
            return
        payload = b"".join(lines)
        for client in targets:
            client.deliver(payload)
        self.stats["frames_to_clients"] += len(lines) * len(targets)
