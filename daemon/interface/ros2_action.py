"""The ROS 2 action cdprd_interfaces/action/FlyPath over rmw_zenoh: a nav_msgs/Path flown
with feedback and cancelled by a hold, served as rcl_action and rclcpp_action serve an
action (docs/guide/ros2.md, "Action"; the wire format in daemon.interface.ros2_wire).

Followed (tests/data/rmw_zenoh_reference.md, "Actions"): rcl_action's names
(<action>/_action/send_goal, cancel_goal and get_result, services like the bridge's
others; <action>/_action/feedback and status, topics), its default QoS (the services and
feedback reliable, volatile, keep last 10; the status reliable, transient local, keep
last 1), its cancel rules (rcl_action_process_cancel_request) and its result timeout
(10 s, ros2/rcl#1012); rclcpp_action's answers (a goal accepted is EXECUTING at once,
the status is published on every change, a result asked for an unknown goal is
STATUS_UNKNOWN at once and for a known one sent once the goal is terminal).

Semantics, one goal at a time:
- send_goal: the goal's Path passes the `path` topic's gates (ingress limit, size, the
  pose count its first bytes declare, then decoding and parsing in the zenoh interface's
  parse thread, a stampless Path timed there) and goes to handler.submit_trajectory as
  the anonymous client's (UNNAMED, its id the goal's so that the state's motion names
  it).  Accepted: EXECUTING, and the goal flying before ends ABORTED ("preempted").
  Refused: accepted false, the reason logged and kept as the goal's result (ABORTED,
  "<code>: <reason>"; rclcpp keeps no refused goal and would answer STATUS_UNKNOWN);
  a refused goal is not in the status list.
- The goal ends SUCCEEDED on the core's trajectory_done at or past its end (the message:
  the accepted submission's JSON); ABORTED when the robot leaves hold and tracking (a
  brake, a disable), when a hold from elsewhere stops it, or when another motion takes
  over (another client's: motion_preempted; the anonymous client's own, e.g. a Path on
  the topic: the state's motion, read at the feedback rate).
- cancel_goal: the goals it names (rcl_action's rules: by id, all, by stamp) go
  CANCELING and the `hold` command runs (ZenohInterface.offer_command, like the hold
  service); CANCELED once the hold answers (its JSON as the message), ABORTED with the
  refusal if it is refused (the robot may then still move), SUCCEEDED if the flight
  ended first.  A cancel is never refused: ERROR_REJECTED is not answered.
- Feedback at ros2.rate_hz from handler.state() while the goal executes or cancels.
- Terminal goals are forgotten RESULT_TIMEOUT s after they ended, the oldest at once
  beyond MAX_GOALS; at most MAX_WAITING get_result requests wait per goal.

Hostile input is treated as the bridge's services treat it: a request whose attachment
or CDR does not read, or that repeats a pending (client, sequence number), is dropped
unanswered (ros2_wire.take_request); a wrong type hash reaches no queryable; zenoh's
ingress limits (ingress_limits) hold floods back.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import inspect
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings
from daemon.interface import ros2_wire as wire
from daemon.interface.messages import TrajectoryRequest, decode_command, reply_error
from daemon.interface.ros2_convert import (
    PATH,
    answer_text,
    check_waypoint_count,
    pose_stamped,
    stamp,
    state_pose,
    trajectory_request,
)
from daemon.interface.zenoh_io import MAX_COMMAND_BYTES, ZenohInterface
from daemon.service.api import MOVING, UNNAMED, CommandError, DaemonHandler

log = logging.getLogger(__name__)

ACTION = "cdprd_interfaces/action/FlyPath"
ACTION_FILE = Path(__file__).with_name("cdprd_interfaces") / "action" / "FlyPath.action"
wire.register(wire.action_types(ACTION, ACTION_FILE.read_text()))  # the one definition
SEND_GOAL, GET_RESULT = f"{ACTION}_SendGoal", f"{ACTION}_GetResult"
FEEDBACK, RESULT = f"{ACTION}_FeedbackMessage", f"{ACTION}_Result"
STATUS = "action_msgs/msg/GoalStatusArray"
# rcl_action_qos_profile_status_default: reliable, transient local, keep last 1
STATUS_DEPTH = 1
# action_msgs/msg/GoalStatus and action_msgs/srv/CancelGoal's constants
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = range(4)
ACTIVE = (ACCEPTED, EXECUTING)  # cancelable (rcl_action_goal_handle_is_cancelable)
RESULT_TIMEOUT = 10.0  # s a terminal goal's result is kept (rcl_action's default)
MAX_GOALS = 16  # goals remembered at most (the oldest terminal ones forgotten first)
MAX_WAITING = 8  # get_result requests waiting for one goal; more are dropped
ZERO_ID = bytes(16)

# (session, node, entity id, topic, type, depth, transient local) -> the bridge's
# publisher (ros2_bridge._Publisher): put(msg) publishes, `token` is its liveliness key,
# `publisher` its zenoh publisher
Publisher = Callable[[zenoh.Session, wire.Node, int, str, str, int, bool], Any]


def services(settings: Ros2Settings) -> dict[str, tuple[str, str]]:
    """The zenoh key of each of the action's services: key -> (service name, type)."""
    name = settings.topic(settings.fly_path_action)
    out = {}
    for part, srvtype in (("send_goal", SEND_GOAL), ("cancel_goal", wire.CANCEL_GOAL)):
        service = f"{name}/_action/{part}"
        out[wire.topic_key(settings.domain_id, service, srvtype)] = (service, srvtype)
    service = f"{name}/_action/get_result"
    out[wire.topic_key(settings.domain_id, service, GET_RESULT)] = (service, GET_RESULT)
    return out


