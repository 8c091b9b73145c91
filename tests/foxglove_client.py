"""A Foxglove WebSocket protocol client for tests, written from the published protocol
(github.com/foxglove/ws-protocol, spec v1), not from the server's code: JSON text
frames "serverInfo" / "advertise" / "subscribe", binary "messageData" frames (opcode
0x01, u32 subscription id, u64 log time in ns, payload, little-endian); and decoding of
the payloads by their advertised schema (protobuf via mcap-protobuf-support, JSON)."""

from __future__ import annotations

import base64
import json
import struct
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


def collect(
    url: str, topics: set[str], timeout: float = 20.0, connect_timeout: float = 20.0
) -> tuple[str, dict[str, dict], dict[str, Received]]:
    """Connect (retrying until `connect_timeout`), subscribe to every advertised channel,
    and read until one message of each of `topics` has arrived: the negotiated
    subprotocol, the advertised channels by topic, the first message of each topic."""
    end = time.monotonic() + connect_timeout
    while True:
        try:
            ws = connect(url, subprotocols=SUBPROTOCOLS, open_timeout=2.0)
            break
        except OSError:
            assert time.monotonic() < end, f"no server at {url}"
            time.sleep(0.1)
    channels: dict[str, dict] = {}
    by_subscription: dict[int, tuple[dict, Callable[[bytes], Any]]] = {}
    first: dict[str, Received] = {}
    with ws:
        end = time.monotonic() + timeout
        while not topics <= first.keys():
            try:
                frame = ws.recv(timeout=max(end - time.monotonic(), 0.01))
            except TimeoutError:
                raise AssertionError(f"only {sorted(first)} of {sorted(topics)} arrived") from None
            if isinstance(frame, str):
                body = json.loads(frame)
                if body["op"] == "advertise":
                    subscriptions = []
                    for channel in body["channels"]:
                        ident = len(by_subscription) + len(subscriptions)
                        channels[channel["topic"]] = channel
                        by_subscription[ident] = (channel, _decoder_of(channel))
                        subscriptions.append({"id": ident, "channelId": channel["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
                continue
            assert frame[0] == MESSAGE_DATA, f"unexpected binary opcode {frame[0]}"
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            channel, decode = by_subscription[subscription]
            if channel["topic"] not in first:
                first[channel["topic"]] = Received(
                    channel["topic"], channel["schemaName"], log_time, decode(frame[13:])
                )
        return ws.subprotocol or "", channels, first


def _decoder_of(channel: dict) -> Callable[[bytes], Any]:
    data = channel["schema"]
    # binary schemas (protobuf's FileDescriptorSet) are base64 in the advertisement
    raw = base64.b64decode(data) if channel["schemaEncoding"] == "protobuf" else data.encode()
    return decoder(channel["encoding"], channel["schemaName"], channel["schemaEncoding"], raw)
