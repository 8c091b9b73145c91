"""A small client of the daemon's zenoh interface, for planners and the `cdprd` CLI.

    from daemon.interface.client import CdprClient
    with CdprClient("cdpr/reference8") as robot:
        robot.enable()
        robot.send_trajectory({"waypoints": [...]})      # returns the accepted body
        robot.subscribe_state(lambda state: print(state["seq"]))

Every call is a zenoh query: the daemon's reply says accepted or why not, so the sender
always gets the reason (a refusal raises RequestError with its code and reason; no
reply raises UnreachableError).  Planners that publish trajectories with a plain put
instead get the same outcome on <prefix>/events, matched by the "id" they chose.

Every request names the client (`client`, default user@host:pid): the daemon records it
in its events, and keeps one client's motion from being replaced by another's unless the
request preempts (docs/reference/zenoh-api.md, "One owner per motion").  The client keeps the id of
each lease it took and sends it with the renewal and the release.
"""

from __future__ import annotations

import getpass
import json
import os
import socket
import threading
import uuid
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import zenoh

from cdpr.path import Path
from cdpr.trajectory import SCHEMA_VERSION, Trajectory
from daemon.config.zenoh_config import DEFAULT_LISTEN, client_zenoh_config

DEFAULT_CONNECT = DEFAULT_LISTEN
CONNECT_ENV = "CDPRD_CONNECT"  # the command-line clients' endpoint when --connect is not given
DEFAULT_TIMEOUT = 5.0  # s; a trajectory is validated along its whole path before the reply
DISCOVERY_KEY = "cdpr/*/alive"


def default_connect() -> str:
    """The endpoint a command-line client connects to without --connect: $CDPRD_CONNECT
    if set (a daemon on another port or host, for every command of a shell), else
    DEFAULT_CONNECT."""
    return os.environ.get(CONNECT_ENV) or DEFAULT_CONNECT


def default_client_name() -> str:
    """user@host:pid: who this process is, as the daemon records it."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (a container)
        user = str(os.getuid())
    return f"{user}@{socket.gethostname()}:{os.getpid()}"[:128]


class ClientError(Exception):
    """Base of the client's errors."""


class UnreachableError(ClientError):
    """No session to the endpoint, or no daemon answered within the timeout."""


class RequestError(ClientError):
    """The daemon answered with an error: `code` (machine), `reason`, the whole `reply`."""

    def __init__(self, reply: dict[str, Any]) -> None:
        error = reply.get("error") if isinstance(reply.get("error"), dict) else {}
        self.reply = reply
        self.code = str(error.get("code", "internal"))
        self.reason = str(error.get("reason", "the daemon sent no reason"))
        super().__init__(f"{self.code}: {self.reason}")


