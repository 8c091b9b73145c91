"""The ROS 2 action cdprd_interfaces/action/FlyPath called as an rclcpp action client on
rmw_zenoh calls it, by a client written here from rcl_action's and rmw_zenoh's design
(tests/data/rmw_zenoh_reference.md, "Actions"), not from the project's encoder: the keys
spelled out (<action>/_action/send_goal, ...), the hashes pinned, the attachments packed
with struct, the messages written and read by rosbags from types declared here from the
.action text and rosidl's layout of the derived types.

First the derivation of those types (daemon.interface.ros2_wire.action_types) is held
to generated rosidl code for example_interfaces/action/Fibonacci; then, against the zenoh
interface's stand-in handler flying as the planner answers (Flying): a goal accepted,
its feedback and status, its result; a goal refused with its reason; a cancel that
holds; cancels by rcl_action's rules; a new goal replacing the one flying; a brake; and
requests rmw_zenoh would not take dropped, reaching nothing.
"""

from __future__ import annotations

import asyncio
import json
import re
import struct
import threading
import time
import uuid as uuid_module
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from cdpr.trajectory import Trajectory
from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings
from daemon.interface import ros2_wire
from daemon.interface.ros2_bridge import ingress_limits
from tests.daemon.test_ros2_services import call, request_attachment
from tests.daemon.test_zenoh_io import WAIT, Running, StandIn

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "rmw_zenoh_reference.md"
ACTION_FILE = (
    Path(__file__).resolve().parents[2]
    / "daemon"
    / "interface"
    / "cdprd_interfaces"
    / "action"
    / "FlyPath.action"
)
# Jazzy's RIHS01 hashes of example_interfaces/action/Fibonacci and what rosidl derives from
# it, and of action_msgs' types (the reference's sources: generated rosidl code)
FIBONACCI = {
    "": "9508051da1ea4658de144b09bd0690ff3de52104683d847aed764d2915906f51",
    "_Goal": "226cb437e4355dcd3e914f930382a3b0cc1da81545bd319ed554e95a03255f51",
    "_Result": "fea81394f25aa4502217953f1a021fb750e79c10bbd43f13dd94632da6569649",
    "_Feedback": "2b12e37361da6f408d4c85bc24a18de64333f29082f2ca34b5ee33dc4c8b42a9",
    "_SendGoal": "d1a57fb2a4afe8c21e34fb10db206f16ce6729b28531141472df92277c55b557",
    "_SendGoal_Request": "3d088942b413247db536576f0286768c6be8fcd5d0c9a5d544f359fba090a238",
    "_SendGoal_Response": "d8c07bb3d5b766fe4b43159c9a5222af5214e2fcc29229b991d826166c512be1",
    "_SendGoal_Event": "d5e5b312dbf847307b0e876c2ecc9d80258e95b0d17f8f7bfc581c4a29c83484",
    "_GetResult": "1b0de0d5d29dc955d92f546706568428632771db13ec84c15ec1c1a59f424a57",
    "_GetResult_Request": "c8a4f5e7d13b81286ee1043e2ecd084281cecf1ff06aaa799464f5f15479f003",
    "_GetResult_Response": "6021dc98ab9b4bbe395e48aa4de81ee5f68eb570f88358affcc648146668b24f",
    "_GetResult_Event": "ac4e9cdb954c2e192c9f0753d46f59ab6f0101d5fb5b9542fd8ab2906e40c4d9",
    "_FeedbackMessage": "c1de71afd52e49a89c53d8262366884185bc0a02f78ce051c4e46b0a7fe59bb2",
}
CANCEL_GOAL_HASH = "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
STATUS_ARRAY_HASH = "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e"
# cdprd_interfaces/action/FlyPath's, by the derivation held to the reference above
SEND_GOAL_HASH = "RIHS01_f7e757e26955c1756335f329dad69a4725402d007d5196046df632b918cfaa7c"
GET_RESULT_HASH = "RIHS01_a04338b78a2118aea0b071fa8d67e09f5ffee00aebcd42d903ffdf44517aca24"
FEEDBACK_HASH = "RIHS01_f2fc0bb24cfb4d1df154b4ed237516fcada59afbd13835f44e9c87f466691b29"
DDS = "cdprd_interfaces::action::dds_::FlyPath_"
SERVICES_QOS = "::,10:,:,:,,"  # rmw_qos_profile_services_default, rmw_qos_profile_default
STATUS_QOS = ":1:,1:,:,:,,"  # rcl_action_qos_profile_status_default: transient local, depth 1
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = range(4)
ROS2 = Ros2Settings(enabled=True, rate_hz=20.0)  # domain 0, namespace /, action fly_path
LEAD = 0.05  # s: the stand-in's flights begin this long after they are accepted

