"""The `zenoh:` config section and the zenoh.Config built from it (DESIGN §10, §14).

Safe by default: the daemon listens on tcp/127.0.0.1:7448 only, multicast scouting and
gossip are OFF whatever the raw zenoh config says, and any endpoint that is not on
loopback is refused unless `expose: true` is set (see docs/reference/zenoh-api.md for TLS and access
control).  The raw `config:` dict passes everything else (transport/link/tls,
access_control, ...) to zenoh unchanged; it is checked by zenoh at load time.
"""

from __future__ import annotations

import errno
import ipaddress
import json
import re
import socket
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import zenoh
from pydantic import Field, field_validator, model_validator

from cdpr.description import PositiveFloat, StrictModel

# one above 7447, which zenoh routers take by default (rmw_zenohd, the ROS 2 router, too):
# a daemon and a ROS 2 graph on one host must not both want it
DEFAULT_PORT = 7448
DEFAULT_LISTEN = f"tcp/127.0.0.1:{DEFAULT_PORT}"
PROTOCOLS = ("tcp", "tls", "quic", "udp", "ws", "unixsock-stream")
_LOCAL_PROTOCOLS = ("unixsock-stream",)  # no network address at all
# key paths of the raw config that the typed fields own (so they cannot be bypassed)
_OWNED_PATHS = ("mode", "listen", "connect", "scouting", "transport/shared_memory")
_RX_LIMIT = "transport/link/rx/max_message_size"
_PREFIX_PATTERN = r"^[A-Za-z0-9_\-.]+(/[A-Za-z0-9_\-.]+)*$"
_RELATIVE_KEY_PATTERN = r"^([A-Za-z0-9_\-.]+|\*\*?)(/([A-Za-z0-9_\-.]+|\*\*?))*$"


class ZenohSettings(StrictModel):
    """The `zenoh:` section of a robot config (every key optional)."""

    prefix: str | None = Field(None, max_length=200)
    """Key prefix of every key the daemon serves; None: cdpr/<robot name>."""
    mode: Literal["peer", "client"] = "peer"
    """peer: the daemon listens itself; client: it connects to a zenohd router."""
    listen: tuple[str, ...] | None = None
    """Endpoints to listen on; None: [tcp/127.0.0.1:7448] as a peer, none as a client."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to (a router, or other peers)."""
    expose: bool = False
    """Allow endpoints off loopback (and multicast scouting): an explicit network choice."""
    multicast_scouting: bool = False
    """zenoh's multicast scouting: announce the daemon and find peers on the local
    network; needs expose."""
    gossip: bool = False
    """zenoh's gossip scouting: peers tell each other of the peers they know."""
    shared_memory: bool = False
    """zenoh's shared-memory transport maps a 16 MiB pool per local peer that sends
    payloads over 3 KiB, and keeps it: off, since the messages here are small."""
    state_rate_hz: PositiveFloat = Field(50.0, le=1000.0)
    """Hz: how often the daemon publishes its state (key <prefix>/state)."""
    max_message_bytes: int = Field(2 * 1024 * 1024, ge=1024, le=256 * 1024 * 1024)
    """Trajectory and command payloads above this size are refused unread."""
    max_waypoints: int = Field(10000, ge=2)
    """The most waypoints a trajectory from zenoh or ROS 2 may have; the lower of this and
    trajectory.max_waypoints applies."""
    queue_depth: int = Field(16, ge=1, le=4096)
    """Per inbound queue (trajectories, commands) and for outgoing events; overflow drops."""
    ingress_limits_hz: dict[str, PositiveFloat] = Field(default_factory=dict)
    """Per key under the prefix (`trajectory`, `cmd/status`, `cmd/*`, ...): zenoh drops
    inbound puts and queries on it that come sooner than 1/limit after the last one it
    let through, before the daemon sees them: a flood then costs the control loop
    next to nothing, a dropped query times out at its sender.  Empty: no limits."""
    config: dict[str, Any] = Field(default_factory=dict)
    """Raw zenoh config (json5 keys, e.g. transport, access_control); see
    docs/reference/zenoh-api.md."""

    @field_validator("prefix")
    @classmethod
    def _plain_prefix(cls, prefix: str | None) -> str | None:
        if prefix is not None and not re.fullmatch(_PREFIX_PATTERN, prefix):
            raise ValueError(
                "a prefix is plain key chunks (letters, digits, _ - .) joined by '/': "
                "no wildcards, no leading or trailing '/'"
            )
        return prefix

    @field_validator("ingress_limits_hz")
    @classmethod
    def _limited_keys(cls, limits: dict[str, float]) -> dict[str, float]:
        for key in limits:
            if not re.fullmatch(_RELATIVE_KEY_PATTERN, key):
                raise ValueError(
                    f"{key!r} is not a key under the prefix: key chunks (letters, digits, "
                    "_ - ., or a * / ** wildcard) joined by '/', no leading '/'"
                )
        return limits

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints_parse(cls, endpoints: tuple[str, ...] | None) -> tuple[str, ...] | None:
        for endpoint in endpoints or ():
            endpoint_host(endpoint)
        return endpoints

    @field_validator("config")
    @classmethod
    def _raw_config(cls, raw: dict[str, Any]) -> dict[str, Any]:
        owned = _owned_keys(raw)
        if owned:
            raise ValueError(
                f"key(s) {', '.join(owned)} are set by zenoh.mode/listen/connect/"
                "multicast_scouting/gossip/shared_memory, not inside zenoh.config"
            )
        _apply_raw(zenoh.Config(), raw)  # zenoh names any unknown or ill-typed key
        return raw

    @model_validator(mode="after")
    def _placement(self) -> ZenohSettings:
        if self.ingress_limits_hz and "downsampling" in self.config:
            raise ValueError(
                "zenoh.ingress_limits_hz and a raw zenoh.config downsampling both set "
                "zenoh's downsampling: use one of them"
            )
        if self.mode == "client" and self.listen:
            raise ValueError("a client does not listen: remove zenoh.listen or use mode: peer")
        if self.mode == "client" and not self.connect:
            raise ValueError("mode: client needs zenoh.connect (the router's endpoint)")
        if not self.expose:
            for key, endpoints in (("listen", self.listen_endpoints), ("connect", self.connect)):
                for endpoint in endpoints:
                    if not is_local(endpoint):
                        raise ValueError(
                            f"zenoh.{key} endpoint {endpoint!r} is not on loopback; exposing "
                            "the daemon on a network is an explicit choice: set "
                            "zenoh.expose: true and configure TLS and access control "
                            "(docs/reference/zenoh-api.md), or use tcp/127.0.0.1:<port>"
                        )
            if self.multicast_scouting:
                raise ValueError(
                    "zenoh.multicast_scouting announces the daemon on the local network; "
                    "set zenoh.expose: true as well if that is intended"
                )
        return self

    @property
    def listen_endpoints(self) -> tuple[str, ...]:
        if self.listen is not None:
            return self.listen
        return (DEFAULT_LISTEN,) if self.mode == "peer" else ()

    def ingress_limit(self, key: str) -> float | None:
        """The lowest of the ingress_limits_hz entries whose key matches `key` (a key
        under the prefix); None: `key` is not limited."""
        target = zenoh.KeyExpr(key)
        rates = [
            hz for pattern, hz in self.ingress_limits_hz.items()
            if zenoh.KeyExpr(pattern).intersects(target)
        ]  # fmt: skip
        return min(rates, default=None)

    def key_prefix(self, robot_name: str) -> str:
        """The configured prefix, else cdpr/<robot_name>."""
        return self.prefix if self.prefix is not None else f"cdpr/{robot_name}"


