"""The robot for RViz over rmw_zenoh's wire format, seen by a subscriber written here from
rmw_zenoh's sources (tests/data/rmw_zenoh_reference.md), not from the project's encoder:
keys and liveliness tokens spelled out, the 33-byte attachment unpacked with struct, CDR
decoded by rosbags.

A transient-local publisher is what rmw_zenoh_cpp declares (an AdvancedPublisher with a
cache of its depth): a subscription that joins after the sample was published, declared
as rmw_zenoh declares a transient-local one (an AdvancedSubscriber whose history detects
late publishers), still gets the last sample, and the liveliness token carries the
transient-local QoS.

Against the bridge on the zenoh interface's stand-in handler (test_zenoh_io.Running) with
a robot file: a late RViz gets robot_description (a URDF whose links and joints are the
robot file's anchors, attachment points, body and mass, read here with xml.etree and with
urdf_parser_py) and /tf_static (the same frames); the cable markers run from the anchors
to the attachment points at the state's pose, coloured in the order of their tensions,
and are deleted when the pose goes away.  The RViz config shipped names those topics.
"""

from __future__ import annotations

import itertools
import math
import re
import struct
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
import zenoh.ext as ze
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from urdf_parser_py.urdf import URDF

from cdpr import Pose, Robot
from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings, build_zenoh_config, client_zenoh_config
from daemon.interface import ros2_wire as wire
from daemon.interface.ros2_bridge import _Publisher
from daemon.interface.urdf import robot_urdf
from tests.daemon.test_zenoh_io import WAIT, Running, StandIn
from tests.loopback import free_port

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = {  # a body box, none, shared attachment points with pulleys
    "reference8-offset": ROOT / "tests" / "data" / "robots" / "reference8-offset.yaml",
    "reference8": ROOT / "config" / "robots" / "reference8.yaml",
    "suspended6": ROOT / "config" / "robots" / "suspended6.yaml",
}
RVIZ = ROOT / "config" / "ros2" / "cdprd.rviz"
JAZZY = get_typestore(Stores.ROS2_JAZZY)
STRING = "std_msgs/msg/String"
TF = "tf2_msgs/msg/TFMessage"
MARKERS = "visualization_msgs/msg/MarkerArray"
# Jazzy's RIHS01 hash of visualization_msgs/msg/MarkerArray, as rosidl_generator_c writes
# it into a generated marker_array__struct.h (tests/data/rmw_zenoh_reference.md)
MARKERS_HASH = "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf"
TF_KEY = (
    "tf2_msgs::msg::dds_::TFMessage_/"
    "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
)
MARKERS_KEY = f"visualization_msgs::msg::dds_::MarkerArray_/{MARKERS_HASH}"
VOLATILE_QOS = "::,10:,:,:,,"
LINE_LIST, ADD, DELETEALL = 5, 0, 3  # Marker.msg's constants
# visualization_msgs/msg/Marker.msg (ros2/common_interfaces @ 9da4a19, comments left out)
MARKER_MSG = """
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ARROW_STRIP=12
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
UVCoordinate[] uv_coordinates
string text
string mesh_resource
MeshFile mesh_file
bool mesh_use_embedded_materials
"""


def _store() -> Any:
    """visualization_msgs' Marker, MarkerArray and the two types they add from their .msg
    text; the builtin, std, geometry and sensor messages from rosbags' Jazzy store."""
    store = get_typestore(Stores.EMPTY)
    nested = ("builtin_interfaces", "std_msgs", "geometry_msgs", "sensor_msgs")
    store.register({n: d for n, d in JAZZY.fielddefs.items() if n.split("/")[0] in nested})
    types: dict[str, Any] = {}
    for name, text in (
        ("visualization_msgs/msg/UVCoordinate", "float32 u\nfloat32 v"),
        ("visualization_msgs/msg/MeshFile", "string filename\nuint8[] data"),
        ("visualization_msgs/msg/Marker", MARKER_MSG),
        (MARKERS, "Marker[] markers"),
    ):
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