# the types as rosidl lays them out (rcl_action's design), from the .action text
_GOAL, _RESULT, _FEEDBACK = re.split(r"^---$", ACTION_FILE.read_text(), flags=re.MULTILINE)
_STORE = get_typestore(Stores.ROS2_JAZZY)
for _name, _text in {
    "FlyPath_Goal": _GOAL,
    "FlyPath_Result": _RESULT,
    "FlyPath_Feedback": _FEEDBACK,
    "SendGoal_Request": "unique_identifier_msgs/UUID goal_id\ncdprd_interfaces/FlyPath_Goal goal",
    "SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp",
    "GetResult_Request": "unique_identifier_msgs/UUID goal_id",
    "GetResult_Response": "int8 status\ncdprd_interfaces/FlyPath_Result result",
    "FeedbackMessage": (
        "unique_identifier_msgs/UUID goal_id\ncdprd_interfaces/FlyPath_Feedback feedback"
    ),
    "CancelGoal_Request": "action_msgs/GoalInfo goal_info",
    "CancelGoal_Response": "int8 return_code\naction_msgs/GoalInfo[] goals_canceling",
}.items():
    _STORE.register(get_types_from_msg(_text, f"cdprd_interfaces/msg/{_name}"))


def msg(name: str, **fields: Any) -> Any:
    return _STORE.types[f"cdprd_interfaces/msg/{name}"](**fields)


def encode(message: Any) -> bytes:
    return bytes(_STORE.serialize_cdr(message, message.__msgtype__))


def decode(raw: bytes, name: str) -> Any:
    return _STORE.deserialize_cdr(raw, f"cdprd_interfaces/msg/{name}")


def key(part: str, type_name: str, type_hash: str, action: str = "fly_path") -> str:
    """<domain>/<action>/_action/<part>/<DDS type name>/<hash> (rcl_action's names.c)."""
    return f"0/{action}/_action/{part}/{type_name}/{type_hash}"


SEND_GOAL = key("send_goal", f"{DDS}SendGoal_", SEND_GOAL_HASH)
GET_RESULT = key("get_result", f"{DDS}GetResult_", GET_RESULT_HASH)
CANCEL_GOAL = key("cancel_goal", "action_msgs::srv::dds_::CancelGoal_", CANCEL_GOAL_HASH)
FEEDBACK = key("feedback", f"{DDS}FeedbackMessage_", FEEDBACK_HASH)
STATUS = key("status", "action_msgs::msg::dds_::GoalStatusArray_", STATUS_ARRAY_HASH)


def uuid_msg(goal_id: bytes) -> Any:
    return _STORE.types["unique_identifier_msgs/msg/UUID"](
        uuid=np.frombuffer(goal_id, dtype=np.uint8).copy()
    )


def time_msg(ns: int) -> Any:
    return _STORE.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def path(*poses: tuple[float, tuple[float, float, float]], frame: str = "world") -> Any:
    """A nav_msgs/msg/Path of (time s, position) poses, identity orientation."""
    types = _STORE.types
    header = types["std_msgs/msg/Header"]
    stamped = [
        types["geometry_msgs/msg/PoseStamped"](
            header=header(stamp=time_msg(int(t * 1e9)), frame_id=frame),
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        )
        for t, (x, y, z) in poses
    ]
    return types["nav_msgs/msg/Path"](
        header=header(stamp=time_msg(0), frame_id=frame), poses=stamped
    )


