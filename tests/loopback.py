"""Loopback helpers shared by the tests that run zenoh or socketcand endpoints."""

from __future__ import annotations

import json
import socket

import zenoh


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zenoh_peer(port: int) -> zenoh.Session:
    """A zenoh peer that connects to tcp/127.0.0.1:`port` only: no listening, no
    multicast scouting, no gossip (what a planner on the same host would open)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)
