"""The ROS 2 bridge's keys behind the same gates as the zenoh interface's JSON keys
(DESIGN §19): the hardware template's access control, the ingress limits, the size cap and
the parse thread with its CPU budget.  Each test is the ROS 2 twin of a JSON-key test in
test_zenoh_io.py and runs on its machinery (Running: the interface, and here the bridge on
its session, on a free loopback port), with ROS 2 samples written as in
test_ros2_process.py (rmw_zenoh's keys, rosbags' CDR)."""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

import pytest
import zenoh

from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings, build_zenoh_config
from daemon.interface import ros2_action, ros2_wire
from daemon.interface.ros2_bridge import ingress_limits, service_keys
from tests.daemon.test_ros2_process import MULTI_DOF, PATH, POSE, STATUS, dds, path
from tests.daemon.test_zenoh_io import (
    PREFIX,
    WAIT,
    Running,
    StandIn,
    ask,
    template_zenoh,
    wait_until,
)

ROS2 = Ros2Settings(enabled=True, rate_hz=20.0)  # domain 0, namespace /
FORGED = b"forged"
HOME = [0.0, 0.0, 1.25]
IDENTITY = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
PATHS = 4  # long ones in a row: one parsing, three waiting (ros2.queue_depth 4)


def key(topic: str, msgtype: str) -> str:
    return ros2_wire.topic_key(ROS2.domain_id, topic, msgtype)