class CdprClient:
    """A zenoh client session to one daemon, addressed by its key prefix.

    prefix None: the only daemon whose liveliness token answers on cdpr/*/alive.
    connect: the endpoint(s) of the daemon or of a router.  zenoh_config: raw zenoh
    keys for the session (e.g. {"transport": {"link": {"tls": {...}}}},
    docs/reference/zenoh-api.md).
    name: the client's name in every request (default_client_name()).
    """

    def __init__(
        self,
        prefix: str | None = None,
        connect: str | Sequence[str] = DEFAULT_CONNECT,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        zenoh_config: dict[str, Any] | None = None,
        name: str | None = None,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.timeout = timeout
        self.name = default_client_name() if name is None else name
        self.lease_ids: dict[str, str] = {}  # the leases this client holds, by command
        self._lease_lock = threading.Lock()  # renewals may come from a thread of their own
        try:
            conf = client_zenoh_config(endpoints, zenoh_config)
        except ValueError as exc:
            raise ClientError(str(exc)) from None
        try:
            self._session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise UnreachableError(
                f"cannot connect to {', '.join(endpoints)}: {_zenoh_text(exc)}"
            ) from None
        try:
            self.prefix = prefix if prefix is not None else self._discover()
        except ClientError:
            self.close()
            raise

    def close(self) -> None:
        self._session.close()

    def __enter__(self) -> CdprClient:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- commands ----------------------------------------------------------------------

    def request(self, command: str, body: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Run `command` with the JSON `body` (and this client's name); its "result", or
        RequestError."""
        return self._query(f"cmd/{command}", {"client": self.name, **(body or {})})["result"]

    def status(self) -> dict[str, Any]:
        return self.request("status")

    def enable(self) -> dict[str, Any]:
        return self.request("enable")

    def disable(self) -> dict[str, Any]:
        return self.request("disable")

    def hold(self) -> dict[str, Any]:
        return self.request("hold")

    def brake(self, reason: str | None = None) -> dict[str, Any]:
        return self.request("brake", None if reason is None else {"reason": reason})

    def reset(self) -> dict[str, Any]:
        return self.request("reset")

    def home(self, pose: str | None = None, preempt: bool = False) -> dict[str, Any]:
        """Home at the robot file's pose `pose` (default: its home pose), where the
        platform rests now: every cable's length offset set and stored.  `preempt`:
        replace another client's motion (else refused while one runs)."""
        return self.request("home", _preempting({} if pose is None else {"pose": pose}, preempt))

    def pretension(self, pose: str | None = None, preempt: bool = False) -> dict[str, Any]:
        """Wind the slack cables in, tension them and close the position loop, the
        platform resting on a fixture at the robot file's pose `pose` (default home)."""
        body = {} if pose is None else {"pose": pose}
        return self.request("pretension", _preempting(body, preempt))

    def goto(
        self,
        position: Sequence[float],
        quaternion: Mapping[str, float] | None = None,
        preempt: bool = False,
    ) -> dict[str, Any]:
        """Move to `position` (m) with `quaternion` {w, x, y, z} (default: identity)."""
        body: dict[str, Any] = {"position": [float(c) for c in position]}
        if quaternion is not None:
            body["quaternion"] = dict(quaternion)
        return self.request("goto", _preempting(body, preempt))

    def identify_payload(self, apply: bool = False, preempt: bool = False) -> dict[str, Any]:
        """Hold a few poses and estimate the payload statically (applied if `apply`)."""
        return self.request("identify_payload", _preempting({"apply": apply}, preempt))

    def payload(
        self,
        frozen: bool | None = None,
        mass: float | None = None,
        center_of_mass: Sequence[float] | None = None,
        lease: float | None = None,
        lease_id: str | None = None,
    ) -> dict[str, Any]:
        """The payload estimate; freeze or unfreeze it, or set mass and centre of mass.
        A freeze with a `lease` (s) lapses unless renewed (frozen again) within it; see
        `observer` for `lease_id`."""
        body: dict[str, Any] = {}
        if mass is not None:
            body["mass"] = float(mass)
            body["center_of_mass"] = [float(c) for c in center_of_mass or ()]
        return self._hold("payload", "frozen", frozen, lease, lease_id, body)

    def observer(
        self, held: bool | None = None, lease: float | None = None, lease_id: str | None = None
    ) -> dict[str, Any]:
        """The external wrench observer; hold it out of the loop, or let it back in.  A
        hold with a `lease` (s) lapses unless renewed (held again) within it.  A renewal
        and a release send the lease's id: `lease_id`, else the one this client got
        when it took the lease (lease_ids)."""
        return self._hold("observer", "held", held, lease, lease_id, {})

    def _hold(
        self,
        command: str,
        key: str,
        hold: bool | None,
        lease: float | None,
        lease_id: str | None,
        body: dict[str, Any],
    ) -> dict[str, Any]:
        """`command` with `key` `hold` (none: no change), on a `lease`, sending the
        lease's id; the id of the lease the reply names is kept, a release forgets it."""
        ident = lease_id
        if hold is not None:
            body[key] = hold
            with self._lease_lock:
                ident = self.lease_ids.get(command) if lease_id is None else lease_id
        if ident is not None:  # an id without a change: the daemon refuses it, naming it
            body["lease_id"] = ident
        if lease is not None:
            body["lease"] = float(lease)
        result = self.request(command, body)
        if hold is not None:
            with self._lease_lock:
                if "lease_id" in result:
                    self.lease_ids[command] = result["lease_id"]
                else:
                    self.lease_ids.pop(command, None)
        return result

    def send_trajectory(
        self,
        trajectory: Trajectory | Mapping[str, Any],
        *,
        start: float | None = None,
        request_id: str | None = None,
        preempt: bool = False,
    ) -> dict[str, Any]:
        """Submit a trajectory (a Trajectory or its JSON form, cdpr/trajectory/parse.py).

        start: unix time (s) at which its first waypoint is due; None: now.
        preempt: replace another client's motion (else refused while one runs; this
        client's own trajectory or goto it replaces either way).
        Returns the accepted reply (with "id" and "result"); RequestError says which
        limit, waypoint and value made the daemon reject it.
        """
        body = trajectory.as_dict() if isinstance(trajectory, Trajectory) else trajectory
        return self._query("trajectory", self._envelope(body, start, request_id, preempt))

    def send_path(
        self,
        path: Path | Mapping[str, Any],
        *,
        start: float | None = None,
        request_id: str | None = None,
        preempt: bool = False,
    ) -> dict[str, Any]:
        """Submit a path (a cdpr.path.Path or its JSON form, docs/guide/paths.md): poses
        without times, which the daemon times within the cables' tensions and runs as a
        trajectory; `start`, `request_id`, `preempt` and the reply as send_trajectory's
        (RequestError names the pose, or where no timing holds the tensions)."""
        body = path.as_dict() if isinstance(path, Path) else path
        return self._query("path", self._envelope(body, start, request_id, preempt))

    def _envelope(
        self,
        body: Mapping[str, Any],
        start: float | None,
        request_id: str | None,
        preempt: bool,
    ) -> dict[str, Any]:
        """A trajectory's or a path's message: `body` with the version, an id, the start
        and who sends it."""
        message = dict(body)
        message.setdefault("version", SCHEMA_VERSION)
        message["id"] = request_id or message.get("id") or uuid.uuid4().hex[:16]
        message["start"] = "now" if start is None else float(start)
        message["client"] = self.name
        return _preempting(message, preempt)

    # -- streams -----------------------------------------------------------------------

    def subscribe_state(self, callback: Callable[[dict[str, Any]], None]) -> zenoh.Subscriber:
        """Call `callback(state)` on every published state (on a zenoh thread).
        Keep the returned subscriber; undeclare() it to stop."""
        return self._subscribe("state", callback)

    def subscribe_events(self, callback: Callable[[dict[str, Any]], None]) -> zenoh.Subscriber:
        """Call `callback(event)` on every event (on a zenoh thread)."""
        return self._subscribe("events", callback)

    def alive(self) -> bool:
        """Whether the daemon's liveliness token is present."""
        replies = self._session.liveliness().get(f"{self.prefix}/alive", timeout=self.timeout)
        return any(reply.ok is not None for reply in replies)

    # -- plumbing ----------------------------------------------------------------------

    def _query(self, name: str, body: Mapping[str, Any] | None) -> dict[str, Any]:
        key = f"{self.prefix}/{name}"
        try:
            payload = None if body is None else json.dumps(body, allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            raise ClientError(f"{key}: the request is not strict JSON: {exc}") from None
        for reply in self._session.get(key, payload=payload, timeout=self.timeout):
            sample = reply.ok if reply.ok is not None else reply.err
            data = sample.payload.to_bytes()
            if reply.ok is None and data == b"Timeout":  # zenoh's own, not the daemon's
                break
            answer = _decode_reply(data, key)
            if reply.ok is not None and answer.get("ok") is True:
                return answer
            raise RequestError(answer)
        raise UnreachableError(
            f"no daemon answered on {key} within {self.timeout:g} s (is the prefix right?)"
        )

    def _subscribe(self, name: str, callback: Callable[[dict[str, Any]], None]) -> zenoh.Subscriber:
        def on_sample(sample: zenoh.Sample) -> None:
            callback(json.loads(sample.payload.to_bytes()))

        return self._session.declare_subscriber(f"{self.prefix}/{name}", on_sample)

    def _discover(self) -> str:
        replies = self._session.liveliness().get(DISCOVERY_KEY, timeout=self.timeout)
        found = sorted(
            {str(r.ok.key_expr).removesuffix("/alive") for r in replies if r.ok is not None}
        )
        if not found:
            raise UnreachableError(f"no daemon answers on {DISCOVERY_KEY}")
        if len(found) > 1:
            raise ClientError(f"several daemons answer: {', '.join(found)}; choose a prefix")
        return found[0]


def _preempting(body: dict[str, Any], preempt: bool) -> dict[str, Any]:
    """`body`, saying "preempt": true if `preempt` (nothing otherwise)."""
    return {**body, "preempt": True} if preempt else body


def _decode_reply(payload: bytes, key: str) -> dict[str, Any]:
    try:
        reply = json.loads(payload)
    except ValueError:
        reply = None
    if not isinstance(reply, dict) or reply.get("version") != SCHEMA_VERSION:
        raise ClientError(f"{key}: not a cdprd reply (schema version 1): {payload[:200]!r}")
    return reply


def _zenoh_text(exc: Exception) -> str:
    return str(exc).split(" at /", 1)[0].strip()