def build_zenoh_config(
    settings: ZenohSettings, prefix: str, ingress_limits: Mapping[str, float] | None = None
) -> zenoh.Config:
    """The daemon's zenoh.Config for keys under `prefix`: raw keys first, then the typed
    fields on top of them.  `ingress_limits` (full key -> Hz) are limited as
    zenoh.ingress_limits_hz is: keys outside the prefix the daemon takes in (ROS 2)."""
    conf = zenoh.Config()
    _apply_raw(conf, settings.config)
    limits = {f"{prefix}/{key}": hz for key, hz in settings.ingress_limits_hz.items()}
    limits.update(ingress_limits or {})
    if limits:
        rules = [{"key_expr": key, "freq": hz} for key, hz in limits.items()]
        downsampling = [{"flows": ["ingress"], "messages": ["put", "query"], "rules": rules}]
        conf.insert_json5("downsampling", json.dumps(downsampling))
    if conf.get_json(_RX_LIMIT) == zenoh.Config().get_json(_RX_LIMIT):
        # zenoh itself drops anything far above our limit; moderately oversized messages
        # still arrive, so that the sender gets a clear "too large" reply
        conf.insert_json5(_RX_LIMIT, str(max(4 * settings.max_message_bytes, 1 << 20)))
    _place(conf, settings.mode, settings.listen_endpoints, settings.connect)
    _restrict(conf, settings.multicast_scouting, settings.gossip, settings.shared_memory)
    return conf


def client_zenoh_config(connect: Sequence[str], raw: dict[str, Any] | None = None) -> zenoh.Config:
    """A client session to a daemon (or router): no listening, no scouting, no gossip."""
    for endpoint in connect:
        endpoint_host(endpoint)
    owned = _owned_keys(raw or {})
    if owned:
        raise ValueError(f"raw client config must not set {', '.join(owned)}")
    conf = zenoh.Config()
    _apply_raw(conf, raw or {})
    _place(conf, "client", [], connect)
    _restrict(conf, False, False, False)
    return conf