PATH_KEY = key("/path", PATH)
OUTPUTS = {  # the daemon's ROS 2 topics a forger tries
    "pose": key("/pose", POSE),
    "diagnostics": key("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    "trajectory_status": key("/trajectory_status", STATUS),
    "robot_description": key("/robot_description", STATUS),
    "tf_static": key("/tf_static", "tf2_msgs/msg/TFMessage"),
    "cables": key("/cables", "visualization_msgs/msg/MarkerArray"),
    "action_status": key("/fly_path/_action/status", "action_msgs/msg/GoalStatusArray"),
}


class Verdicts:
    """The bridge's verdicts on the status topic, decoded."""

    def __init__(self, session: zenoh.Session) -> None:
        self.items: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(OUTPUTS["trajectory_status"], self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        text = ros2_wire.deserialize(sample.payload.to_bytes(), STATUS).data
        with self._lock:
            self.items.append(json.loads(text))

    def count(self) -> int:
        with self._lock:
            return len(self.items)


def attachment(sequence: int) -> bytes:
    return ros2_wire.attachment(sequence, time.time_ns(), bytes(16))


# -- access control -------------------------------------------------------------------------


@pytest.mark.parametrize("access_control", [True, False])
def test_with_the_templates_zenoh_section_only_the_daemon_speaks_ros2(
    access_control: bool,
) -> None:
    """Another local process publishes on the daemon's ROS 2 topics (pose, diagnostics,
    trajectory_status, the robot's description, static frames, cables and the action's
    status) and declares a second node `cdprd`.  With the template's zenoh section none
    of it reaches a subscriber, which still gets the daemon's own poses; without its
    access control (the control case) all of it does."""
    served = Running(StandIn(), template_zenoh(access_control), ros2=ROS2)
    forger, listener = served.session(), served.session()
    seen: list[tuple[str, bytes]] = []
    declared: list[Any] = []  # kept: zenoh undeclares what is dropped
    forged_node = f"@ros2_lv/0/{forger.info.zid()}/0/0/NN/%/%/cdprd"
    try:
        declared += [
            listener.declare_subscriber(
                "0/**", lambda s: seen.append((str(s.key_expr), s.payload.to_bytes()))
            ),
            forger.liveliness().declare_token(forged_node),
        ]

        def own_poses() -> int:
            return sum(1 for k, p in seen if k == OUTPUTS["pose"] and p != FORGED)

        wait_until(lambda: own_poses() >= 1, "the daemon's pose")
        for _ in range(20):
            for key_expr in OUTPUTS.values():
                forger.put(key_expr, FORGED, attachment=attachment(1))
        list(forger.get(f"{PREFIX}/trajectory", timeout=WAIT))  # after the puts, on one link

        def nodes() -> list[str]:
            replies = listener.liveliness().get("@ros2_lv/0/*/*/*/NN/**", timeout=WAIT)
            return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)

        def forged_on() -> dict[str, int]:
            return {k: sum(1 for s, p in seen if s == k and p == FORGED) for k in OUTPUTS.values()}

        if not access_control:
            wait_until(lambda: min(forged_on().values()) == 20, "the forged puts")
            wait_until(lambda: forged_node in nodes(), "the forged node")
            return
        poses = own_poses()
        wait_until(lambda: own_poses() >= poses + 3, "three more poses")  # forged ones came by
        tokens = nodes()
        counts = forged_on()
    finally:
        declared.clear()
        forger.close()
        listener.close()
        served.stop()
    assert counts == dict.fromkeys(OUTPUTS.values(), 0)
    assert len(tokens) == 1 and tokens[0].endswith("/NN/%/%/cdprd"), tokens
    assert forged_node not in tokens


# -- ingress limits --------------------------------------------------------------------------


def test_the_ros2_trajectory_topics_take_the_trajectory_limit_or_their_own() -> None:
    """(The services take their commands' limits: test_ros2_services.py.)"""
    intake = {key("/path", PATH), key("/multi_dof_trajectory", MULTI_DOF)}
    assert all(dds(PATH) in k or dds(MULTI_DOF) in k for k in intake)
    services = set(service_keys(ROS2))
    # the action's send_goal as a trajectory topic, its cancel_goal and get_result as
    # services (test_ros2_action.py)
    action = ros2_action.services(ROS2)
    intake |= {k for k, (_name, srvtype) in action.items() if srvtype.endswith("_SendGoal")}
    services |= set(action) - intake
    limited = ZenohSettings(ingress_limits_hz={"trajectory": 5.0, "cmd/*": 20.0})
    assert ingress_limits(ROS2, limited) == {
        **dict.fromkeys(intake, 5.0),
        **dict.fromkeys(services, 20.0),
    }
    assert ingress_limits(ROS2, ZenohSettings(ingress_limits_hz={"**": 3.0})) == dict.fromkeys(
        intake | services, 3.0
    )
    own = ROS2.model_copy(update={"ingress_limit_hz": 1.0})
    assert ingress_limits(own, limited) == {
        **dict.fromkeys(intake, 1.0),
        **dict.fromkeys(services, 20.0),
    }
    assert ingress_limits(ROS2, ZenohSettings()) == {}
    assert ingress_limits(ROS2.model_copy(update={"enabled": False}), limited) == {}
    (entry,) = json.loads(
        build_zenoh_config(limited, PREFIX, ingress_limits(ROS2, limited)).get_json("downsampling")
    )
    rules = {rule["key_expr"]: rule["freq"] for rule in entry["rules"]}
    assert rules == {
        f"{PREFIX}/trajectory": 5.0,
        f"{PREFIX}/cmd/*": 20.0,
        **dict.fromkeys(intake, 5.0),
        **dict.fromkeys(services, 20.0),
    }


def test_zenoh_drops_paths_that_come_faster_than_the_trajectory_limit() -> None:
    """With trajectory limited to 2 Hz, a burst of ten Paths reaches the bridge as one (one
    verdict), and a Path half a second later is let through (test_zenoh_io's
    test_zenoh_drops_what_comes_faster_than_the_ingress_limit for the JSON key)."""
    served = Running(StandIn(), ingress_limits_hz={"trajectory": 2.0}, ros2=ROS2)
    try:
        with served.session() as session:
            verdicts = Verdicts(session)
            for k in range(10):
                session.put(PATH_KEY, b"not cdr", attachment=attachment(1 + k))
            wait_until(lambda: verdicts.count() >= 1, "the first verdict")
            time.sleep(0.3)
            assert verdicts.count() == 1
            assert ask(session, "cmd/status")["ok"]  # the zenoh interface: not limited
            time.sleep(0.3)
            session.put(PATH_KEY, b"not cdr", attachment=attachment(11))
            wait_until(lambda: verdicts.count() == 2, "the Path after 0.6 s")
    finally:
        served.stop()


# -- size cap --------------------------------------------------------------------------------


def path_of(poses: int, frame_id: str = "world") -> bytes:
    raw = path([(0.01 * k, HOME) for k in range(poses)], IDENTITY)
    if frame_id == "world":
        return raw
    msg = ros2_wire.deserialize(raw, PATH)
    msg.header.frame_id = frame_id
    return ros2_wire.serialize(msg)


def test_paths_too_large_or_too_long_are_refused_before_any_decoding(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 4 MB Path is above zenoh.max_message_bytes (2 MiB, the cap of the JSON key too)
    and is refused by its size; a Path that declares more poses than max_waypoints by the
    count in its first bytes: the CDR decoder never runs, the handler sees nothing."""
    decoded: list[int] = []
    original = ros2_wire.deserialize

    def deserialize(raw: bytes, msgtype: str) -> Any:
        if msgtype == PATH:
            decoded.append(len(raw))
        return original(raw, msgtype)

    large = path_of(2, frame_id="x" * 4_000_000)
    long = path_of(10_001)
    assert len(large) > 4_000_000 and len(long) < 2 * 2**20
    monkeypatch.setattr(ros2_wire, "deserialize", deserialize)
    handler = StandIn()
    served = Running(handler, ros2=ROS2)
    try:
        with served.session() as session:
            verdicts = Verdicts(session)
            session.put(PATH_KEY, large, attachment=attachment(1))
            session.put(PATH_KEY, long, attachment=attachment(2))
            wait_until(lambda: verdicts.count() >= 2, "two verdicts")
    finally:
        served.stop()
    first, second = verdicts.items
    assert first["event"] == second["event"] == "trajectory_rejected"
    assert first["error"]["limit"] == "max_message_bytes", first
    assert first["error"]["value"] == len(large)
    assert second["error"]["limit"] == "max_waypoints", second
    assert second["error"]["value"] == 10_001
    assert decoded == [] and handler.calls == []


def test_the_declared_count_is_read_as_the_decoder_reads_it() -> None:
    for poses in (1, 3, 17):
        raw = path_of(poses, frame_id="a" * poses)
        assert ros2_wire.sequence_length(raw, PATH) == poses
    assert ros2_wire.sequence_length(b"", PATH) is None
    assert ros2_wire.sequence_length(path_of(3)[:18], PATH) is None  # cut in the frame id
    assert ros2_wire.sequence_length(b"\x01\x01\x00\x00" + bytes(20), PATH) is None  # not CDR


# -- parse thread and budget -----------------------------------------------------------------


def test_long_paths_parse_in_the_interfaces_budgeted_thread_and_status_is_answered() -> None:
    """A run of long Paths (1000 poses, ~0.5 s of CPU each under the pause hook) is
    decoded in the zenoh interface's parse thread under its CPU budget (its pause hook
    installed), never on the loop or a thread of the bridge's own; meanwhile every status
    query is answered."""
    where: list[tuple[str, str]] = []
    original = ros2_wire.deserialize

    def deserialize(raw: bytes, msgtype: str) -> Any:
        if msgtype == PATH:
            where.append((threading.current_thread().name, type(sys.getprofile()).__name__))
        return original(raw, msgtype)

    long = path_of(1000)
    served = Running(StandIn(), ros2=ROS2)
    ros2_wire.deserialize = deserialize  # type: ignore[assignment]
    try:
        with served.session() as session:
            verdicts = Verdicts(session)
            for k in range(PATHS):  # blocking: a sender's full queue drops puts by default
                block = zenoh.CongestionControl.BLOCK
                session.put(PATH_KEY, long, attachment=attachment(1 + k), congestion_control=block)
            answered = [ask(session, "cmd/status")["ok"] for _ in range(10)]
            end = time.monotonic() + 20 * WAIT  # the budget: 1/4 of a core, on a loaded host
            while verdicts.count() < PATHS:
                assert time.monotonic() < end, f"{verdicts.count()} verdicts of {PATHS}"
                time.sleep(0.05)
    finally:
        ros2_wire.deserialize = original  # type: ignore[assignment]
        served.stop()
    assert answered == [True] * 10
    assert [v["event"] for v in verdicts.items] == ["trajectory_accepted"] * PATHS, verdicts.items
    assert len(where) == PATHS
    assert {name.split("_")[0] for name, _ in where} == {"cdprd-trajectory-parse"}
    assert {hook for _, hook in where} == {"_Yielding"}


# -- a Path without times is a path ----------------------------------------------------------


@pytest.mark.parametrize("timed", [True, False])
def test_a_path_whose_poses_carry_no_times_is_timed_by_the_daemon(timed: bool) -> None:
    """A planner's nav_msgs/Path (every pose one stamp) is a path: with the daemon's
    timer it reaches the handler timed within the tensions (from the first pose to the
    last, as <prefix>/path would), without one it is rejected saying why."""
    from daemon.config import load_config
    from daemon.service.planner import path_timer
    from tests.daemon.test_zenoh_paths import CONFIG

    corner = [(0.0, HOME), (0.0, [0.2, 0.0, 1.25]), (0.0, [0.2, 0.2, 1.3])]
    timer = path_timer(load_config(CONFIG)) if timed else None
    served = Running(StandIn(), ros2=ROS2, timer=timer)
    try:
        with served.session() as session:
            verdicts = Verdicts(session)
            session.put(PATH_KEY, path(corner, IDENTITY), attachment=attachment(1))
            wait_until(lambda: verdicts.count() == 1, "the verdict")
    finally:
        served.stop()
    [verdict] = verdicts.items
    handed = [c[1] for c in served.handler.calls if c[0] == "trajectory"]
    if not timed:
        assert verdict["event"] == "trajectory_rejected" and handed == [], verdict
        assert "poses without times are a path" in json.dumps(verdict)
        return
    assert verdict["event"] == "trajectory_accepted", verdict
    [trajectory] = handed
    end = trajectory.sample(trajectory.end_time).pose.position
    assert trajectory.duration > 0.5 and list(end) == pytest.approx([0.2, 0.2, 1.3])
