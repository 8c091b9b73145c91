"""The contract between the zenoh interface (daemon/interface/zenoh_io.py) and the daemon service.

The interface owns the network side: it decodes and schema-checks every message, so the
service only ever sees well-formed requests.  The service owns the robot: it decides
whether a command or a trajectory is acceptable now.

Threading: every DaemonHandler method is called ON THE EVENT LOOP thread, one call at a
time, and must return promptly (it shares the loop with the control cycle).
`ZenohInterface.publish_event({"event": "state", ...})` may be called from any thread;
it never blocks (a full queue drops the event and counts it).
"""

from __future__ import annotations

import math
import re
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from cdpr.trajectory import TrajectoryError

if TYPE_CHECKING:
    from cdpr.trajectory import Trajectory

COMMANDS = (
    "enable", "disable", "hold", "brake", "reset", "goto", "status",
    "payload", "identify_payload", "home", "pretension", "observer",
)  # fmt: skip
"""The command names, each served on `<prefix>/cmd/<name>`."""

MOVING = ("hold", "tracking")
"""The published safety states in which the robot follows plans (holds or flies): a
motion runs only in them (daemon.service.motion; SafetyState's values)."""

ERROR_CODES = (
    "bad_request",  # malformed or ill-typed input (the interface says which field)
    "unknown_command",  # not one of COMMANDS
    "invalid_state",  # well-formed, but not allowed in the current safety state
    "rejected",  # a trajectory or goto the robot cannot follow (limit, workspace, ...)
    "drive_error",  # the drives did not do what the command needed
    "busy",  # the interface's queue was full or it is shutting down: retry later
    "not_owner",  # another client owns what it would change: the motion running (unless
    # preempt) or a lease (without its lease_id)
    "preempted",  # a procedure stopped because another request replaced its motion
    "internal",  # the handler raised something other than CommandError (a bug)
)
"""The documented machine codes; a new one is a lower-case snake_case word."""


ANONYMOUS = "anonymous"
"""The client of a request that names none (daemon.service.motion)."""


@dataclass(frozen=True)
class Claim:
    """Who asks for a motion, as its request says: the `client` it names (a name the
    client chooses; recorded in events; not a credential), whether it may replace another
    client's motion (`preempt`), and a trajectory's `id`."""

    client: str = ANONYMOUS
    preempt: bool = False
    id: str | None = None

    @classmethod
    def of(cls, args: dict[str, Any]) -> Claim:
        """The claim of a command's args (the "client" and "preempt" it was sent with)."""
        return cls(args.get("client", ANONYMOUS), bool(args.get("preempt", False)))


UNNAMED = Claim()
"""The claim of a request that names no client and does not preempt."""


class CommandError(Exception):
    """A request the service refuses: `code` for machines, `reason` for people.

    `details` (JSON-able: str, int, finite float, bool, None, lists and dicts of them) is
    added to the error body, e.g. {"limit": "cable_length", "waypoint": 3, "value": 2.1}.
    """

    def __init__(self, code: str, reason: str, **details: Any) -> None:
        if not isinstance(code, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", code):
            code, reason = "internal", f"bad CommandError code {code!r}: {reason}"
        super().__init__(f"{code}: {reason}")
        self.code = code
        self.reason = reason
        self.details = details


def trajectory_error_details(exc: TrajectoryError) -> dict[str, Any]:
    """The machine-readable part of a TrajectoryError, as CommandError details: the
    limit, the waypoint, the field and the value, those it has (a value only if finite)."""
    details = {"limit": exc.limit, "waypoint": exc.waypoint, "field": exc.field}
    if exc.value is not None and math.isfinite(exc.value):
        details["value"] = exc.value
    return {k: v for k, v in details.items() if v is not None}


def rejection(what: str, exc: TrajectoryError) -> CommandError:
    """A TrajectoryError as the refusal "rejected" of `what` (a trajectory, a goto, ...),
    naming the limit, the waypoint, the field and the value (DESIGN §7)."""
    return CommandError("rejected", f"{what} rejected: {exc}", **trajectory_error_details(exc))


class DaemonHandler(Protocol):
    """Implemented by the service; every method runs on the event-loop thread."""

    def command(
        self, name: str, args: dict[str, Any]
    ) -> dict[str, Any] | Awaitable[dict[str, Any]]:
        """Run command `name` (one of COMMANDS): the JSON reply body, or an awaitable of it
        for commands that wait for the drives (the reply is sent when it completes).

        args, already validated: {} for every command, and "client": str where the
        request names its client, "preempt": true where a goto, identify_payload, home
        or pretension says so (Claim.of), except
            goto:  {"pose": cdpr.pose.Pose}  (unit quaternion, normalised)
            brake: {"reason": str} or {}     (the sender's reason, <= 200 characters)
            payload: any of {"frozen": bool, "mass": float (kg),
                             "center_of_mass": [x, y, z] (m, platform frame)}, and
                   "lease": float (s, with frozen true: daemon.service.lease),
                   "lease_id": str (with frozen: the running lease's, to renew or end it)
            identify_payload: {"apply": bool}
            home:  {"pose_name": str} or {}  (a pose of the robot file; default home)
            pretension: as home (the fixture's pose the platform rests at)
            observer: {"held": bool} or {}  (the external wrench observer held out of
                   the loop, or let back in), and "lease", "lease_id" as payload's
        Raise CommandError to refuse (e.g. "invalid_state" for enable while BRAKED).
        """
        ...

    def submit_trajectory(
        self, trajectory: Trajectory, start: float | None, claim: Claim = UNNAMED
    ) -> dict[str, Any] | Awaitable[dict[str, Any]]:
        """Accept a parsed, schema-checked trajectory to run, or raise CommandError;
        or return an awaitable of that (e.g. to validate a long path between cycles).
        `claim`: who sends it (daemon.service.motion: refused with "not_owner" while
        another client's motion runs, unless it preempts).

        start: the unix time (s) at which the trajectory's first waypoint is due, or None
        for "as soon as possible".  The service validates against the robot (limits,
        workspace, approach from the current reference) and either accepts, returning
        a JSON-able body (e.g. {"start": 1718.2, "duration": 4.0}), or raises
        CommandError("rejected", reason, limit=..., waypoint=..., value=...).
        The interface publishes the trajectory_accepted / trajectory_rejected event
        itself (with the sender's id); the service does not.
        """
        ...

    def subscribe(self, sink: Callable[[dict[str, Any]], None]) -> None:
        """Pass every event from now on to `sink` (the core's and the planner's: state
        changes, brake, trajectory_done, motion_preempted, ...), as the zenoh interface
        publishes them: the ROS 2 action server follows its goal by them."""
        ...

    async def slack(self) -> None:
        """Return when the control cycle has slack (no cycle waiting for its feedback, the
        next one not due): the interface publishes the state then, off the cycle's way."""
        ...

    def state(self) -> dict[str, Any]:
        """The state snapshot to publish now (docs/reference/zenoh-api.md, "State and events").

        The interface adds version, seq, time and its own counters ("interface");
        non-finite floats are sent as null; numpy arrays and scalars are accepted.
        """
        ...