SHORT = path((0.0, (0.0, 0.0, 1.25)), (0.6, (0.03, 0.0, 1.25)))  # a 0.6 s trajectory
LONG = path((0.0, (0.0, 0.0, 1.25)), (3.0, (0.1, 0.0, 1.25)))


def goal_request(goal_id: bytes, flown: Any) -> bytes:
    return encode(
        msg("SendGoal_Request", goal_id=uuid_msg(goal_id), goal=msg("FlyPath_Goal", path=flown))
    )


class Client:
    """An action client's requests, each with its sequence number (from 1), to action
    `action` of domain `domain`, each answer awaited up to `timeout` s."""

    def __init__(
        self,
        session: zenoh.Session,
        domain: int = 0,
        action: str = "fly_path",
        timeout: float = WAIT,
    ) -> None:
        self.session = session
        self.sequence = 0
        self.timeout = timeout
        self.keys = {
            name: k.replace("0/fly_path/", f"{domain}/{action.strip('/')}/", 1)
            for name, k in (("send", SEND_GOAL), ("result", GET_RESULT), ("cancel", CANCEL_GOAL))
        }

    def attachment(self) -> bytes:
        self.sequence += 1
        return request_attachment(self.sequence)

    def send_goal(self, goal_id: bytes, flown: Any) -> Any:
        request = goal_request(goal_id, flown)
        (reply,) = call(self.session, self.keys["send"], request, self.attachment(), self.timeout)
        return self._response(reply, "SendGoal_Response")

    def get_result(self, goal_id: bytes) -> Callable[[], Any]:
        """Ask for the result now; the returned call waits for it."""
        request = encode(msg("GetResult_Request", goal_id=uuid_msg(goal_id)))
        replies = self.session.get(
            self.keys["result"],
            payload=request,
            attachment=self.attachment(),
            target=zenoh.QueryTarget.ALL_COMPLETE,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout,
        )
        return lambda: self._response(next(iter(replies)), "GetResult_Response")

    def cancel(self, goal_id: bytes = bytes(16), before_ns: int = 0) -> Any:
        info = _STORE.types["action_msgs/msg/GoalInfo"](
            goal_id=uuid_msg(goal_id), stamp=time_msg(before_ns)
        )
        request = encode(msg("CancelGoal_Request", goal_info=info))
        (reply,) = call(self.session, self.keys["cancel"], request, self.attachment(), self.timeout)
        return self._response(reply, "CancelGoal_Response")

    def _response(self, reply: zenoh.Reply, name: str) -> Any:
        """The Response, after checking rmw_zenoh's reply attachment."""
        assert reply.ok is not None, reply.err
        echoed, stamp, size, gid = struct.unpack("<qqB16s", reply.ok.attachment.to_bytes())
        assert (size, gid) == (16, bytes(range(100, 116)))
        assert echoed <= self.sequence and stamp > 0
        return decode(reply.ok.payload.to_bytes(), name)


