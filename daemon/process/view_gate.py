"""The live view's gate: which web pages may open the Foxglove WebSocket
(docs/guide/live-view.md).

A browser lets any page it shows open a WebSocket to 127.0.0.1, and a page whose name
was made to resolve to 127.0.0.1 (DNS rebinding) even counts as same-origin there; what
the server sees of the page is the upgrade request's `Origin` and `Host` headers.  So a
connection is refused (HTTP 403, before any WebSocket frame) when it sends an Origin that
is not in view.allowed_origins (default: Foxglove's web app) or a Host that is not the
bound address, localhost or in view.allowed_hosts.  A client that sends no Origin is not
a web page (browsers always send one on a WebSocket) and is let in: Foxglove's desktop
app, scripts, tests.

foxglove-sdk 0.30's server has no hook for this: its handshake only checks the
subprotocol (rust/foxglove/src/websocket/handshake.rs) and start_server takes no origin
or host list.  So this gate listens on the view's address instead, reads the upgrade
request's head, and either answers 403 or opens a connection to the sdk's server and
passes the bytes through unchanged both ways (the head first).  The sdk's server itself
listens on 127.0.0.1 at a free port, and only over TLS, with a certificate made at start
that only the gate trusts (pinned): a page that finds that port cannot talk to it (plain
ws:// is no TLS handshake; wss:// meets a certificate no browser accepts, and a
WebSocket has no "accept anyway"), so the gate cannot be bypassed from a browser.  The
gate runs on its own thread and event loop: a slow or hostile client never touches the
companion's loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import ipaddress
import logging
import os
import ssl
import threading
from collections.abc import Iterable, Sequence

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

log = logging.getLogger("cdprd")

INNER_HOST = "127.0.0.1"
MAX_HEAD = 16 * 1024  # bytes of request line and headers before the gate gives up
HEAD_TIMEOUT = 10.0  # s a client may take to send them
START_TIMEOUT = 10.0  # s to bind
PIPE_CHUNK = 64 * 1024
LOGGED_REFUSALS = 64  # distinct reasons logged; more refusals are counted only
_VALIDITY = datetime.timedelta(days=36500)  # the pinned certificate never expires in use


class GateError(OSError):
    """The gate could not listen (e.g. the port in use); strerror says why."""


def inner_tls() -> tuple[bytes, bytes]:
    """A fresh self-signed certificate for INNER_HOST and its key (PEM, PKCS#8): what
    the sdk's server is given (tls_cert, tls_key), and all the gate trusts."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "cdprd live view")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(days=1))
        .not_valid_after(now + _VALIDITY)
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address(INNER_HOST))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    return cert.public_bytes(serialization.Encoding.PEM), key_pem


def refusal(
    fields: Sequence[tuple[str, str]], origins: Iterable[str], hosts: Iterable[str]
) -> str | None:
    """Why an upgrade request with header `fields` ((name in lower case, value), in
    order) is refused, or None.  `origins`: the allowed Origin values; `hosts`: the
    allowed Host names (no port).  Exactly one Host, at most one Origin."""
    host = [value for name, value in fields if name == "host"]
    origin = [value for name, value in fields if name == "origin"]
    if len(host) != 1 or len(origin) > 1:
        return f"{len(host)} Host and {len(origin)} Origin headers"
    if host_name(host[0]) not in {h.lower() for h in hosts}:
        return f"Host {host[0][:100]!r} is not this view's address"
    if origin and origin[0].lower() not in {o.lower() for o in origins}:
        return f"Origin {origin[0][:100]!r} is not in view.allowed_origins"
    return None