def ingress_limits(
    settings: Ros2Settings, zenoh_settings: ZenohSettings, trajectory_hz: float | None
) -> dict[str, float]:
    """What zenoh limits the action's services to (key -> Hz): send_goal as the
    trajectory topics (`trajectory_hz`), cancel_goal as `cmd/hold`, get_result as
    `cmd/status`; none where those are not limited."""
    limits = {
        SEND_GOAL: trajectory_hz,
        wire.CANCEL_GOAL: zenoh_settings.ingress_limit("cmd/hold"),
        GET_RESULT: zenoh_settings.ingress_limit("cmd/status"),
    }
    return {
        key: hz
        for key, (_service, srvtype) in services(settings).items()
        if (hz := limits[srvtype]) is not None
    }


@dataclasses.dataclass(eq=False)
class _Goal:
    """One goal: `uuid` its id, `stamp` when it was taken (ns since the UNIX epoch);
    once accepted, `start` and `end` the core times its trajectory begins and ends, `t`
    the core time last seen; the result's fields; the get_result requests waiting."""

    uuid: bytes
    ident: str
    stamp: int
    accepted: bool = False
    status: int = ABORTED
    start: float = 0.0
    end: float = 0.0
    t: float = 0.0
    success: bool = False
    message: str = ""
    max_error: float = 0.0
    waiting: list[tuple[zenoh.Query, str, wire.Attachment]] = dataclasses.field(
        default_factory=list
    )

    @property
    def terminal(self) -> bool:
        return self.status in (SUCCEEDED, CANCELED, ABORTED)

    def info(self) -> Any:
        return wire.message(wire.GOAL_INFO, goal_id=_uuid(self.uuid), stamp=stamp(self.stamp))