class Flying(StandIn):
    """The stand-in answering a flight as the planner does: each trajectory flown from
    LEAD s after it is accepted, its core-time start and end in the reply, its motion
    (with the claim's id) in the state, and the core's events to the subscribers: its
    trajectory_done at its end, a hold's state event."""

    def __init__(self) -> None:
        super().__init__()
        self.t0 = time.monotonic()
        self.motion: dict[str, Any] | None = None
        self.timer: asyncio.TimerHandle | None = None

    def now(self) -> float:
        return time.monotonic() - self.t0

    def submit_trajectory(self, trajectory: Trajectory, start: float | None, claim: Any) -> Any:
        self._record("trajectory", trajectory, start, claim)
        begin = self.now() + LEAD
        end = begin + trajectory.duration
        self._stop()
        self.motion = {"what": "trajectory", "client": claim.client, "id": claim.id}
        loop = asyncio.get_running_loop()
        self.timer = loop.call_later(end - self.now(), self._done)
        return {
            "accepted": True,
            "what": "trajectory",
            "start": begin,
            "end": end,
            "duration": end - begin,
        }

    def command(self, name: str, args: dict[str, Any]) -> Any:
        if name != "hold":
            return super().command(name, args)
        self._record(name, args)
        self._stop()
        self.emit({"event": "state", "why": "hold"})
        return {"state": "hold", "command": "hold"}

    def state(self) -> dict[str, Any]:
        moving = "tracking" if self.motion else "hold"
        return {**super().state(), "t": self.now(), "state": moving, "motion": self.motion}

    def emit(self, event: dict[str, Any]) -> None:
        event.setdefault("t", self.now())
        event.setdefault("state", "hold")
        for sink in self.sinks:
            sink(event)

    def _stop(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
        self.motion = self.timer = None

    def _done(self) -> None:
        self.motion = self.timer = None
        self.emit({"event": "trajectory_done"})


class Watch:
    """The feedback and status messages received, decoded as they come."""

    def __init__(self, session: zenoh.Session) -> None:
        self.feedback: list[Any] = []
        self.status: list[list[tuple[bytes, int]]] = []
        self.lock = threading.Lock()
        self.entities = [
            session.declare_subscriber(FEEDBACK, self._on_feedback),
            session.declare_subscriber(STATUS, self._on_status),
        ]
        time.sleep(0.3)  # the subscriptions' way to the daemon's session

    def _on_feedback(self, sample: zenoh.Sample) -> None:
        assert sample.attachment is not None and len(sample.attachment.to_bytes()) == 33
        with self.lock:
            self.feedback.append(decode(sample.payload.to_bytes(), "FeedbackMessage"))

    def _on_status(self, sample: zenoh.Sample) -> None:
        array = _STORE.deserialize_cdr(sample.payload.to_bytes(), "action_msgs/msg/GoalStatusArray")
        with self.lock:
            self.status.append(
                [(bytes(s.goal_info.goal_id.uuid), s.status) for s in array.status_list]
            )

    def statuses(self, goal_id: bytes) -> list[int]:
        """The goal's successive statuses, repeats merged."""
        out: list[int] = []
        with self.lock:
            for array in self.status:
                for gid, status in array:
                    if gid == goal_id and (not out or out[-1] != status):
                        out.append(status)
        return out

    def close(self) -> None:
        for entity in self.entities:
            entity.undeclare()


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def new_id() -> bytes:
    return uuid_module.uuid4().bytes


# -- the derivation ---------------------------------------------------------------------


def test_the_derived_types_hash_as_rosidls_generated_code() -> None:
    """example_interfaces/action/Fibonacci through action_types gives the hashes of the
    generated code (and the reference records them), as do action_msgs' types."""
    text = (
        "# Goal\nint32 order\n---\n# Result\nint32[] sequence\n---\n# Feedback\nint32[] sequence\n"
    )
    action = "example_interfaces/action/Fibonacci"
    ros2_wire.register(ros2_wire.action_types(action, text))
    reference = REFERENCE.read_text()
    for suffix, expected in FIBONACCI.items():
        assert ros2_wire.type_hash(action + suffix) == f"RIHS01_{expected}", suffix
        assert expected in reference, suffix
    assert ros2_wire.type_hash(ros2_wire.CANCEL_GOAL) == CANCEL_GOAL_HASH
    assert ros2_wire.type_hash("action_msgs/msg/GoalStatusArray") == STATUS_ARRAY_HASH
    assert CANCEL_GOAL_HASH.removeprefix("RIHS01_") in reference
    assert STATUS_ARRAY_HASH.removeprefix("RIHS01_") in reference


def test_fly_paths_types_are_the_pinned_ones() -> None:
    from daemon.interface import ros2_action

    assert ros2_wire.type_hash(f"{ros2_action.ACTION}_SendGoal") == SEND_GOAL_HASH
    assert ros2_wire.type_hash(f"{ros2_action.ACTION}_GetResult") == GET_RESULT_HASH
    assert ros2_wire.type_hash(f"{ros2_action.ACTION}_FeedbackMessage") == FEEDBACK_HASH


# -- goals ------------------------------------------------------------------------------


def test_a_goal_flies_with_rising_feedback_and_succeeds() -> None:
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    watch = Watch(s)
    client = Client(s)
    goal_id = new_id()
    try:
        before = time.time_ns()
        answer = client.send_goal(goal_id, SHORT)
        result = client.get_result(goal_id)()  # asked at once, answered at the end
        wait_for(lambda: SUCCEEDED in watch.statuses(goal_id), "the status SUCCEEDED")
    finally:
        watch.close()
        s.close()
        served.stop()
    assert answer.accepted is True
    assert before <= answer.stamp.sec * 10**9 + answer.stamp.nanosec <= time.time_ns()
    assert result.status == SUCCEEDED
    assert result.result.success is True
    assert '"duration":' in result.result.message and '"accepted":true' in result.result.message
    assert 0.6 <= result.result.duration < 0.7  # the stand-in's start to end
    assert watch.statuses(goal_id) == [EXECUTING, SUCCEEDED]
    ours = [f.feedback for f in watch.feedback if bytes(f.goal_id.uuid) == goal_id]
    assert len(ours) >= 3  # 20 Hz over 0.65 s, on a loaded host a few at least
    progress = [f.progress for f in ours]
    assert progress == sorted(progress) and 0.0 <= progress[0] < progress[-1] <= 1.0
    remaining = [f.time_remaining for f in ours]
    assert remaining == sorted(remaining, reverse=True) and remaining[0] <= 0.65 + 1e-9
    assert all(f.tracking_error == 0.0 for f in ours)  # the stand-in tracks perfectly
    assert ours[-1].pose.header.frame_id == "world"
    assert ours[-1].pose.pose.position.z == 1.25
    (flown,) = [c for c in handler.calls if c[0] == "trajectory"]
    claim = flown[3]
    assert (claim.client, claim.preempt, claim.id) == (
        "anonymous",
        False,
        f"/fly_path#{goal_id.hex()}",
    )
    assert flown[1].duration == pytest.approx(0.6)


def test_a_status_subscription_that_joins_late_gets_the_last_list() -> None:
    """rcl_action's status topic is transient local, keep last 1: a subscription
    declared as rmw_zenoh declares a transient-local one, after the goal ended, still
    gets the list with the goal SUCCEEDED."""
    from tests.daemon.test_ros2_model import LateSubscription

    served = Running(Flying(), ros2=ROS2)
    s = served.session()
    client = Client(s)
    goal_id = new_id()
    try:
        assert client.send_goal(goal_id, SHORT).accepted is True
        assert client.get_result(goal_id)().status == SUCCEEDED
        late = LateSubscription(s, STATUS, depth=1)
        (payload, (sequence, _stamp, size, _gid)), *_ = late.wait()
    finally:
        s.close()
        served.stop()
    array = _STORE.deserialize_cdr(payload, "action_msgs/msg/GoalStatusArray")
    assert [(bytes(x.goal_info.goal_id.uuid), x.status) for x in array.status_list] == [
        (goal_id, SUCCEEDED)
    ]
    assert size == 16 and sequence >= 3  # the empty list, EXECUTING, SUCCEEDED before it


def test_a_goal_that_ends_publishes_its_status_before_it_answers_the_results_waiting() -> None:
    """A client that has the result and then joins the status topic must find the goal
    terminal there: the status is put before the waiting get_result is answered (the
    other way round, a late subscription between the two got EXECUTING: a CI failure of
    the test above under load)."""
    from daemon.interface import ros2_action

    events: list[tuple[str, Any]] = []

    class Query:
        def reply(self, key: str, payload: bytes, attachment: bytes) -> None:
            events.append(("result", key))

        def drop(self) -> None:
            pass

    class Status:
        def put(self, msg: Any) -> None:
            events.append(("status", [x.status for x in msg.status_list]))

    server = ros2_action.FlyPathServer(ROS2, None, None, 1 << 20, None)  # type: ignore[arg-type]
    server._status = Status()
    server._loop = asyncio.new_event_loop()
    try:
        goal = ros2_action._Goal(bytes(16), "fly_path#0", 0, accepted=True, status=EXECUTING)
        server._remember(goal)
        request = ros2_wire.Attachment(1, 0, bytes(16))
        server._pending.take(request)
        goal.waiting.append((Query(), "fly_path/_action/get_result", request))
        server._finish(goal, SUCCEEDED, "done")
    finally:
        server._loop.close()
    assert events == [("status", [SUCCEEDED]), ("result", "fly_path/_action/get_result")]


@pytest.mark.parametrize(
    ("flown", "reason"),
    [
        (path((0.0, (0.0, 0.0, 1.25)), (1.0, (0.1, 0.0, 1.25)), frame="map"), "frame 'map'"),
        (path((0.0, (0.0, 0.0, 1.25)), (1.0, (float("nan"), 0.0, 1.25))), "waypoint 1"),
        (path(), "a Path without poses"),
    ],
    ids=["foreign frame", "NaN", "no poses"],
)
def test_a_bad_goal_is_refused_and_its_result_names_why(flown: Any, reason: str) -> None:
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    watch = Watch(s)
    client = Client(s)
    goal_id = new_id()
    try:
        answer = client.send_goal(goal_id, flown)
        result = client.get_result(goal_id)()
        unknown = client.get_result(new_id())()
        time.sleep(0.2)
    finally:
        watch.close()
        s.close()
        served.stop()
    assert answer.accepted is False
    assert result.status == ABORTED and result.result.success is False
    assert reason in result.result.message and ": " in result.result.message
    assert unknown.status == UNKNOWN  # as rclcpp_action answers a goal it does not know
    assert watch.statuses(goal_id) == []  # a refused goal is in no status list
    assert [c for c in handler.calls if c[0] == "trajectory"] == []


def test_a_cancel_holds_the_robot_and_ends_the_goal_canceled() -> None:
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    watch = Watch(s)
    client = Client(s)
    goal_id = new_id()
    try:
        assert client.send_goal(goal_id, LONG).accepted
        result = client.get_result(goal_id)
        wait_for(lambda: len(watch.feedback) >= 2, "feedback")
        canceled = client.cancel(goal_id)
        ended = result()
        again = client.cancel(goal_id)
        unknown = client.cancel(new_id())
    finally:
        watch.close()
        s.close()
        served.stop()
    assert canceled.return_code == ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in canceled.goals_canceling] == [goal_id]
    assert ended.status == CANCELED and ended.result.success is False
    assert '"command":"hold"' in ended.result.message  # the hold's answer
    assert 0.0 < ended.result.duration < 3.0
    assert watch.statuses(goal_id) == [EXECUTING, CANCELING, CANCELED]
    assert (again.return_code, list(again.goals_canceling)) == (ERROR_GOAL_TERMINATED, [])
    assert (unknown.return_code, list(unknown.goals_canceling)) == (ERROR_UNKNOWN_GOAL_ID, [])
    assert [c[0] for c in handler.calls] == ["trajectory", "hold"]


