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
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import zenoh

from cdpr.trajectory import SCHEMA_VERSION, Trajectory
from daemon.config.zenoh_config import DEFAULT_LISTEN, client_zenoh_config

DEFAULT_CONNECT = DEFAULT_LISTEN
DEFAULT_TIMEOUT = 5.0  # s; a trajectory is validated along its whole path before the reply
DISCOVERY_KEY = "cdpr/*/alive"


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
    keys for the session (e.g. {"transport": {"link": {"tls": {...}}}}, docs/zenoh.md).
    """

    def __init__(
        self,
        prefix: str | None = None,
        connect: str | Sequence[str] = DEFAULT_CONNECT,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        zenoh_config: dict[str, Any] | None = None,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.timeout = timeout
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
        """Run `command` with the JSON `body`; its "result", or RequestError."""
        return self._query(f"cmd/{command}", body)["result"]

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

    def home(self, pose: str | None = None) -> dict[str, Any]:
        """Home at the robot file's pose `pose` (default: its home pose), where the
        platform rests now: every cable's length offset set and stored."""
        return self.request("home", None if pose is None else {"pose": pose})

    def pretension(self, pose: str | None = None) -> dict[str, Any]:
        """Wind the slack cables in, tension them and close the position loop, the
        platform resting on a fixture at the robot file's pose `pose` (default home)."""
        return self.request("pretension", None if pose is None else {"pose": pose})

    def goto(
        self, position: Sequence[float], quaternion: Mapping[str, float] | None = None
    ) -> dict[str, Any]:
        """Move to `position` (m) with `quaternion` {w, x, y, z} (default: identity)."""
        body: dict[str, Any] = {"position": [float(c) for c in position]}
        if quaternion is not None:
            body["quaternion"] = dict(quaternion)
        return self.request("goto", body)

    def identify_payload(self, apply: bool = False) -> dict[str, Any]:
        """Hold a few poses and estimate the payload statically (applied if `apply`)."""
        return self.request("identify_payload", {"apply": apply})

    def payload(
        self,
        frozen: bool | None = None,
        mass: float | None = None,
        center_of_mass: Sequence[float] | None = None,
        lease: float | None = None,
    ) -> dict[str, Any]:
        """The payload estimate; freeze or unfreeze it, or set mass and centre of mass.
        A freeze with a `lease` (s) lapses unless renewed (frozen again) within it."""
        body: dict[str, Any] = {}
        if frozen is not None:
            body["frozen"] = frozen
        if mass is not None:
            body["mass"] = float(mass)
            body["center_of_mass"] = [float(c) for c in center_of_mass or ()]
        if lease is not None:
            body["lease"] = float(lease)
        return self.request("payload", body)

    def observer(self, held: bool | None = None, lease: float | None = None) -> dict[str, Any]:
        """The external wrench observer; hold it out of the loop, or let it back in.  A
        hold with a `lease` (s) lapses unless renewed (held again) within it."""
        body: dict[str, Any] = {} if held is None else {"held": held}
        if lease is not None:
            body["lease"] = float(lease)
        return self.request("observer", body)

    def send_trajectory(
        self,
        trajectory: Trajectory | Mapping[str, Any],
        *,
        start: float | None = None,
        request_id: str | None = None,
    ) -> dict[str, Any]:
        """Submit a trajectory (a Trajectory or its JSON form, cdpr/trajectory/parse.py).

        start: unix time (s) at which its first waypoint is due; None: now.
        Returns the accepted reply (with "id" and "result"); RequestError says which
        limit, waypoint and value made the daemon reject it.
        """
        body = dict(trajectory.as_dict() if isinstance(trajectory, Trajectory) else trajectory)
        body.setdefault("version", SCHEMA_VERSION)
        body["id"] = request_id or body.get("id") or uuid.uuid4().hex[:16]
        body["start"] = "now" if start is None else float(start)
        return self._query("trajectory", body)

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