STORE = _store()
STRING_KEY = (  # <type name>/<type hash> of std_msgs/msg/String (design.md's example)
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
LATCHED_QOS = ":1:,1:,:,:,,"  # reliable, TRANSIENT_LOCAL (1), keep last 1 (the reference)


class LateSubscription:
    """A transient-local subscription as rmw_zenoh_cpp declares one
    (rmw_subscription_data.cpp): an AdvancedSubscriber with subscriber detection, a
    history of `depth` samples that detects late publishers, and heartbeat recovery;
    each sample kept as (payload bytes, attachment fields)."""

    def __init__(self, session: zenoh.Session, key: str, depth: int) -> None:
        self.samples: list[tuple[bytes, tuple[int, int, int, bytes]]] = []
        self.lock = threading.Lock()
        self.subscriber = ze.declare_advanced_subscriber(
            session,
            key,
            self._on_sample,
            history=ze.HistoryConfig(detect_late_publishers=True, max_samples=depth),
            recovery=ze.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        extra = sample.attachment
        assert extra is not None, "rmw_zenoh drops a sample without an attachment"
        fields = struct.unpack("<qqB16s", extra.to_bytes())  # seq, stamp, 16, gid
        with self.lock:
            self.samples.append((sample.payload.to_bytes(), fields))

    def wait(self, count: int = 1) -> list[tuple[bytes, tuple[int, int, int, bytes]]]:
        wait_until(lambda: len(self.samples) >= count, f"{count} samples")
        with self.lock:
            return list(self.samples)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def listening_session() -> tuple[zenoh.Session, str]:
    """A peer session listening on a free loopback port (multicast and gossip off)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return zenoh.open(build_zenoh_config(ZenohSettings(listen=[endpoint]), "cdpr/test")), endpoint


def test_a_transient_local_publisher_serves_a_subscription_that_joins_later() -> None:
    server, endpoint = listening_session()
    late = None
    try:
        zid = str(server.info.zid())
        node = wire.Node(0, zid, 0, "/", "cdprd")
        publisher = _Publisher(server, node, 4, "/latched", STRING, depth=1, transient_local=True)
        assert publisher.token == (
            f"@ros2_lv/0/{zid}/0/4/MP/%/%/cdprd/%latched/{STRING_KEY}/{LATCHED_QOS}"
        )
        for text in ("first", "second"):
            publisher.put(JAZZY.types[STRING](data=text))
        late = zenoh.open(client_zenoh_config([endpoint]))
        subscription = LateSubscription(late, f"0/latched/{STRING_KEY}", depth=1)
        ((payload, (sequence, stamp, size, gid)),) = subscription.wait()
        assert JAZZY.deserialize_cdr(payload, STRING).data == "second"  # the cache's depth: 1
        assert (sequence, size, gid) == (2, 16, wire.gid(publisher.token))
        assert 0 < time.time_ns() - stamp < WAIT * 1e9
        publisher.put(JAZZY.types[STRING](data="third"))  # then live, as any subscriber
        assert JAZZY.deserialize_cdr(subscription.wait(2)[1][0], STRING).data == "third"
        publisher.publisher.undeclare()
    finally:
        if late is not None:
            late.close()
        server.close()


# -- the URDF --------------------------------------------------------------------------


def _robot_file(name: str) -> dict[str, Any]:
    return yaml.safe_load(ROBOTS[name].read_text())


def _numbers(text: str | None) -> list[float]:
    assert text is not None
    return [float(v) for v in text.split()]


def check_urdf(text: str, name: str, settings: Ros2Settings) -> None:
    """The URDF against robot file `name` read here with yaml: a world root, an anchor
    link fixed in it at each anchor, a floating platform with the file's mass and
    inertia and the box round its body (or its attachment points), an attachment link
    fixed in it at each attachment point; and urdf_parser_py reads the same tree."""
    data = _robot_file(name)
    cables, platform = data["cables"], data["platform"]
    root = ET.fromstring(text)
    assert root.tag == "robot" and root.get("name") == data["name"]
    n = len(cables)
    anchors = [f"anchor{k}" for k in range(n)]
    attachments = [f"attachment{k}" for k in range(n)]
    links = [link.get("name") for link in root.findall("link")]
    assert sorted(links) == sorted(["world", "platform", *anchors, *attachments])
    joints = {j.find("child").get("link"): j for j in root.findall("joint")}  # type: ignore[union-attr]
    floating = joints["platform"]
    assert floating.get("type") == "floating"
    assert floating.find("parent").get("link") == "world"  # type: ignore[union-attr]
    for k, cable in enumerate(cables):
        for child, parent, xyz in (
            (anchors[k], "world", cable["anchor"]),
            (attachments[k], "platform", cable["attachment"]),
        ):
            joint = joints[child]
            assert joint.get("type") == "fixed"
            assert joint.find("parent").get("link") == parent  # type: ignore[union-attr]
            origin = joint.find("origin")
            assert origin is not None
            assert _numbers(origin.get("xyz")) == pytest.approx(xyz, abs=1e-12)
    body = root.find("link[@name='platform']")
    assert body is not None
    box = body.find("visual/geometry/box")
    centre = body.find("visual/origin")
    assert box is not None and centre is not None
    points = np.array([c["attachment"] for c in cables], dtype=float)
    if "body" in platform:
        corners = platform["body"]["box"]
        points = np.vstack([points, corners["min"], corners["max"]])
    lo, hi = points.min(axis=0), points.max(axis=0)
    assert _numbers(box.get("size")) == pytest.approx(np.maximum(hi - lo, 0.02))
    assert _numbers(centre.get("xyz")) == pytest.approx((lo + hi) / 2)
    mass = body.find("inertial/mass")
    inertia = body.find("inertial/inertia")
    assert mass is not None and inertia is not None
    assert float(mass.get("value", "nan")) == platform["mass"]
    (ixx, ixy, ixz), (_, iyy, iyz), (_, _, izz) = platform["inertia"]
    assert {k: float(v) for k, v in inertia.attrib.items()} == pytest.approx(
        {"ixx": ixx, "ixy": ixy, "ixz": ixz, "iyy": iyy, "iyz": iyz, "izz": izz}
    )
    parsed = URDF.from_xml_string(text.encode())  # an independent reader (ROS's own)
    assert parsed.get_root() == "world" and parsed.name == data["name"]
    by_child = {j.child: j for j in parsed.joints}
    assert by_child["platform"].type == "floating"
    for k, cable in enumerate(cables):
        assert by_child[anchors[k]].origin.xyz == pytest.approx(cable["anchor"])
        assert by_child[attachments[k]].origin.xyz == pytest.approx(cable["attachment"])
    assert parsed.link_map["platform"].inertial.mass == platform["mass"]


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_the_urdf_is_the_robot_files(name: str) -> None:
    settings = Ros2Settings()
    check_urdf(robot_urdf(Robot.from_yaml(ROBOTS[name]), settings), name, settings)


def test_the_marker_array_hash_is_jazzys() -> None:
    """MarkerArray from the .msg text hashes to the value in public generated code, and
    the bridge keys its markers under the same."""
    assert STORE.hash_rihs01(MARKERS) == MARKERS_HASH
    assert wire.type_hash(MARKERS) == MARKERS_HASH
    assert wire.topic_key(0, "/cables", MARKERS) == f"0/cables/{MARKERS_KEY}"


# -- the bridge, seen from a late RViz -------------------------------------------------

ROS2 = Ros2Settings(enabled=True, rate_hz=20.0)  # domain 0, namespace /
TILTED = Pose((0.1, -0.05, 1.3), (math.cos(0.1), 0.0, math.sin(0.1), 0.0))  # 0.2 rad about y


def rotate(q: tuple[float, float, float, float], v: list[float]) -> np.ndarray:
    """v rotated by unit quaternion q = (w, x, y, z): v + 2 w (u x v) + 2 u x (u x v)."""
    w, u = q[0], np.array(q[1:])
    v = np.asarray(v, dtype=float)
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


class Inbox:
    """A plain subscriber (volatile, as RViz's marker display): the samples decoded."""

    def __init__(self, session: zenoh.Session, key: str, msgtype: str) -> None:
        self.items: list[Any] = []
        self.lock = threading.Lock()
        self.msgtype = msgtype
        self.subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        assert sample.attachment is not None and len(sample.attachment.to_bytes()) == 33
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)
        with self.lock:
            self.items.append(msg)

    def next(self, condition: Callable[[Any], bool], what: str) -> Any:
        """The first message to arrive from now on that meets `condition`."""
        with self.lock:
            self.items.clear()
        found: list[Any] = []

        def arrived() -> bool:
            with self.lock:
                found.extend(m for m in self.items if condition(m))
                self.items.clear()
            return bool(found)

        wait_until(arrived, what)
        return found[0]


def test_a_late_rviz_gets_the_robot_description_and_the_static_frames() -> None:
    name = "reference8-offset"
    served = Running(StandIn(), ros2=ROS2, robot=Robot.from_yaml(ROBOTS[name]))
    try:
        with served.session() as session:  # joins after the bridge published both
            description = LateSubscription(session, f"0/robot_description/{STRING_KEY}", 1)
            frames = LateSubscription(session, f"0/tf_static/{TF_KEY}", 100)
            ((payload, (sequence, _, _, gid)),) = description.wait()
            assert sequence == 1
            check_urdf(STORE.deserialize_cdr(payload, STRING).data, name, ROS2)
            ((payload, _),) = frames.wait()
            msg = JAZZY.deserialize_cdr(payload, TF)
            cables = _robot_file(name)["cables"]
            got = {
                (t.header.frame_id, t.child_frame_id): (
                    [
                        t.transform.translation.x,
                        t.transform.translation.y,
                        t.transform.translation.z,
                    ],
                    [
                        t.transform.rotation.w,
                        t.transform.rotation.x,
                        t.transform.rotation.y,
                        t.transform.rotation.z,
                    ],
                )
                for t in msg.transforms
            }
            want = {("world", f"anchor{k}"): c["anchor"] for k, c in enumerate(cables)}
            want |= {("platform", f"attachment{k}"): c["attachment"] for k, c in enumerate(cables)}
            assert got.keys() == want.keys()
            for frames_pair, xyz in want.items():
                assert got[frames_pair][0] == pytest.approx(xyz)
                assert got[frames_pair][1] == [1.0, 0.0, 0.0, 0.0]
            tokens = [
                str(reply.ok.key_expr)
                for reply in session.liveliness().get("@ros2_lv/0/**", timeout=WAIT)
                if reply.ok is not None
            ]
    finally:
        served.stop()
    head = r"@ros2_lv/0/[0-9a-f]+/0/\d+/MP/%/%/cdprd/"
    for topic, typed, qos in (
        ("robot_description", STRING_KEY, LATCHED_QOS),
        ("tf_static", TF_KEY, LATCHED_QOS),
        ("cables", MARKERS_KEY, VOLATILE_QOS),
    ):
        pattern = re.escape(f"%{topic}/{typed}/{qos}")
        matching = [t for t in tokens if re.fullmatch(head + pattern, t)]
        assert len(matching) == 1, (topic, tokens)
        if topic == "robot_description":
            assert wire.gid(matching[0]) == gid  # the token the samples' GID hashes


def test_the_cables_are_lines_from_the_anchors_at_the_pose_coloured_by_tension() -> None:
    name = "reference8"
    robot_file = _robot_file(name)
    t_min, force_max = robot_file["actuator"]["t_min"], robot_file["actuator"]["force_max"]
    handler = StandIn()
    handler.pose = TILTED
    tensions = [400.0, 50.0, 10.0, 300.0, 120.0, 590.0, 30.0, 200.0]  # cable 2 below t_min
    handler.tensions = tensions
    served = Running(handler, ros2=ROS2, robot=Robot.from_yaml(ROBOTS[name]))
    try:
        with served.session() as session:
            inbox = Inbox(session, f"0/cables/{MARKERS_KEY}", MARKERS)
            msg = inbox.next(lambda m: len(m.markers) == 8, "the cables")
            q = TILTED.quaternion_tuple
            for k, (marker, cable) in enumerate(
                zip(msg.markers, robot_file["cables"], strict=True)
            ):
                assert (marker.ns, marker.id, marker.type, marker.action) == (
                    "cables",
                    k,
                    LINE_LIST,
                    ADD,
                )
                assert marker.header.frame_id == "world"
                ends = [[p.x, p.y, p.z] for p in marker.points]
                attachment = np.array(TILTED.position_tuple) + rotate(q, cable["attachment"])
                assert ends[0] == pytest.approx(cable["anchor"], abs=1e-9)
                assert ends[1] == pytest.approx(attachment.tolist(), abs=1e-9)
                assert marker.lifetime.sec + marker.lifetime.nanosec > 0
            colors = [(m.color.r, m.color.g, m.color.b) for m in msg.markers]
            slack = [k for k, t in enumerate(tensions) if t < t_min]
            assert slack == [2]
            r, g, b = colors[2]
            assert r == g == b and msg.markers[2].scale.x < msg.markers[0].scale.x  # grey, thin
            taut = sorted((t, k) for k, t in enumerate(tensions) if t >= t_min)
            warmth = [colors[k][0] - colors[k][2] for _, k in taut]  # red less blue
            assert all(a < z for a, z in itertools.pairwise(warmth))
            assert max(tensions) < force_max
            handler.pose = None  # idle or braked: no pose in the state
            gone = inbox.next(lambda m: len(m.markers) == 1, "the deletion")
            (deletion,) = gone.markers
            assert (deletion.ns, deletion.action) == ("cables", DELETEALL)
    finally:
        served.stop()


def test_the_rviz_config_shows_the_bridges_topics() -> None:
    """config/ros2/cdprd.rviz: RViz2's YAML with the world as fixed frame and a display
    for each of the ros2: section's default topics, the robot description transient local."""
    settings = Ros2Settings()
    config = yaml.safe_load(RVIZ.read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == settings.world_frame
    displays: dict[str, list[dict[str, Any]]] = {}
    for display in manager["Displays"]:
        displays.setdefault(display["Class"].removeprefix("rviz_default_plugins/"), []).append(
            display
        )
    (model,) = displays["RobotModel"]
    assert model["Description Source"] == "Topic"
    topic = model["Description Topic"]
    assert topic["Value"] == settings.topic(settings.robot_description_topic)
    assert (topic["Durability Policy"], topic["Depth"]) == ("Transient Local", 1)
    assert "TF" in displays
    (markers,) = displays["MarkerArray"]
    assert markers["Topic"]["Value"] == settings.topic(settings.cables_topic)
    poses = {d["Topic"]["Value"] for d in displays["Pose"]}
    assert poses == {
        settings.topic(settings.pose_topic),
        settings.topic(settings.reference_pose_topic),
    }


@pytest.mark.parametrize(("rate_hz", "least", "most"), [(20.0, 20, 20), (1000.0, 30, 34)])
def test_the_cables_go_out_at_the_state_rate_but_at_most_30_hz(
    rate_hz: float, least: int, most: int
) -> None:
    """At the loop's rate (1 kHz) the markers would take most of a core: one second of
    snapshots at `rate_hz`, with the loop's jitter, publishes them every snapshot below
    30 Hz and about 30 times above (a snapshot 10 % early still counts: at most 33)."""
    from daemon.interface.ros2_model import RobotModel

    robot = Robot.from_yaml(ROBOTS["reference8"])
    model = RobotModel(robot, Ros2Settings(rate_hz=rate_hz))
    jitter = np.random.default_rng(1).uniform(-0.05, 0.05, int(rate_hz))
    times = [round((k + j) * 1e9 / rate_hz) for k, j in enumerate(jitter)]
    assert least <= sum(model.cables_due(ns) for ns in times) <= most