def test_cancels_by_stamp_and_of_all_follow_rcl_action() -> None:
    """A stamp cancels the goals accepted at or before it, a zero id and stamp all of
    them; none to cancel is no error (ERROR_NONE, an empty list)."""
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    client = Client(s)
    first, second = new_id(), new_id()
    try:
        none = client.cancel()  # nothing flies
        stamp = client.send_goal(first, LONG).stamp
        before = client.cancel(bytes(16), stamp.sec * 10**9 + stamp.nanosec - 1)
        assert client.send_goal(second, LONG).accepted
        every = client.cancel()
        ended = client.get_result(second)()
    finally:
        s.close()
        served.stop()
    assert (none.return_code, list(none.goals_canceling)) == (ERROR_NONE, [])
    assert (before.return_code, list(before.goals_canceling)) == (ERROR_NONE, [])
    assert every.return_code == ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in every.goals_canceling] == [second]
    assert ended.status == CANCELED


def test_a_new_goal_replaces_the_one_flying_and_a_brake_aborts() -> None:
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    client = Client(s)
    first, second = new_id(), new_id()
    try:
        assert client.send_goal(first, LONG).accepted
        replaced = client.get_result(first)
        assert client.send_goal(second, LONG).accepted
        braked = client.get_result(second)
        replaced_result = replaced()
        served.loop.call_soon_threadsafe(
            handler.emit,
            {"event": "brake", "state": "braked", "trigger": "command", "message": "by test"},
        )
        braked_result = braked()
    finally:
        s.close()
        served.stop()
    assert replaced_result.status == ABORTED
    assert replaced_result.result.message == f"preempted: replaced by goal /fly_path#{second.hex()}"
    assert braked_result.status == ABORTED
    assert braked_result.result.message == "invalid_state: the robot is braked (command: by test)"