def endpoint_host(endpoint: str) -> str | None:
    """The host of a zenoh endpoint 'proto/host:port[?meta][#config]'; None for a socket path.

    ValueError names the problem when the endpoint is not of that form.
    """
    if not isinstance(endpoint, str) or "/" not in endpoint:
        raise ValueError(f"endpoint {endpoint!r} is not of the form <protocol>/<host>:<port>")
    protocol, address = endpoint.split("/", 1)
    if protocol not in PROTOCOLS:
        raise ValueError(
            f"endpoint {endpoint!r}: protocol {protocol!r} is not one of {', '.join(PROTOCOLS)}"
        )
    address = address.split("#", 1)[0].split("?", 1)[0]
    if protocol in _LOCAL_PROTOCOLS:
        if not address:
            raise ValueError(f"endpoint {endpoint!r} has no socket path")
        return None
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"endpoint {endpoint!r} is not of the form {protocol}/<host>:<port>")
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def _tcp_address(endpoint: str) -> tuple[socket.AddressFamily, str, int] | None:
    """The socket family, host and port of a TCP endpoint (tcp/, tls/); None for others."""
    protocol = endpoint.split("/", 1)[0]
    host = endpoint_host(endpoint)
    if protocol not in ("tcp", "tls") or host is None:
        return None
    port = int(endpoint.split("#", 1)[0].split("?", 1)[0].rpartition(":")[2])
    return (socket.AF_INET6 if ":" in host else socket.AF_INET), host, port


def taken(endpoint: str) -> bool:
    """True when a TCP endpoint (tcp/, tls/) names a port something on this host already
    listens on, so that zenoh's listener would fail ("Address already in use"); bound
    as zenoh binds (SO_REUSEADDR), so a closing connection does not count.  False for
    other protocols, and where binding fails for another reason (zenoh will say)."""
    address = _tcp_address(endpoint)
    if address is None:
        return False
    family, host, port = address
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE
    return False


def answers(endpoint: str, timeout: float = 0.5) -> bool:
    """True when something accepts a TCP connection at a tcp/ or tls/ endpoint now (a
    router that is up); False when nothing does, or for other protocols."""
    address = _tcp_address(endpoint)
    if address is None:
        return False
    family, host, port = address
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.settimeout(timeout)
        return probe.connect_ex((host, port)) == 0


def is_local(endpoint: str) -> bool:
    """True when the endpoint cannot be reached from another machine (loopback or a socket)."""
    host = endpoint_host(endpoint)
    return host is None or loopback_host(host)


def loopback_host(host: str) -> bool:
    """True for "localhost" and loopback addresses; a host name may resolve to anything."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _owned_keys(raw: dict[str, Any]) -> list[str]:
    """The raw keys (nested, or paths such as 'scouting/gossip') the typed fields own."""
    owned = set()
    for path in _leaf_paths(raw):
        for mine in _OWNED_PATHS:
            if path == mine or path.startswith(mine + "/") or mine.startswith(path + "/"):
                owned.add(path)
    return sorted(owned)


def _leaf_paths(raw: dict[str, Any], prefix: str = "") -> list[str]:
    paths = []
    for key, value in raw.items():
        path = f"{prefix}/{key.strip('/')}".strip("/")
        paths += _leaf_paths(value, path) if isinstance(value, dict) and value else [path]
    return paths


def _apply_raw(conf: zenoh.Config, raw: dict[str, Any]) -> None:
    for key, value in raw.items():
        try:
            conf.insert_json5(key, json.dumps(value, allow_nan=False))
        except (ValueError, TypeError) as exc:  # not JSON-able
            raise ValueError(f"{key}: {exc}") from None
        except zenoh.ZError as exc:
            raise ValueError(f"{key}: {zenoh_reason(exc)}") from None


def _place(conf: zenoh.Config, mode: str, listen: Sequence[str], connect: Sequence[str]) -> None:
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))


def _restrict(conf: zenoh.Config, multicast: bool, gossip: bool, shared_memory: bool) -> None:
    """Multicast scouting, gossip and shared memory: each only when asked for."""
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    conf.insert_json5("scouting/gossip/enabled", json.dumps(gossip))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))


def zenoh_reason(exc: Exception) -> str:
    """The readable part of a zenoh error, on one line (the Rust wrapping and the source
    locations dropped)."""
    text = str(exc)
    found = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text)
    if found:
        return found.group(1).replace('\\"', '"')
    return " ".join(re.sub(r" at \S+\.rs:\d+\.?", "", text).split())
