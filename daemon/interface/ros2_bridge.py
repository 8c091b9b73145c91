"""ROS 2 over rmw_zenoh on the daemon's zenoh session: cdprd appears as a ROS 2 node
(docs/guide/ros2.md; the wire format in daemon.interface.ros2_wire, the messages in
daemon.interface.ros2_convert).

At `rate_hz` the state goes out as PoseStamped (measured, reference), JointState, /tf and
diagnostics.  A Path or MultiDOFJointTrajectory comes in through the same gates as a
trajectory on the zenoh interface (DESIGN §19): zenoh's ingress limit
(`ingress_limits`: ros2.ingress_limit_hz, by default zenoh.ingress_limits_hz's on
`trajectory`), the same size cap (zenoh.max_message_bytes unless ros2.max_message_bytes
says otherwise), checked on zenoh's thread with the waypoint count its first bytes
declare (ros2_wire.sequence_length) before anything is decoded; then it is decoded,
converted and parsed in the zenoh interface's parse thread, within its CPU budget
(ZenohInterface.run_parser: a flood of long ones leaves the loop its time; a Path whose
poses carry no times, all one stamp, is a path, timed there as `<prefix>/path` is by the
interface's timer), and submitted
to the handler like a trajectory from the zenoh interface; its verdict, accepted or
rejected with the reason, goes out on the status topic as JSON text.  Trajectories are
handled one at a time; at most `queue_depth` wait, more are refused "busy".

Given the robot, RViz's view of it as well (daemon.interface.ros2_model): its URDF on
robot_description and its fixed frames on /tf_static (transient local, for displays that
start later), and the cables as markers at `rate_hz`.

The std_srvs/srv/Trigger services enable, hold, brake, reset and disable run those
commands, the std_srvs/srv/SetBool services hold_observer and freeze_payload the
observer and payload commands with held / frozen = data, as rmw_zenoh_cpp's service
servers answer (ros2_wire): a request whose
attachment or CDR does not read, or that repeats a pending (client, sequence number), is
dropped unanswered as rmw_zenoh drops it.  A good one joins the zenoh interface's
command queue (ZenohInterface.offer_command: its depth, one enable or reset at a time,
"busy" beyond), under the ingress limit zenoh.ingress_limits_hz puts on
`cmd/<command>`; the answer is success and the command's result as JSON text, or the
refusal's "<code>: <reason>".
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import inspect
import logging
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext as ze

from cdpr import Robot
from cdpr.path import Path
from cdpr.trajectory import SCHEMA_VERSION, Trajectory, TrajectoryLimits
from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings
from daemon.interface import ros2_action, ros2_model
from daemon.interface import ros2_wire as wire
from daemon.interface.messages import (
    EVENT_KEY,
    VERSION_KEY,
    TrajectoryRequest,
    check_size,
    decode_command,
    encode,
    error_body,
    reply_error,
)
from daemon.interface.ros2_convert import (
    DIAGNOSTICS,
    JOINTS,
    MULTI_DOF,
    PATH,
    POSE,
    STATUS,
    TF,
    answer_text,
    check_waypoint_count,
    state_messages,
    status_message,
    trajectory_request,
)
from daemon.interface.zenoh_io import MAX_COMMAND_BYTES, ZenohInterface
from daemon.service.api import UNNAMED, CommandError, DaemonHandler

log = logging.getLogger(__name__)

PUBLISHED = {  # setting naming the topic -> its type
    "pose_topic": POSE,
    "reference_pose_topic": POSE,
    "joint_states_topic": JOINTS,
    "tf_topic": TF,
    "diagnostics_topic": DIAGNOSTICS,
    "status_topic": STATUS,
}
ACCEPTED = {"path_topic": PATH, "multi_dof_trajectory_topic": MULTI_DOF}
SERVICES = {  # setting naming the service -> its type, the command it runs, the argument
    # SetBool's data sets (a Trigger has none)
    "enable_service": (wire.TRIGGER, "enable", None),
    "hold_service": (wire.TRIGGER, "hold", None),
    "brake_service": (wire.TRIGGER, "brake", None),
    "reset_service": (wire.TRIGGER, "reset", None),
    "disable_service": (wire.TRIGGER, "disable", None),
    "observer_hold_service": (wire.SET_BOOL, "observer", "held"),
    "payload_freeze_service": (wire.SET_BOOL, "payload", "frozen"),
}
ROUTER_RETRY = 2.0  # s between attempts to reach the ROS 2 router
# s: a transient-local publisher's sporadic heartbeat, rmw_zenoh_cpp's
# SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (500 ms)
HEARTBEAT = 0.5
Service = tuple[str, str, str, str | None]  # its name, type, command, argument
Received = tuple[str, str, bytes, bytes | None]  # topic, type, payload, attachment


def intake_keys(settings: Ros2Settings) -> dict[str, tuple[str, str]]:
    """The zenoh key of each trajectory topic the node takes: key -> (topic, type)."""
    out = {}
    for name, msgtype in ACCEPTED.items():
        topic = settings.topic(getattr(settings, name))
        out[wire.topic_key(settings.domain_id, topic, msgtype)] = (topic, msgtype)
    return out


def service_keys(settings: Ros2Settings) -> dict[str, Service]:
    """The zenoh key of each service the node serves, and what it is."""
    out = {}
    for name, (srvtype, command, argument) in SERVICES.items():
        service = settings.topic(getattr(settings, name))
        key = wire.topic_key(settings.domain_id, service, srvtype)
        out[key] = (service, srvtype, command, argument)
    return out


def ingress_limits(settings: Ros2Settings, zenoh_settings: ZenohSettings) -> dict[str, float]:
    """What zenoh limits the node's inputs to (key -> Hz), for the session's config
    (ZenohInterface's `ingress_limits`): the trajectory topics to ros2.ingress_limit_hz,
    else the limit on the zenoh interface's `trajectory`; each service to the limit on
    its command's `cmd/<command>`; the action's as ros2_action.ingress_limits says; none
    when those are not set or ROS 2 is off."""
    if not settings.enabled:
        return {}
    out = {}
    hz = settings.ingress_limit_hz or zenoh_settings.ingress_limit("trajectory")
    if hz is not None:
        out.update(dict.fromkeys(intake_keys(settings), hz))
    for key, (_service, _srvtype, command, _argument) in service_keys(settings).items():
        limit = zenoh_settings.ingress_limit(f"cmd/{command}")
        if limit is not None:
            out[key] = limit
    out.update(ros2_action.ingress_limits(settings, zenoh_settings, hz))
    return out


class _Publisher:
    """One ROS 2 publisher, reliable, keep last `depth`, as rmw_zenoh_cpp declares it
    (ros2_wire): its zenoh publisher, liveliness token (with the QoS), GID and sequence
    numbers.  Volatile by default; `transient_local`: an AdvancedPublisher whose cache
    keeps the last `depth` samples for late-joining transient-local subscriptions."""

    def __init__(
        self,
        session: zenoh.Session,
        node: wire.Node,
        entity_id: int,
        topic: str,
        msgtype: str,
        depth: int = 10,
        transient_local: bool = False,
    ) -> None:
        qos = wire.qos_keyexpr(depth, transient_local)
        self.token = node.entity_token(entity_id, wire.PUBLISHER, topic, msgtype, qos)
        self.gid = wire.gid(self.token)
        self.sequence = 0
        key = wire.topic_key(node.domain_id, topic, msgtype)
        drop, reliable = zenoh.CongestionControl.DROP, zenoh.Reliability.RELIABLE
        self.publisher: zenoh.Publisher | ze.AdvancedPublisher
        if transient_local:
            self.publisher = ze.declare_advanced_publisher(
                session,
                key,
                congestion_control=drop,
                reliability=reliable,
                cache=ze.CacheConfig(max_samples=depth),
                sample_miss_detection=ze.MissDetectionConfig(sporadic_heartbeat=HEARTBEAT),
                publisher_detection=True,
            )
        else:
            self.publisher = session.declare_publisher(
                key, congestion_control=drop, reliability=reliable
            )

    def put(self, msg: Any) -> None:
        self.sequence += 1
        extra = wire.attachment(self.sequence, time.time_ns(), self.gid)
        self.publisher.put(wire.serialize(msg), attachment=extra)


class Ros2Bridge:
    """`await start()`, then `await close()`; the handler is called on start()'s loop."""

    def __init__(
        self,
        settings: Ros2Settings,
        handler: DaemonHandler,
        interface: ZenohInterface,
        router: zenoh.Config | None = None,
        robot: Robot | None = None,
    ) -> None:
        """With `interface`'s limits, size cap and parse thread; on its session (whose
        `ingress_limits` must be this bridge's: module function ingress_limits), or on a
        client session of the bridge's own to the ROS 2 graph's router, `router`
        (ros2.router: the router relays between its clients and the graph's peers, where
        it would not relay between two peers without gossip, which stays off here).
        With `robot`, RViz's view of it too (daemon.interface.ros2_model)."""
        self.settings = settings
        self.limits: TrajectoryLimits = interface.limits
        self.max_message_bytes = settings.max_message_bytes or interface.settings.max_message_bytes
        self._interface = interface
        self._handler = handler
        self._own_session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._publishers: dict[str, _Publisher] = {}
        self._entities: list[Any] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._queue: asyncio.Queue[Received] | None = None
        self._pending = wire.Pending()  # requests taken, not yet answered
        self._router = router
        self._model = None if robot is None else ros2_model.RobotModel(robot, settings)
        self.node: wire.Node | None = None  # once declared
        self._action = ros2_action.FlyPathServer(
            settings, handler, interface, self.max_message_bytes, _Publisher
        )

    async def start(self) -> None:
        """Declare the node on the interface's session, or on a client session of its
        own once the router answers (tried every ROUTER_RETRY s meanwhile, so that the
        daemon runs while the ROS 2 graph is down); then publish and take trajectories
        and requests."""
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue(self.settings.queue_depth)
        if self._router is None:
            self._declare(self._interface.session)
        else:
            self._tasks.append(self._loop.create_task(self._join_router(self._router)))

    async def _join_router(self, config: zenoh.Config) -> None:
        waited = False
        while True:
            try:
                session = await asyncio.to_thread(zenoh.open, config)
                break
            except zenoh.ZError as exc:
                if not waited:
                    log.warning("ROS 2: the router does not answer (%s); trying again", exc)
                waited = True
                await asyncio.sleep(ROUTER_RETRY)
        self._own_session = session
        if waited:
            log.info("ROS 2: the router answers now")
        self._declare(session)

    def _declare(self, session: zenoh.Session) -> None:
        """The node, its publishers, subscriptions and services (each with its liveliness
        token) on `session`, and the tasks that publish and take trajectories."""
        assert self._loop is not None
        settings = self.settings
        self.node = node = wire.Node(
            settings.domain_id, str(session.info.zid()), 0, settings.namespace, settings.node_name
        )
        liveliness = session.liveliness()
        self._entities.append(liveliness.declare_token(node.token()))
        entity_id = 0
        for name, msgtype in PUBLISHED.items():
            entity_id += 1
            topic = self.settings.topic(getattr(self.settings, name))
            self._publishers[name] = _Publisher(session, node, entity_id, topic, msgtype)
            self._entities.append(liveliness.declare_token(self._publishers[name].token))
        for key, (topic, msgtype) in intake_keys(self.settings).items():
            entity_id += 1
            receive = self._receiver(topic, msgtype)
            self._entities.append(session.declare_subscriber(key, receive))
            token = node.entity_token(entity_id, wire.SUBSCRIPTION, topic, msgtype)
            self._entities.append(liveliness.declare_token(token))
        for key, served in service_keys(self.settings).items():
            entity_id += 1
            serve = self._server(key, served)
            self._entities.append(session.declare_queryable(key, serve, complete=True))
            service, srvtype = served[:2]
            token = node.entity_token(entity_id, wire.SERVICE_SERVER, service, srvtype)
            self._entities.append(liveliness.declare_token(token))
        if self._model is not None:
            for name, (msgtype, depth, latched) in ros2_model.TOPICS.items():
                entity_id += 1
                topic = settings.topic(getattr(settings, name))
                publisher = _Publisher(session, node, entity_id, topic, msgtype, depth, latched)
                self._publishers[name] = publisher
                self._entities.append(liveliness.declare_token(publisher.token))
            for name, msg in self._model.latched(time.time_ns()).items():
                self._publishers[name].put(msg)
        entity_id = self._action.declare(session, node, entity_id)
        self._tasks += [
            self._loop.create_task(self._publish_states()),
            self._loop.create_task(self._take_trajectories()),
        ]
        log.info(
            "ROS 2 (rmw_zenoh) node %s in namespace %s, domain %d",
            self.settings.node_name,
            self.settings.namespace,
            self.settings.domain_id,
        )

    async def close(self) -> None:
        await self._action.close()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for entity in [*self._entities, *(p.publisher for p in self._publishers.values())]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        if self._own_session is not None:
            with contextlib.suppress(zenoh.ZError):
                self._own_session.close()

    # -- out --------------------------------------------------------------------------

    async def _publish_states(self) -> None:
        """The state at rate_hz, in the cycle's slack; a period missed is skipped."""
        assert self._loop is not None
        period = 1.0 / self.settings.rate_hz
        due = self._loop.time()
        failures = 0
        while True:
            await asyncio.sleep(due - self._loop.time())
            await self._handler.slack()
            try:
                state, ns = self._handler.state(), time.time_ns()
                messages = state_messages(state, self.settings, ns)
                if self._model is not None and self._model.cables_due(ns):
                    messages["cables_topic"] = self._model.cables(state, ns)
                for name, msg in messages.items():
                    self._publishers[name].put(msg)
            except Exception:
                failures += 1
                if failures == 1 or failures % 1000 == 0:
                    log.exception("publishing the ROS 2 state failed (%d times)", failures)
            due = max(due + period, self._loop.time())

    def _status(
        self, ident: str | None, topic: str, error: CommandError | None, **more: Any
    ) -> None:
        body: dict[str, Any] = {
            VERSION_KEY: SCHEMA_VERSION,
            EVENT_KEY: "trajectory_accepted" if error is None else "trajectory_rejected",
            "id": ident,
            "topic": topic,
            **more,
        }
        if error is not None:
            body["error"] = error_body(error)
        try:
            self._publishers["status_topic"].put(status_message(encode(body).decode()))
        except zenoh.ZError:
            log.warning("could not publish a trajectory verdict on %s", topic)

    # -- in ---------------------------------------------------------------------------

    def _receiver(self, topic: str, msgtype: str) -> Callable[[zenoh.Sample], None]:
        """The subscriber callback (zenoh's thread): the room in the queue, the size and
        the waypoint count the payload declares checked, a copy, no more."""

        def receive(sample: zenoh.Sample) -> None:
            if self._queue is not None and self._queue.full():  # a hint: do not copy
                self._on_loop(self._status, None, topic, _busy())  # what would be dropped
                return
            try:
                check_size(len(sample.payload), self.max_message_bytes)
                payload = sample.payload.to_bytes()
                count = wire.sequence_length(payload, msgtype)
                if count is not None:
                    check_waypoint_count(count, msgtype, self.limits.max_waypoints)
            except CommandError as error:
                self._on_loop(self._status, None, topic, error)
                return
            extra = sample.attachment
            item = (topic, msgtype, payload, None if extra is None else extra.to_bytes())
            self._on_loop(self._offer, item)

        return receive

    def _server(self, key: str, served: Service) -> Callable[[zenoh.Query], None]:
        """The queryable callback of service `served` (zenoh's thread): the request read
        as rmw_zenoh's ServiceData::take_request reads it, or dropped unanswered; then
        its command queued with the zenoh interface's, its arguments checked as theirs."""
        _service, srvtype, command, argument = served

        def taken(query: zenoh.Query, msg: Any, request: wire.Attachment) -> None:
            respond = functools.partial(self._respond, query, key, srvtype, request)
            data = {} if argument is None else {argument: bool(msg.data)}
            try:
                args = decode_command(command, data, self.limits.unit_tolerance)
            except CommandError as exc:
                respond(reply_error(command, exc), False)
                return
            self._interface.offer_command(command, args, respond)

        reqtype = f"{srvtype}_Request"
        return wire.request_server(key, reqtype, MAX_COMMAND_BYTES, self._pending, taken)

    def _respond(
        self,
        query: zenoh.Query,
        key: str,
        srvtype: str,
        request: wire.Attachment,
        body: dict[str, Any],
        ok: bool,
    ) -> None:
        """Answer a request with the command's reply `body` (wire.respond)."""
        self._pending.done(request)
        response = wire.message(f"{srvtype}_Response", success=ok, message=answer_text(body, ok))
        wire.respond(query, key, response, request)

    def _on_loop(self, call: Callable[..., None], *args: Any) -> None:
        assert self._loop is not None
        with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
            self._loop.call_soon_threadsafe(call, *args)

    def _offer(self, item: Received) -> None:
        assert self._queue is not None
        try:
            self._queue.put_nowait(item)
        except asyncio.QueueFull:
            self._status(None, item[0], _busy())

    async def _take_trajectories(self) -> None:
        assert self._queue is not None and self._loop is not None
        while True:
            item = await self._queue.get()
            topic = item[0]
            parse = functools.partial(
                read_trajectory, item, self.settings, self.limits, self._interface.timer
            )
            ident, parsed = await self._interface.run_parser(parse, _shutting_down)
            if isinstance(parsed, CommandError):
                self._status(ident, topic, parsed)
                continue
            try:
                # a ROS 2 message names no client: every ROS 2 sender is the unnamed one
                result = self._handler.submit_trajectory(parsed.trajectory, parsed.start, UNNAMED)
                if inspect.isawaitable(result):
                    result = await result
            except CommandError as exc:
                self._status(ident, topic, exc)
            except Exception as exc:
                log.exception("the handler failed on a ROS 2 trajectory")
                error = CommandError("internal", f"the daemon failed: {type(exc).__name__}")
                self._status(ident, topic, error)
            else:
                self._status(ident, topic, None, result=result)


def _busy() -> CommandError:
    return CommandError("busy", "too many trajectories waiting: this one was dropped")


def _shutting_down() -> tuple[None, CommandError]:
    return None, CommandError("busy", "the daemon is shutting down")


def read_trajectory(
    item: Received,
    settings: Ros2Settings,
    limits: TrajectoryLimits,
    timer: Callable[[Path], Trajectory] | None = None,
) -> tuple[str | None, TrajectoryRequest | CommandError]:
    """A received sample's request id (<topic>#<sequence number>, once the attachment
    reads) and its trajectory parsed, or a stampless Path's poses timed by `timer`; or
    why not: every bad input gets a CommandError that names the problem, never another
    exception."""
    topic, msgtype, payload, extra = item
    ident = None
    try:
        ident = f"{topic}#{wire.read_attachment(extra).sequence_number}"
        msg = wire.deserialize(payload, msgtype)
    except wire.WireError as exc:
        return ident, CommandError("bad_request", f"{msgtype}: {exc}")
    return ident, trajectory_request(msg, ident, settings, limits, timer)