def test_another_motion_taking_over_aborts_the_goal() -> None:
    """A flight of the same anonymous client (a Path on the topic) raises no event: the
    state's motion, read at the feedback rate, names another flight."""
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    client = Client(s)
    goal_id = new_id()
    try:
        assert client.send_goal(goal_id, LONG).accepted
        result = client.get_result(goal_id)
        handler.motion = {"what": "trajectory", "client": "anonymous"}
        ended = result()
    finally:
        s.close()
        served.stop()
    assert ended.status == ABORTED
    assert ended.result.message == "preempted: replaced by trajectory from anonymous"


# -- hostile requests -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("what", "where", "payload", "attachment"),
    [
        ("no attachment", SEND_GOAL, goal_request(bytes(16), SHORT), None),
        (
            "a short attachment",
            SEND_GOAL,
            goal_request(bytes(16), SHORT),
            request_attachment(1)[:-1],
        ),
        ("truncated CDR", SEND_GOAL, goal_request(bytes(16), SHORT)[:-7], request_attachment(1)),
        (
            "trailing bytes",
            SEND_GOAL,
            goal_request(bytes(16), SHORT) + bytes(8),
            request_attachment(1),
        ),
        ("no goal id", SEND_GOAL, bytes([0, 1, 0, 0, 7]), request_attachment(1)),
        (
            "a wrong hash",
            SEND_GOAL.replace("RIHS01_f", "RIHS01_0"),
            goal_request(bytes(16), SHORT),
            request_attachment(1),
        ),
        ("a cancel without attachment", CANCEL_GOAL, bytes(4 + 24), None),
        ("a result request, malformed", GET_RESULT, bytes([0, 1, 0, 0, 1]), request_attachment(1)),
    ],
    ids=lambda value: value if isinstance(value, str) and not value.startswith("0/") else "",
)
def test_requests_rmw_zenoh_would_not_take_get_no_reply(
    what: str, where: str, payload: bytes, attachment: bytes | None
) -> None:
    handler = Flying()
    served = Running(handler, ros2=ROS2)
    s = served.session()
    try:
        replies = call(s, where, payload, attachment, timeout=1.0)
        alive = Client(s).send_goal(new_id(), SHORT)  # the action still answers
    finally:
        s.close()
        served.stop()
    assert replies == [], what
    assert alive.accepted is True
    assert [c[0] for c in handler.calls] == ["trajectory"], what