class FlyPathServer:
    """The action server; `declare()` on a session, then `await close()`.  Its state
    lives on the event loop that declared it; zenoh's threads only hand requests over."""

    def __init__(
        self,
        settings: Ros2Settings,
        handler: DaemonHandler,
        interface: ZenohInterface,
        max_message_bytes: int,
        publisher: Publisher,
    ) -> None:
        """Goals parsed with `interface`'s limits, timer and parse thread, their
        commands run through its queue, within `max_message_bytes`; feedback and status
        published by `publisher(session, node, entity_id, topic, type, depth,
        transient_local)`: the status transient local, as rcl_action publishes it."""
        self.settings = settings
        self.name = settings.topic(settings.fly_path_action)
        self.max_message_bytes = max_message_bytes
        self._handler = handler
        self._interface = interface
        self._publisher = publisher
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending = wire.Pending()
        self._goals: dict[bytes, _Goal] = {}  # by id, oldest first
        self._current: _Goal | None = None  # the goal flying
        self._queued = 0  # goals taken, not yet answered
        self._one_at_a_time = asyncio.Lock()
        self._tasks: set[asyncio.Task[None]] = set()
        self._entities: list[Any] = []
        self._feedback: Any = None
        self._status: Any = None

    def declare(self, session: zenoh.Session, node: wire.Node, entity_id: int) -> int:
        """The services, the feedback and status publishers and their liveliness tokens
        on `session`, after `node`'s entity `entity_id`; the last entity id used.  The
        handler's events reach the server from now on."""
        self._loop = asyncio.get_running_loop()
        liveliness = session.liveliness()
        take = {SEND_GOAL: self._take_goal, wire.CANCEL_GOAL: self._cancel}
        for key, (service, srvtype) in services(self.settings).items():
            entity_id += 1
            serve = self._server(key, srvtype, take.get(srvtype, self._get_result))
            self._entities.append(session.declare_queryable(key, serve, complete=True))
            token = node.entity_token(entity_id, wire.SERVICE_SERVER, service, srvtype)
            self._entities.append(liveliness.declare_token(token))
        for part, msgtype, depth, latched in (
            ("feedback", FEEDBACK, 10, False),  # rmw_qos_profile_default
            ("status", STATUS, STATUS_DEPTH, True),
        ):
            entity_id += 1
            topic = f"{self.name}/_action/{part}"
            publisher = self._publisher(session, node, entity_id, topic, msgtype, depth, latched)
            setattr(self, f"_{part}", publisher)
            self._entities += [publisher.publisher, liveliness.declare_token(publisher.token)]
        self._handler.subscribe(self._on_event)
        self._publish_status()  # an empty list: what a late subscriber gets first
        return entity_id

    async def close(self) -> None:
        """Stop serving: the goals not yet ended end ABORTED (their results answered),
        the goals not yet answered are dropped."""
        for goal in list(self._goals.values()):
            if not goal.terminal:
                self._finish(goal, ABORTED, "busy: the daemon is shutting down")
        for entity in self._entities:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task

    # -- zenoh's threads ------------------------------------------------------------------

    def _server(
        self, key: str, srvtype: str, take: Callable[[zenoh.Query, str, Any, Any], None]
    ) -> Callable[[zenoh.Query], None]:
        """The queryable callback of one service: the request taken as rmw_zenoh takes
        it (a goal's Path only sized and its pose count read here: decoded in the parse
        thread), or dropped unanswered; then handed to the loop."""
        goal = srvtype == SEND_GOAL
        reqtype = None if goal else f"{srvtype}_Request"
        cap = self.max_message_bytes if goal else MAX_COMMAND_BYTES

        def taken(query: zenoh.Query, msg: Any, request: wire.Attachment) -> None:
            assert self._loop is not None
            with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
                self._loop.call_soon_threadsafe(take, query, key, request, msg)

        return wire.request_server(key, reqtype, cap, self._pending, taken)

    # -- send_goal ------------------------------------------------------------------------

    def _take_goal(
        self, query: zenoh.Query, key: str, request: wire.Attachment, raw: bytes
    ) -> None:
        """A goal request (its CDR undecoded): refused at once for a queue full of goals
        or more poses than max_waypoints (read from its first bytes); else parsed and
        submitted in turn."""
        goal_id = raw[4 : 4 + len(ZERO_ID)]
        if len(goal_id) != len(ZERO_ID):  # not even an id: malformed
            self._drop(query, key, request, "no goal id")
            return
        count = wire.sequence_length(raw, PATH, skip=len(ZERO_ID))
        try:
            if self._queued >= self.settings.queue_depth:
                raise CommandError("busy", "too many goals waiting: this one was dropped")
            if count is not None:
                check_waypoint_count(count, PATH, self._interface.limits.max_waypoints)
        except CommandError as exc:
            self._refuse(query, key, request, goal_id, exc)
            return
        self._queued += 1
        assert self._loop is not None
        task = self._loop.create_task(self._receive_goal(query, key, request, raw))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _receive_goal(
        self, query: zenoh.Query, key: str, request: wire.Attachment, raw: bytes
    ) -> None:
        try:
            async with self._one_at_a_time:
                read = functools.partial(self._read_goal, raw)
                parsed = await self._interface.run_parser(read, lambda: None)
                if parsed is None:  # malformed, or the interface closes
                    self._drop(query, key, request, "malformed CDR")
                    return
                goal_id, trajectory = parsed
                if goal_id in self._goals:
                    error = CommandError("bad_request", "the goal id is another goal's")
                    self._refuse(query, key, request, goal_id, error, keep=False)
                elif isinstance(trajectory, CommandError):
                    self._refuse(query, key, request, goal_id, trajectory)
                else:
                    await self._submit(query, key, request, goal_id, trajectory)
        finally:
            self._queued -= 1

    def _read_goal(self, raw: bytes) -> tuple[bytes, TrajectoryRequest | CommandError] | None:
        """In the parse thread: the goal's id and its Path parsed (or why not); None
        for CDR that does not read as the SendGoal request."""
        try:
            msg = wire.deserialize(raw, f"{SEND_GOAL}_Request")
        except wire.WireError as exc:
            log.debug("ROS 2 action %s: goal dropped: %s", self.name, exc)
            return None
        goal_id = bytes(msg.goal_id.uuid)
        limits, timer = self._interface.limits, self._interface.timer
        return goal_id, trajectory_request(
            msg.goal.path, self._ident(goal_id), self.settings, limits, timer
        )

    async def _submit(
        self,
        query: zenoh.Query,
        key: str,
        request: wire.Attachment,
        goal_id: bytes,
        parsed: TrajectoryRequest,
    ) -> None:
        """Hand the goal's trajectory to the handler; accepted, it is the goal flying."""
        ident = self._ident(goal_id)
        # the anonymous client's, as a Path on the topic: its id names it in the motion
        claim = dataclasses.replace(UNNAMED, id=ident)
        try:
            result = self._handler.submit_trajectory(parsed.trajectory, parsed.start, claim)
            if inspect.isawaitable(result):
                result = await result
            start, end = float(result["start"]), float(result["end"])
        except CommandError as exc:
            self._refuse(query, key, request, goal_id, exc)
            return
        except Exception as exc:
            log.exception("the handler failed on a ROS 2 goal")
            error = CommandError("internal", f"the daemon failed: {type(exc).__name__}")
            self._refuse(query, key, request, goal_id, error)
            return
        goal = _Goal(goal_id, ident, time.time_ns(), True, EXECUTING, start, end, start)
        goal.message = answer_text({"result": result}, True)
        self._answer_goal(query, key, request, goal)
        previous, self._current = self._current, goal
        self._remember(goal)
        if previous is not None and not previous.terminal:
            self._finish(previous, ABORTED, f"preempted: replaced by goal {ident}")
        self._publish_status()
        log.info("ROS 2 action %s: goal %s accepted: %s", self.name, ident, goal.message)
        assert self._loop is not None
        task = self._loop.create_task(self._follow(goal))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _refuse(
        self,
        query: zenoh.Query,
        key: str,
        request: wire.Attachment,
        goal_id: bytes,
        error: CommandError,
        keep: bool = True,
    ) -> None:
        """Answer accepted false; the reason logged, and kept as the goal's result
        (ABORTED) unless `keep` is false (the id is another goal's)."""
        goal = _Goal(goal_id, self._ident(goal_id), time.time_ns())
        goal.message = answer_text(reply_error("trajectory", error), False)
        log.info("ROS 2 action %s: goal %s refused: %s", self.name, goal.ident, goal.message)
        self._answer_goal(query, key, request, goal)
        if keep:
            self._remember(goal)
            self._expire_later(goal)

    def _answer_goal(
        self, query: zenoh.Query, key: str, request: wire.Attachment, goal: _Goal
    ) -> None:
        self._pending.done(request)
        response = wire.message(
            f"{SEND_GOAL}_Response", accepted=goal.accepted, stamp=stamp(goal.stamp)
        )
        wire.respond(query, key, response, request)

    def _drop(self, query: zenoh.Query, key: str, request: wire.Attachment, why: str) -> None:
        log.debug("ROS 2 action %s: request dropped: %s", key, why)
        self._pending.done(request)
        with contextlib.suppress(zenoh.ZError):
            query.drop()

    # -- the goal flying ------------------------------------------------------------------

    async def _follow(self, goal: _Goal) -> None:
        """Feedback at rate_hz from the state, in the cycle's slack, while `goal` flies
        (or cancels); and the motion the state names checked: another's ends the goal."""
        period = 1.0 / self.settings.rate_hz
        while True:
            await asyncio.sleep(period)
            await self._handler.slack()
            if goal.terminal:
                return
            state = self._handler.state()
            goal.t = float(state.get("t", goal.t))
            error = _position_error(state)
            if error is not None:
                goal.max_error = max(goal.max_error, error)
            motion = state.get("motion")
            if motion is not None and motion.get("id") != goal.ident and goal.t < goal.end:
                what = f"{motion.get('what')} from {motion.get('client')}"
                self._finish(goal, ABORTED, f"preempted: replaced by {what}")
                return
            pose = state_pose(state)
            if pose is None:
                continue
            span = goal.end - goal.start
            feedback = wire.message(
                f"{ACTION}_Feedback",
                progress=min(1.0, max(0.0, (goal.t - goal.start) / span)) if span > 0 else 1.0,
                time_remaining=max(0.0, goal.end - goal.t),
                tracking_error=math.nan if error is None else error,
                pose=pose_stamped(pose, time.time_ns(), self.settings.world_frame),
            )
            self._put(
                self._feedback, wire.message(FEEDBACK, goal_id=_uuid(goal.uuid), feedback=feedback)
            )

    def _on_event(self, event: dict[str, Any]) -> None:
        """A handler event (any thread): looked at on the loop."""
        assert self._loop is not None
        with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
            self._loop.call_soon_threadsafe(self._event, event)

    def _event(self, event: dict[str, Any]) -> None:
        """End the goal flying on the events that end its flight."""
        goal = self._current
        if goal is None or goal.terminal:
            return
        name, state = event.get("event"), event.get("state")
        if name == "trajectory_done" and float(event.get("t", -math.inf)) >= goal.end - 1e-6:
            goal.t = goal.end
            flown = event.get("max_position_error")  # every cycle's, where states are samples
            if isinstance(flown, (int, float)) and math.isfinite(flown):
                goal.max_error = max(goal.max_error, float(flown))
            goal.success = True  # the message stays the accepted submission's JSON
            self._finish(goal, SUCCEEDED, goal.message)
        elif state is not None and state not in MOVING:
            why = f"{event.get('trigger')}: {event.get('message')}" if name == "brake" else name
            self._finish(goal, ABORTED, f"invalid_state: the robot is {state} ({why})")
        elif name == "motion_preempted" and event.get("id") == goal.ident:
            by = event.get("by") or {}
            what = f"{by.get('what')} from {by.get('client')}"
            self._finish(goal, ABORTED, f"preempted: replaced by {what}")
        elif name == "state" and event.get("why") == "hold" and goal.status == EXECUTING:
            self._finish(goal, ABORTED, "preempted: a hold stopped it")

    # -- cancel_goal ----------------------------------------------------------------------

    def _cancel(self, query: zenoh.Query, key: str, request: wire.Attachment, msg: Any) -> None:
        """Cancel the goals the request names as rcl_action_process_cancel_request picks
        them: CANCELING, and the robot held."""
        info = msg.goal_info
        goal_id = bytes(info.goal_id.uuid)
        before = info.stamp.sec * 10**9 + info.stamp.nanosec
        code, goals = ERROR_NONE, []
        if goal_id != ZERO_ID and before == 0:
            goal = self._goals.get(goal_id)
            if goal is None or not goal.accepted:
                code = ERROR_UNKNOWN_GOAL_ID
            elif goal.status not in ACTIVE:
                code = ERROR_GOAL_TERMINATED
            else:
                goals = [goal]
        else:
            if goal_id == ZERO_ID and before == 0:
                before = 2**63 - 1  # every goal
            goals = [
                g
                for g in self._goals.values()
                if g.accepted and g.status in ACTIVE and (g.stamp <= before or g.uuid == goal_id)
            ]
        for goal in goals:
            goal.status = CANCELING
        if goals:
            self._publish_status()
            held = functools.partial(self._held, goals)
            hold = decode_command("hold", {}, self._interface.limits.unit_tolerance)
            self._interface.offer_command("hold", hold, held)
        self._pending.done(request)
        response = wire.message(
            f"{wire.CANCEL_GOAL}_Response",
            return_code=code,
            goals_canceling=[goal.info() for goal in goals],
        )
        wire.respond(query, key, response, request)

    def _held(self, goals: list[_Goal], body: dict[str, Any], ok: bool) -> None:
        """The cancel's hold answered (on the loop): the goals still canceling end."""
        for goal in goals:
            if goal.status == CANCELING:
                self._finish(goal, CANCELED if ok else ABORTED, answer_text(body, ok))

    # -- get_result -----------------------------------------------------------------------

    def _get_result(self, query: zenoh.Query, key: str, request: wire.Attachment, msg: Any) -> None:
        goal = self._goals.get(bytes(msg.goal_id.uuid))
        if goal is None or goal.terminal:
            self._answer_result(query, key, request, goal)
        elif len(goal.waiting) >= MAX_WAITING:
            self._drop(query, key, request, f"{MAX_WAITING} result requests wait already")
        else:
            goal.waiting.append((query, key, request))

    def _answer_result(
        self, query: zenoh.Query, key: str, request: wire.Attachment, goal: _Goal | None
    ) -> None:
        """The result of `goal` (terminal), or STATUS_UNKNOWN for no goal."""
        self._pending.done(request)
        fields: dict[str, Any] = {}
        if goal is not None and goal.accepted:
            fields = {
                "duration": min(goal.t, goal.end) - goal.start,
                "max_tracking_error": goal.max_error,
            }
        if goal is not None:
            fields.update(success=goal.success, message=goal.message)
        result = wire.message(RESULT, **{**_EMPTY_RESULT, **fields})
        status = UNKNOWN if goal is None else goal.status
        wire.respond(
            query,
            key,
            wire.message(f"{GET_RESULT}_Response", status=status, result=result),
            request,
        )

    # -- goals ----------------------------------------------------------------------------

    def _finish(self, goal: _Goal, status: int, message: str) -> None:
        """`goal` ends with `status`: the status published, then its waiting results
        answered (so that a client that has the result and then joins the transient-local
        status topic gets the terminal list, not the one before it: answered first, a
        late subscription could come between the two), its result kept RESULT_TIMEOUT s."""
        goal.status, goal.message = status, message
        if self._current is goal:
            self._current = None
        self._publish_status()
        waiting, goal.waiting = goal.waiting, []
        for query, key, request in waiting:
            self._answer_result(query, key, request, goal)
        log.info(
            "ROS 2 action %s: goal %s ended (status %d): %s", self.name, goal.ident, status, message
        )
        self._expire_later(goal)

    def _remember(self, goal: _Goal) -> None:
        """Keep `goal`; beyond MAX_GOALS the oldest terminal goals are forgotten."""
        self._goals[goal.uuid] = goal
        for old in [g for g in self._goals.values() if g.terminal][: len(self._goals) - MAX_GOALS]:
            del self._goals[old.uuid]

    def _expire_later(self, goal: _Goal) -> None:
        assert self._loop is not None
        self._loop.call_later(RESULT_TIMEOUT, self._expire, goal)

    def _expire(self, goal: _Goal) -> None:
        if self._goals.get(goal.uuid) is goal:
            del self._goals[goal.uuid]
            if goal.accepted:
                self._publish_status()

    def _publish_status(self) -> None:
        """Every goal accepted and not yet forgotten, with its status (rclcpp_action's
        publish_status)."""
        statuses = [
            wire.message("action_msgs/msg/GoalStatus", goal_info=goal.info(), status=goal.status)
            for goal in self._goals.values()
            if goal.accepted
        ]
        self._put(self._status, wire.message(STATUS, status_list=statuses))

    def _put(self, publisher: Any, msg: Any) -> None:
        try:
            publisher.put(msg)
        except zenoh.ZError:
            log.warning("ROS 2 action %s: could not publish a %s", self.name, msg.__msgtype__)

    def _ident(self, goal_id: bytes) -> str:
        """The goal's name in logs and in the motion: <action>#<its id in hex>."""
        return f"{self.name}#{goal_id.hex()}"


_EMPTY_RESULT = {"success": False, "message": "", "duration": 0.0, "max_tracking_error": 0.0}


def _uuid(goal_id: bytes) -> Any:
    return wire.message(wire.UUID, uuid=np.frombuffer(goal_id, dtype=np.uint8).copy())


def _position_error(state: dict[str, Any]) -> float | None:
    """The norm of the tracking error's position part (m), if the state has it."""
    error = state.get("tracking_error")
    if not error:
        return None
    norm = float(np.linalg.norm(np.asarray(error[:3], dtype=float)))
    return norm if math.isfinite(norm) else None