def host_name(host: str) -> str:
    """A Host header's name without its port, lower case: '[::1]:8765' -> '::1'."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:].split("]", 1)[0]
    if host.count(":") == 1:
        host = host.split(":", 1)[0]
    return host.rstrip(".")


def _fields(head: bytes) -> list[tuple[str, str]]:
    """The header fields of a request head: (name in lower case, value), in order."""
    out = []
    for line in head.decode("latin-1").split("\r\n")[1:]:
        name, sep, value = line.partition(":")
        if sep:
            out.append((name.strip().lower(), value.strip()))
    return out


class ViewGate:
    """Listens on (host, port) on a thread of its own and lets the requests `refusal`
    has no objection to through to the sdk's server on INNER_HOST:`inner_port`, which
    presents `cert` (PEM).  close() stops it and every connection through it."""

    def __init__(
        self,
        host: str,
        port: int,
        inner_port: int,
        cert: bytes,
        origins: Iterable[str],
        hosts: Iterable[str],
    ) -> None:
        self._inner_port = inner_port
        self._origins = tuple(origins)
        self._hosts = tuple(hosts)
        self._tls = ssl.create_default_context(cadata=cert.decode())
        self._tls.verify_flags &= ~ssl.VERIFY_X509_STRICT  # a self-signed, pinned certificate
        self._logged: set[str] = set()  # the reasons logged
        self.refused = 0
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="cdprd-view-gate", daemon=True
        )
        self._thread.start()
        self._connections: set[asyncio.Task[None]] = set()
        opening = asyncio.run_coroutine_threadsafe(
            asyncio.start_server(self._serve, host, port), self._loop
        )
        try:
            self._server = opening.result(START_TIMEOUT)
        except OSError as exc:
            self._stop_loop()
            reason = os.strerror(exc.errno) if exc.errno else str(exc)
            raise GateError(exc.errno, reason) from None
        self.port: int = self._server.sockets[0].getsockname()[1]

    def close(self) -> None:
        async def shut() -> None:
            self._server.close()
            for task in list(self._connections):
                task.cancel()
            if self._connections:
                await asyncio.wait(self._connections)

        with contextlib.suppress(RuntimeError, TimeoutError):  # the loop is already gone
            asyncio.run_coroutine_threadsafe(shut(), self._loop).result(START_TIMEOUT)
        self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT)
        self._loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        try:
            await self._connection(reader, writer)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
            pass  # a client that left, stalled or sent too long a head: nothing to answer
        finally:
            self._connections.discard(task)
            writer.close()

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async with asyncio.timeout(HEAD_TIMEOUT):
            head = await _read_head(reader)
        fields = _fields(head)
        why = refusal(fields, self._origins, self._hosts)
        if why is not None:
            self._refuse(writer, why)
            await writer.drain()
            return
        inner_reader, inner_writer = await asyncio.open_connection(
            INNER_HOST, self._inner_port, ssl=self._tls, server_hostname=INNER_HOST
        )
        try:
            inner_writer.write(head)
            pipes = [_pipe(reader, inner_writer), _pipe(inner_reader, writer)]
            _, pending = await asyncio.wait(
                [asyncio.ensure_future(p) for p in pipes], return_when=asyncio.FIRST_COMPLETED
            )
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        finally:
            inner_writer.close()

    def _refuse(self, writer: asyncio.StreamWriter, why: str) -> None:
        """Answer 403 naming why; log each reason once (LOGGED_REFUSALS at most: a page
        may retry forever), count every refusal."""
        self.refused += 1
        if why not in self._logged and len(self._logged) < LOGGED_REFUSALS:
            self._logged.add(why)
            log.warning("live view: refused a connection: %s", why)
        body = f"refused: {why}\n".encode()
        writer.write(
            b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain; charset=utf-8\r\n"
            + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
            + body
        )


async def _read_head(reader: asyncio.StreamReader) -> bytes:
    """The request line and headers, through the blank line (at most MAX_HEAD bytes)."""
    head = b""
    while not head.endswith(b"\r\n\r\n"):
        line = await reader.readuntil(b"\n")
        head += line
        if len(head) > MAX_HEAD:
            raise asyncio.LimitOverrunError("request head too long", len(head))
    return head


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    with contextlib.suppress(OSError):
        while chunk := await source.read(PIPE_CHUNK):
            sink.write(chunk)
            await sink.drain()