def test_the_action_is_announced_as_rcl_action_declares_it() -> None:
    ros2 = Ros2Settings(enabled=True, namespace="/lab", fly_path_action="fly")
    served = Running(Flying(), ros2=ros2)
    s = served.session()
    try:
        replies = s.liveliness().get(
            "@ros2_lv/0/*/*/*/*/%/%lab/cdprd/%lab%fly%_action%$*/**", timeout=WAIT
        )
        tokens = sorted(str(r.ok.key_expr).split("/", 9)[5:] for r in replies if r.ok is not None)
    finally:
        s.close()
        served.stop()
    expected = sorted(
        [
            [
                "SS",
                "%",
                "%lab",
                "cdprd",
                f"%lab%fly%_action%send_goal/{DDS}SendGoal_/{SEND_GOAL_HASH}/{SERVICES_QOS}",
            ],
            [
                "SS",
                "%",
                "%lab",
                "cdprd",
                f"%lab%fly%_action%cancel_goal/action_msgs::srv::dds_::CancelGoal_/{CANCEL_GOAL_HASH}/{SERVICES_QOS}",
            ],
            [
                "SS",
                "%",
                "%lab",
                "cdprd",
                f"%lab%fly%_action%get_result/{DDS}GetResult_/{GET_RESULT_HASH}/{SERVICES_QOS}",
            ],
            [
                "MP",
                "%",
                "%lab",
                "cdprd",
                f"%lab%fly%_action%feedback/{DDS}FeedbackMessage_/{FEEDBACK_HASH}/{SERVICES_QOS}",
            ],
            [
                "MP",
                "%",
                "%lab",
                "cdprd",
                f"%lab%fly%_action%status/action_msgs::msg::dds_::GoalStatusArray_/{STATUS_ARRAY_HASH}/{STATUS_QOS}",
            ],
        ]
    )
    assert tokens == expected


