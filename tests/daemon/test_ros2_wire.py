"""rmw_zenoh's wire format (daemon.interface.ros2_wire) against references the project did
not write: the literal examples of rmw_zenoh's design document (tests/data/
rmw_zenoh_reference.md), rosbags' RIHS01 hashes and CDR, zenoh-ext's serializer (which
rmw_zenoh's attachment uses); hostile trajectories refused with a named reason
(daemon.interface.ros2_bridge.read_trajectory); the `ros2:` section; the state as ROS 2
messages (daemon.interface.ros2_convert), decoded by rosbags."""

from __future__ import annotations

import math
import re
import struct
import time
from pathlib import Path

import pytest
import zenoh
import zenoh.ext as ze
from rosbags.typesys import Stores, get_typestore

from cdpr import ConfigError
from cdpr.pose import Pose, liediff
from cdpr.trajectory import TrajectoryLimits
from daemon.config.ros2_config import Ros2Settings
from daemon.interface import ros2_wire as wire
from daemon.interface.messages import TrajectoryRequest
from daemon.interface.ros2_bridge import read_trajectory
from daemon.interface.ros2_convert import state_messages
from daemon.service.api import CommandError
from tests.daemon_stack import config_for

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "rmw_zenoh_reference.md"
STORE = get_typestore(Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ZID = "aac3178e146ba6f1fc6e6a4085e77f21"  # the design document's example session
PATH = "nav_msgs/msg/Path"
MULTI_DOF = "trajectory_msgs/msg/MultiDOFJointTrajectory"
SETTINGS = Ros2Settings(enabled=True)
LIMITS = TrajectoryLimits()
TWO = [(0.0, (0, 0, 1.25)), (1.0, (0, 0, 1.3))]  # a good path: 5 cm up in a second


def _reference_text() -> str:
    return REFERENCE.read_text()


def test_keys_match_the_design_documents_examples() -> None:
    text = _reference_text()
    for topic in ("/chatter", "/robot1/chatter"):
        key = wire.topic_key(0, topic, "std_msgs/msg/String")
        assert f"`{key}`" in text
    assert STORE.hash_rihs01("std_msgs/msg/String") == STRING_HASH


def test_liveliness_tokens_match_the_design_documents_examples() -> None:
    text = _reference_text()
    listener = wire.Node(2, ZID, 0, "/", "listener")
    assert f"`{listener.token()}`" in text
    subscription = listener.entity_token(10, wire.SUBSCRIPTION, "/chatter", "std_msgs/msg/String")
    assert f"`{subscription}`" in text


def test_keys_carry_rosbags_type_hash_for_every_type_used() -> None:
    for msgtype in (
        "geometry_msgs/msg/PoseStamped",
        "sensor_msgs/msg/JointState",
        "tf2_msgs/msg/TFMessage",
        "diagnostic_msgs/msg/DiagnosticArray",
        PATH,
        MULTI_DOF,
    ):
        package, _, name = msgtype.split("/")
        key = wire.topic_key(3, "/ns/topic", msgtype)
        assert key == f"3/ns/topic/{package}::msg::dds_::{name}_/{STORE.hash_rihs01(msgtype)}"


@pytest.mark.parametrize(
    "srvtype",
    [
        "std_srvs/srv/Trigger",
        "std_srvs/srv/Trigger_Request",
        "std_srvs/srv/Trigger_Response",
        "std_srvs/srv/Trigger_Event",
        "std_srvs/srv/SetBool",
        "std_srvs/srv/SetBool_Response",
        "std_srvs/srv/SetBool_Event",
    ],
)
def test_the_trigger_service_hashes_are_jazzys(srvtype: str) -> None:
    """The reference's table of Jazzy's values (tests/data/rmw_zenoh_reference.md)."""
    assert f"| {srvtype} | `{wire.type_hash(srvtype)}` |" in _reference_text()


def test_a_service_is_keyed_and_announced_under_its_service_type() -> None:
    key = wire.topic_key(0, "/cdprd/enable", wire.TRIGGER)
    assert key == (
        "0/cdprd/enable/std_srvs::srv::dds_::Trigger_/"
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
    )
    node = wire.Node(0, ZID, 0, "/", "cdprd")
    token = node.entity_token(3, wire.SERVICE_SERVER, "/cdprd/enable", wire.TRIGGER)
    assert (
        token
        == f"@ros2_lv/0/{ZID}/0/3/SS/%/%/cdprd/%cdprd%enable/"
        + "/".join(key.split("/")[3:])
        + "/::,10:,:,:,,"
    )


def test_qos_strings_are_qos_to_keyexprs() -> None:
    """rmw_zenoh's compact QoS (liveliness_utils.cpp's qos_to_keyexpr: a field left empty
    where it equals rmw_zenoh's default, qos.cpp; durability TRANSIENT_LOCAL = 1 in
    rmw/types.h), against the design document's examples and the reference's values."""
    text = _reference_text()
    assert wire.qos_keyexpr(10) == wire.DEFAULT_QOS == "::,10:,:,:,,"  # the listener's
    assert wire.qos_keyexpr(7) == "::,7:,:,:,,"  # the talker's
    assert "/::,10:,:,:,,`" in text and "/::,7:,:,:,,`" in text
    assert wire.qos_keyexpr(42) == "::,:,:,:,,"  # rmw_zenoh's defaults: every field empty
    transient = wire.qos_keyexpr(1, transient_local=True)
    assert transient == ":1:,1:,:,:,,"
    assert f"`{transient}`" in text


def test_the_attachment_is_what_zenoh_ext_serializes_and_reads() -> None:
    gid = bytes(range(16))
    ours = wire.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(ours) == 33  # 8 + 8 + 1 + 16, as the design document lists
    assert ze.z_deserialize(tuple[ze.Int64, ze.Int64, bytes], zenoh.ZBytes(ours)) == (
        7,
        1_700_000_000_123_456_789,
        gid,
    )
    theirs = ze.z_serialize((ze.Int64(-3), ze.Int64(42), gid)).to_bytes()
    assert wire.read_attachment(theirs) == (-3, 42, gid)


@pytest.mark.parametrize(
    ("raw", "named"),
    [
        (None, "no attachment"),
        (b"\x01" * 20, "attachment of 20 bytes"),
        (struct.pack("<qqB16s", 1, 2, 15, bytes(16)), "gid length 15"),
    ],
)
def test_a_bad_attachment_is_named(raw: bytes | None, named: str) -> None:
    with pytest.raises(wire.WireError, match=named):
        wire.read_attachment(raw)


# -- trajectories in -------------------------------------------------------------------


def _msg(msgtype: str, **fields):
    return STORE.types[msgtype](**fields)


def _header(sec: int, nanosec: int = 0, frame: str = "world"):
    stamp = _msg("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
    return _msg("std_msgs/msg/Header", stamp=stamp, frame_id=frame)


def _pose(x: float, y: float, z: float, w: float = 1.0):
    return _msg(
        "geometry_msgs/msg/Pose",
        position=_msg("geometry_msgs/msg/Point", x=x, y=y, z=z),
        orientation=_msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=w),
    )


def path_cdr(points: list[tuple[float, tuple[float, float, float]]], frame: str = "world"):
    """A nav_msgs/msg/Path in CDR, made by rosbags: (time s, position) per pose."""
    poses = [
        _msg(
            "geometry_msgs/msg/PoseStamped",
            header=_header(1000 + int(t), round((t % 1) * 1e9), frame),
            pose=_pose(*p),
        )
        for t, p in points
    ]
    return bytes(STORE.serialize_cdr(_msg(PATH, header=_header(1000), poses=poses), PATH))


def _attachment(sequence: int = 5) -> bytes:
    return ze.z_serialize((ze.Int64(sequence), ze.Int64(time.time_ns()), bytes(16))).to_bytes()


def _read(payload: bytes, msgtype: str = PATH, extra: bytes | None = None):
    extra = _attachment() if extra is None else extra
    return read_trajectory(("/path", msgtype, payload, extra), SETTINGS, LIMITS)


def test_a_path_becomes_a_trajectory_timed_by_its_stamps() -> None:
    ident, parsed = _read(path_cdr([(0.0, (0, 0, 1.25)), (1.5, (0.1, 0, 1.3))]))
    assert ident == "/path#5"
    assert isinstance(parsed, TrajectoryRequest)
    assert parsed.start is None
    assert parsed.trajectory.duration == pytest.approx(1.5)
    end = parsed.trajectory.waypoints[-1].pose.position
    assert end.tolist() == pytest.approx([0.1, 0.0, 1.3])


def test_a_multi_dof_trajectory_becomes_a_trajectory() -> None:
    def point(t: float, x: float):
        transform = _msg(
            "geometry_msgs/msg/Transform",
            translation=_msg("geometry_msgs/msg/Vector3", x=x, y=0.0, z=1.25),
            rotation=_msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
        )
        return _msg(
            "trajectory_msgs/msg/MultiDOFJointTrajectoryPoint",
            transforms=[transform],
            velocities=[],
            accelerations=[],
            time_from_start=_msg("builtin_interfaces/msg/Duration", sec=int(t), nanosec=0),
        )

    points = [point(0, 0), point(2, 0.1)]
    msg = _msg(MULTI_DOF, header=_header(0), joint_names=["platform"], points=points)
    _, parsed = _read(bytes(STORE.serialize_cdr(msg, MULTI_DOF)), MULTI_DOF)
    assert isinstance(parsed, TrajectoryRequest)
    assert parsed.trajectory.duration == pytest.approx(2.0)


def _huge_pose_count() -> bytes:
    good = path_cdr(TWO)
    # header: stamp (8) + frame_id (uint32 length 6 + "world\0") = 18, aligned to 20
    count_at = 4 + 20
    assert struct.unpack_from("<I", good, count_at)[0] == 2
    return good[:count_at] + struct.pack("<I", 0xFFFFFFFF) + good[count_at + 4 :]


def _second(position: tuple[float, float, float]) -> list:
    return [TWO[0], (1.0, position)]


@pytest.mark.parametrize(
    ("payload", "extra", "code", "named"),
    [
        pytest.param(path_cdr(TWO)[:-9], None, "bad_request", "malformed CDR", id="truncated"),
        pytest.param(_huge_pose_count(), None, "bad_request", "malformed CDR", id="huge-sequence"),
        pytest.param(b"", None, "bad_request", "malformed CDR", id="empty"),
        pytest.param(b"\x00\x01\x00\x00", None, "bad_request", "malformed CDR", id="header-only"),
        pytest.param(
            path_cdr(TWO) + bytes(64), None, "bad_request", "malformed CDR", id="trailing-bytes"
        ),
        pytest.param(
            path_cdr(_second((math.nan, 0, 1.3))),
            None,
            "rejected",
            r"waypoints\[1\]\.position\[0\]: nan is not a finite number",
            id="nan",
        ),
        pytest.param(
            path_cdr(_second((0, 0, math.inf))),
            None,
            "rejected",
            r"waypoints\[1\]\.position\[2\]: inf is not a finite number",
            id="infinity",
        ),
        pytest.param(  # (every pose at one time is no trajectory but a path: its tests)
            path_cdr([*TWO, (0.5, (0, 0, 1.28))]),
            None,
            "rejected",
            "waypoint 2: times_increasing",
            id="times-not-increasing",
        ),
        pytest.param(
            path_cdr(TWO, frame="map"), None, "rejected", "frame 'map'", id="foreign-frame"
        ),
        pytest.param(path_cdr([]), None, "bad_request", "without poses", id="no-poses"),
        pytest.param(
            path_cdr(TWO), b"\x00" * 7, "bad_request", "attachment of 7 bytes", id="bad-attachment"
        ),
    ],
)
def test_hostile_trajectories_are_refused_with_a_named_reason(
    payload: bytes, extra: bytes | None, code: str, named: str
) -> None:
    _, parsed = _read(payload, extra=extra)
    assert isinstance(parsed, CommandError), parsed
    assert parsed.code == code
    assert re.search(named, str(parsed)), str(parsed)


def test_a_missing_attachment_is_refused() -> None:
    payload = path_cdr(TWO)
    ident, parsed = read_trajectory(("/path", PATH, payload, None), SETTINGS, LIMITS)
    assert ident is None
    assert isinstance(parsed, CommandError) and "no attachment" in str(parsed)


def test_more_poses_than_the_waypoint_limit_are_refused_before_parsing() -> None:
    payload = path_cdr([(float(k), (0, 0, 1.25)) for k in range(12)])
    limits = TrajectoryLimits(max_waypoints=10)
    _, parsed = read_trajectory(("/path", PATH, payload, _attachment()), SETTINGS, limits)
    assert isinstance(parsed, CommandError) and parsed.code == "rejected"
    assert "12 poses exceed the limit of 10" in str(parsed)


@pytest.mark.parametrize(
    ("section", "named"),
    [
        ({"namespace": "lab/"}, "ros2.namespace"),
        ({"domain_id": 300}, "ros2.domain_id"),
        ({"pose_topic": "a b"}, "ros2.pose_topic"),
        ({"enable": True}, "ros2.enable"),
    ],
)
def test_a_bad_ros2_section_names_the_key(section: dict, named: str) -> None:
    with pytest.raises(ConfigError, match=named):
        config_for("cia402", ros2=section)


def test_topics_resolve_against_the_namespace() -> None:
    settings = config_for("cia402", ros2={"enabled": True, "namespace": "/lab"}).ros2
    assert settings.topic("pose") == "/lab/pose"
    assert settings.topic("/tf") == "/tf"
    assert Ros2Settings().topic("pose") == "/pose"


# -- state out ---------------------------------------------------------------------------

HELD = {
    "state": "hold",
    "fault": None,
    "lengths": [1.5] * 8,
    "rates": [0.01] * 8,
    "forces": [-40.0] * 8,
    "pose": {
        "position": [0.1, 0.0, 1.25],
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
    },
    "tracking_error": [0.002, -0.001, 0.0, 0.0, 0.0, 0.01],
    "cycle": {"cycles": 1234, "misses": 0},
}


def _out(state: dict) -> dict:
    """state_messages through CDR and back, decoded by rosbags."""
    messages = state_messages(state, SETTINGS, 1_700_000_000_250_000_000)
    return {
        name: STORE.deserialize_cdr(wire.serialize(m), m.__msgtype__)
        for name, m in messages.items()
    }


def _as_pose(ros) -> Pose:
    p, q = ros.position, ros.orientation
    return Pose((p.x, p.y, p.z), (q.w, q.x, q.y, q.z))


def test_the_reference_pose_is_the_measured_pose_less_the_tracking_error() -> None:
    out = _out(HELD)
    measured = _as_pose(out["pose_topic"].pose)
    reference = _as_pose(out["reference_pose_topic"].pose)
    assert measured.position.tolist() == pytest.approx(HELD["pose"]["position"])
    assert liediff(reference, measured) == pytest.approx(HELD["tracking_error"], abs=1e-12)
    stamp = out["pose_topic"].header.stamp
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 250_000_000)
    tf = out["tf_topic"].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in tf] == [
        ("world", "platform"),
        ("world", "platform_reference"),
    ]
    assert tf[1].transform.translation.x == pytest.approx(reference.position[0])
    joints = out["joint_states_topic"]
    assert joints.position.tolist() == HELD["lengths"]
    assert joints.effort.tolist() == HELD["forces"]
    (status,) = out["diagnostics_topic"].status
    assert status.level == 0 and status.message == "hold"


def test_a_braked_robot_is_an_error_with_its_fault_and_sends_no_pose() -> None:
    braked = {
        "state": "braked",
        "fault": {"trigger": "stale_feedback", "message": "drive 3 silent"},
        "lengths": [1.5] * 8,
        "rates": [0.0] * 8,
    }
    out = _out(braked)
    assert set(out) == {"joint_states_topic", "diagnostics_topic"}
    assert out["joint_states_topic"].effort.tolist() == []
    (status,) = out["diagnostics_topic"].status
    assert status.level == 2
    assert status.message == "braked: stale_feedback: drive 3 silent"
    assert {v.key: v.value for v in status.values}["fault_trigger"] == "stale_feedback"
