"""A Foxglove WebSocket protocol client for tests, written from the published protocol
(github.com/foxglove/ws-protocol, spec v1), not from the server's code: JSON text
frames "serverInfo" / "advertise" / "subscribe", binary "messageData" frames (opcode
0x01, u32 subscription id, u64 log time in ns, payload, little-endian); and decoding of
the payloads by their advertised schema (protobuf via mcap-protobuf-support, JSON)."""

from __future__ import annotations

import base64
import json
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01


def decoder(
    message_encoding: str, schema_name: str, schema_encoding: str, schema_data: bytes
) -> Callable[[bytes], Any]:
    """A function from a payload to the decoded message (a protobuf message or JSON)."""
    if message_encoding == "json":
        return json.loads
    schema = Schema(id=1, name=schema_name, encoding=schema_encoding, data=schema_data)
    decode = DecoderFactory().decoder_for(message_encoding, schema)
    assert decode is not None, f"cannot decode {message_encoding} / {schema_name}"
    return decode


@dataclass
class Received:
    topic: str
    schema_name: str
    log_time: int
    message: Any


class Subscriber:
    """A connection that subscribes to every channel the server advertises."""

    def __init__(self, url: str, connect_timeout: float = 20.0) -> None:
        end = time.monotonic() + connect_timeout
        while True:
            try:
                self.ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=2.0)
                break
            except OSError:
                assert time.monotonic() < end, f"no server at {url}"
                time.sleep(0.1)
        self.subprotocol = self.ws.subprotocol or ""
        self.channels: dict[str, dict] = {}  # advertised, by topic
        self._subscribed: dict[int, tuple[dict, Callable[[bytes], Any]]] = {}

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.ws.close()

    def receive(self, timeout: float) -> Received | None:
        """The next message of a subscribed channel, decoded; None if none within
        `timeout` s (advertisements met on the way are subscribed to)."""
        end = time.monotonic() + timeout
        while True:
            try:
                frame = self.ws.recv(timeout=max(end - time.monotonic(), 0.001))
            except TimeoutError:
                return None
            if isinstance(frame, str):
                body = json.loads(frame)
                if body["op"] == "advertise":
                    self._subscribe(body["channels"])
                continue
            assert frame[0] == MESSAGE_DATA, f"unexpected binary opcode {frame[0]}"
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            channel, decode = self._subscribed[subscription]
            topic = channel["topic"]
            return Received(topic, channel["schemaName"], log_time, decode(frame[13:]))

    def _subscribe(self, channels: list[dict]) -> None:
        subscriptions = []
        for channel in channels:
            ident = len(self._subscribed)
            self.channels[channel["topic"]] = channel
            self._subscribed[ident] = (channel, _decoder_of(channel))
            subscriptions.append({"id": ident, "channelId": channel["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))


def collect(
    url: str, topics: set[str], timeout: float = 20.0
) -> tuple[str, dict[str, dict], dict[str, Received]]:
    """Subscribe to everything and read until one message of each of `topics` has
    arrived: the negotiated subprotocol, the advertised channels by topic, the first
    message of each topic."""
    first: dict[str, Received] = {}
    with Subscriber(url) as subscriber:
        end = time.monotonic() + timeout
        while not topics <= first.keys():
            received = subscriber.receive(end - time.monotonic())
            if received is None:
                raise AssertionError(f"only {sorted(first)} of {sorted(topics)} arrived")
            first.setdefault(received.topic, received)
        return subscriber.subprotocol, subscriber.channels, first


def watch(url: str, seconds: float) -> None:
    """Subscribe to everything for `seconds`, printing how many messages have arrived
    and decoded so far once a second (bench/loop.py --view's viewer, which may be
    stopped at any time)."""
    count = 0
    with Subscriber(url, connect_timeout=seconds) as subscriber:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            second = time.monotonic() + min(left, 1.0)
            while (now := time.monotonic()) < second:
                count += subscriber.receive(second - now) is not None
            print(count, flush=True)


def _decoder_of(channel: dict) -> Callable[[bytes], Any]:
    data = channel["schema"]
    # binary schemas (protobuf's FileDescriptorSet) are base64 in the advertisement
    raw = base64.b64decode(data) if channel["schemaEncoding"] == "protobuf" else data.encode()
    return decoder(channel["encoding"], channel["schemaName"], channel["schemaEncoding"], raw)


if __name__ == "__main__":  # python -m tests.foxglove_client URL SECONDS
    watch(sys.argv[1], float(sys.argv[2]))