def test_the_action_takes_the_limits_of_trajectories_hold_and_status() -> None:
    limited = ZenohSettings(
        ingress_limits_hz={"trajectory": 2.0, "cmd/hold": 20.0, "cmd/status": 50.0}
    )
    limits = ingress_limits(ROS2, limited)
    assert {k: v for k, v in limits.items() if "_action" in k} == {
        SEND_GOAL: 2.0,
        CANCEL_GOAL: 20.0,
        GET_RESULT: 50.0,
    }


# -- the simulated robot ----------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.host_timing
@pytest.mark.timeout(180)
def test_the_simulated_robot_flies_a_goal_and_a_cancel_holds_it(tmp_path: Path) -> None:
    """`cdprd run --sim` with ROS 2 on (domain 7, namespace /lab): enabled by its
    service, the robot flies a goal to SUCCEEDED with rising feedback, and a second,
    longer goal cancelled midway ends CANCELED, the robot holding."""
    from tests.daemon.test_ros2_process import DOMAIN, NAMESPACE, PREFIX, _listening, wait
    from tests.daemon.test_ros2_services import service_key, trigger
    from tests.loopback import free_port, zenoh_peer
    from tests.processes import CONFIG, ROOT, finish, start_daemon

    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["ros2"] = {"enabled": True, "domain_id": DOMAIN, "namespace": NAMESPACE, "rate_hz": 20}
    data["safety"]["stale_cycles"] = 100  # a loaded host's late feedback is not the point
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    proc = start_daemon(config, "--sim")
    flights = {
        "short": path((0.0, (0.0, 0.0, 1.25)), (1.5, (0.05, 0.0, 1.25))),
        "long": path((0.0, (0.0, 0.0, 1.25)), (8.0, (0.2, 0.0, 1.25))),
    }
    try:
        wait(lambda: _listening(port), 60.0, "the daemon to listen")
        s = zenoh_peer(port)
        feedback: list[Any] = []
        kept = s.declare_subscriber(
            FEEDBACK.replace("0/fly_path/", f"{DOMAIN}/lab/fly_path/", 1),
            lambda x: feedback.append(decode(x.payload.to_bytes(), "FeedbackMessage").feedback),
        )
        states: list[str] = []
        kept_state = s.declare_subscriber(
            f"{PREFIX}/state", lambda x: states.append(json.loads(x.payload.to_bytes())["state"])
        )
        client = Client(s, DOMAIN, f"{NAMESPACE}/fly_path", timeout=60.0)  # a cold host
        try:
            wait(lambda: bool(states) and states[-1] == "idle", 60.0, "idle")
            enable = service_key(f"{NAMESPACE}/enable", DOMAIN)
            assert trigger(s, enable, 900).success
            first, second = new_id(), new_id()
            assert client.send_goal(first, flights["short"]).accepted
            result = client.get_result(first)()
            assert client.send_goal(second, flights["long"]).accepted
            canceling = client.get_result(second)
            wait(lambda: bool(feedback) and feedback[-1].progress > 0.1, 30.0, "flying")
            canceled = client.cancel(second)
            ended = canceling()
        finally:
            kept.undeclare()
            kept_state.undeclare()
            s.close()
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert result.status == SUCCEEDED and result.result.success, result
    assert result.result.duration > 1.5  # the approach, then the trajectory
    assert canceled.return_code == ERROR_NONE
    assert ended.status == CANCELED, ended
    assert '"state":"hold"' in ended.result.message
    progress = [f.progress for f in feedback]
    assert max(progress) > 0.1
