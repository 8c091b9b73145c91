"""`cdprd run --sim` with `ros2:` enabled, seen from this process as a ROS 2 node on
rmw_zenoh would see it, using only the plain zenoh API, rosbags (CDR, RIHS01 hashes),
zenoh-ext (attachments) and xxhash, with the key and token formats written out here from
rmw_zenoh's design document (tests/data/rmw_zenoh_reference.md):

- PoseStamped and JointState arrive on <domain>/<topic>/<DDS type>/<rosbags' RIHS01 hash>,
  decode with rosbags, equal the state published over the daemon's own zenoh interface,
  and carry rmw_zenoh's attachment (sequence numbers counting up, a recent timestamp, the
  GID = XXH3-128 of the publisher's liveliness key);
- the node's and its entities' liveliness tokens are queryable and parse per the format;
- a Path published with an rmw_zenoh attachment is flown by the simulated robot, a
  MultiDOFJointTrajectory brings it back, and hostile payloads are refused with the
  reason on the status topic while the robot holds.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import xxhash
import yaml
import zenoh
import zenoh.ext as ze
from rosbags.typesys import Stores, get_typestore

from daemon.config.zenoh_config import client_zenoh_config
from tests.loopback import free_port, zenoh_peer
from tests.processes import CONFIG, ROOT, finish, start_daemon

PREFIX = "cdpr/reference8"
STORE = get_typestore(Stores.ROS2_JAZZY)
DOMAIN = 7
NAMESPACE = "/lab"
QOS = "::,10:,:,:,,"  # reliable, volatile, keep last 10 in rmw_zenoh's compact form
PATH = "nav_msgs/msg/Path"
MULTI_DOF = "trajectory_msgs/msg/MultiDOFJointTrajectory"
POSE = "geometry_msgs/msg/PoseStamped"
JOINTS = "sensor_msgs/msg/JointState"
STATUS = "std_msgs/msg/String"

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


def dds(msgtype: str) -> str:
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def key(topic: str, msgtype: str, domain: int = DOMAIN) -> str:
    """<domain_id>/<fully_qualified_name>/<type_name>/<type_hash> (design.md)."""
    return f"{domain}/{topic.strip('/')}/{dds(msgtype)}/{STORE.hash_rihs01(msgtype)}"


class Inbox:
    """The samples received on one key: (decoded message, attachment bytes)."""

    def __init__(self, s: zenoh.Session, topic: str, msgtype: str, domain: int = DOMAIN) -> None:
        self.msgtype = msgtype
        self.items: list[tuple[object, bytes | None]] = []
        self.lock = threading.Lock()
        self.sub = s.declare_subscriber(key(topic, msgtype, domain), self.on_sample)

    def on_sample(self, sample: zenoh.Sample) -> None:
        msg = STORE.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)
        extra = None if sample.attachment is None else sample.attachment.to_bytes()
        with self.lock:
            self.items.append((msg, extra))

    def last(self):
        with self.lock:
            return self.items[-1] if self.items else (None, None)

    def count(self) -> int:
        with self.lock:
            return len(self.items)


def wait(condition, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)


def get_json(s: zenoh.Session, key_expr: str) -> dict:
    for reply in s.get(key_expr, timeout=10.0):
        return json.loads((reply.ok or reply.err).payload.to_bytes())
    raise AssertionError(f"no reply on {key_expr}")


def msg(msgtype: str, **fields):
    return STORE.types[msgtype](**fields)


def time_msg(seconds: float):
    return msg("builtin_interfaces/msg/Time", sec=int(seconds), nanosec=round(seconds % 1 * 1e9))


def quaternion(q: dict):
    return msg("geometry_msgs/msg/Quaternion", x=q["x"], y=q["y"], z=q["z"], w=q["w"])


def path(points: list[tuple[float, list[float]]], q: dict) -> bytes:
    poses = [
        msg(
            "geometry_msgs/msg/PoseStamped",
            header=msg("std_msgs/msg/Header", stamp=time_msg(100 + t), frame_id="world"),
            pose=msg(
                "geometry_msgs/msg/Pose",
                position=msg("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                orientation=quaternion(q),
            ),
        )
        for t, p in points
    ]
    header = msg("std_msgs/msg/Header", stamp=time_msg(100), frame_id="world")
    return bytes(STORE.serialize_cdr(msg(PATH, header=header, poses=poses), PATH))


def multi_dof(points: list[tuple[float, list[float]]], q: dict) -> bytes:
    out = [
        msg(
            "trajectory_msgs/msg/MultiDOFJointTrajectoryPoint",
            transforms=[
                msg(
                    "geometry_msgs/msg/Transform",
                    translation=msg("geometry_msgs/msg/Vector3", x=p[0], y=p[1], z=p[2]),
                    rotation=quaternion(q),
                )
            ],
            velocities=[],
            accelerations=[],
            time_from_start=msg("builtin_interfaces/msg/Duration", sec=int(t), nanosec=0),
        )
        for t, p in points
    ]
    header = msg("std_msgs/msg/Header", stamp=time_msg(0), frame_id="")
    body = msg(MULTI_DOF, header=header, joint_names=["platform"], points=out)
    return bytes(STORE.serialize_cdr(body, MULTI_DOF))


def test_a_ros2_node_on_rmw_zenoh_sees_the_daemon_and_flies_it(tmp_path: Path) -> None:
    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["ros2"] = {"enabled": True, "domain_id": DOMAIN, "namespace": NAMESPACE, "rate_hz": 20}
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    proc = start_daemon(config, "--sim")
    try:
        wait(lambda: _listening(port), 60.0, "the daemon to listen")  # a loaded host: slow
        s = zenoh_peer(port)
        try:
            _exercise(s)
        finally:
            s.close()
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out


def _exercise(s: zenoh.Session) -> None:
    states: list[dict] = []
    s.declare_subscriber(
        f"{PREFIX}/state", lambda x: states.append(json.loads(x.payload.to_bytes()))
    )
    poses = Inbox(s, f"{NAMESPACE}/pose", POSE)
    joints = Inbox(s, f"{NAMESPACE}/joint_states", JOINTS)
    status = Inbox(s, f"{NAMESPACE}/trajectory_status", STATUS)
    wait(lambda: states and states[-1]["state"] == "idle", 30.0, "idle")
    wait(lambda: joints.count() > 2, 10.0, "JointState")

    # -- liveliness: the node and its entities, per the reference format
    replies = s.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=5.0)
    tokens = [str(r.ok.key_expr) for r in replies]
    parts = [t.split("/") for t in tokens]
    nodes = [p for p in parts if p[5] == "NN"]
    assert len(nodes) == 1, tokens
    admin, domain, zid, nid, eid, _, enclave, ns, name = nodes[0]
    assert (admin, domain, nid, eid) == ("@ros2_lv", str(DOMAIN), "0", "0")
    assert (enclave, ns, name) == ("%", "%lab", "cdprd")
    entities = {(p[5], p[9]): p for p in parts if p[5] != "NN"}
    pose_token = entities[("MP", "%lab%pose")]
    assert pose_token[:4] == ["@ros2_lv", "7", zid, "0"]
    assert pose_token[10:] == [dds(POSE), STORE.hash_rihs01(POSE), QOS]
    for kind, topic, msgtype in [
        ("MP", "%lab%joint_states", JOINTS),
        ("MP", "%tf", "tf2_msgs/msg/TFMessage"),
        ("MP", "%diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
        ("MP", "%lab%trajectory_status", STATUS),
        ("MS", "%lab%path", PATH),
        ("MS", "%lab%multi_dof_trajectory", MULTI_DOF),
    ]:
        assert entities[(kind, topic)][10:12] == [dds(msgtype), STORE.hash_rihs01(msgtype)]
    for service in ("enable", "hold", "brake", "reset", "disable"):  # test_ros2_services.py
        assert entities[("SS", f"%lab%{service}")][10] == "std_srvs::srv::dds_::Trigger_"
    for service in ("hold_observer", "freeze_payload"):
        assert entities[("SS", f"%lab%{service}")][10] == "std_srvs::srv::dds_::SetBool_"
    for topic, msgtype, qos in [  # the robot for RViz (test_ros2_model.py)
        ("%lab%robot_description", STATUS, ":1:,1:,:,:,,"),  # transient local, keep last 1
        ("%tf_static", "tf2_msgs/msg/TFMessage", ":1:,1:,:,:,,"),
        ("%lab%cables", "visualization_msgs/msg/MarkerArray", QOS),
    ]:
        assert entities[("MP", topic)][10:] == [dds(msgtype), STORE.hash_rihs01(msgtype), qos]
    for part in ("send_goal", "cancel_goal", "get_result"):  # the action (test_ros2_action.py)
        assert ("SS", f"%lab%fly_path%_action%{part}") in entities
    goals = entities[("MP", "%lab%fly_path%_action%status")]
    assert goals[10:] == ["action_msgs::msg::dds_::GoalStatusArray_", goals[11], ":1:,1:,:,:,,"]
    assert ("MP", "%lab%fly_path%_action%feedback") in entities
    ids = [int(p[4]) for p in parts if p[5] != "NN"]
    assert len(set(ids)) == len(ids) == 23  # 6 + 3 publishers, 2 subscriptions, 12 services

    # -- JointState: the lengths of the JSON state, rmw_zenoh's attachment
    joint_msg, extra = joints.last()
    assert list(joint_msg.name) == [f"cable{k}" for k in range(8)]
    assert np.allclose(joint_msg.position, states[-1]["lengths"], atol=1e-3)
    sequence, stamp, gid = ze.z_deserialize(tuple[ze.Int64, ze.Int64, bytes], zenoh.ZBytes(extra))
    assert sequence >= 3 and abs(stamp - time.time_ns()) < 60e9  # UNIX epoch ns
    joints_token = "/".join(entities[("MP", "%lab%joint_states")])
    assert gid == xxhash.xxh3_128_intdigest(joints_token.encode()).to_bytes(16, "little")

    # -- hold: the pose appears and equals the JSON state's
    assert get_json(s, f"{PREFIX}/cmd/enable")["ok"] is True
    wait(lambda: states[-1]["state"] == "hold", 10.0, "hold")
    wait(lambda: poses.count() > 2, 10.0, "PoseStamped")
    pose_msg, extra = poses.last()
    assert pose_msg.header.frame_id == "world"
    p = pose_msg.pose.position
    assert [p.x, p.y, p.z] == pytest.approx(states[-1]["pose"]["position"], abs=2e-3)
    first = ze.z_deserialize(tuple[ze.Int64, ze.Int64, bytes], zenoh.ZBytes(extra))[0]
    wait(lambda: poses.count() > 4, 5.0, "more poses")
    later = ze.z_deserialize(tuple[ze.Int64, ze.Int64, bytes], zenoh.ZBytes(poses.last()[1]))[0]
    assert later > first

    # -- a Path flown, a MultiDOFJointTrajectory back; hostile ones refused
    start = states[-1]["pose"]
    q = start["quaternion"]
    home = list(start["position"])
    target = [home[0] + 0.1, home[1], home[2]]
    path_key = key(f"{NAMESPACE}/path", PATH)
    gid_out = bytes(range(16))

    def put(key_expr: str, payload: bytes, sequence: int | None) -> None:
        extra = None
        if sequence is not None:
            extra = ze.z_serialize((ze.Int64(sequence), ze.Int64(time.time_ns()), gid_out))
        s.put(key_expr, payload, attachment=extra)

    def verdict(count: int) -> dict:
        wait(lambda: status.count() >= count, 20.0, f"verdict {count}")
        with status.lock:
            return json.loads(status.items[count - 1][0].data)

    put(path_key, path([(0.0, home), (1.5, target)], q), 1)
    accepted = verdict(1)
    assert accepted["event"] == "trajectory_accepted", accepted
    assert accepted["id"] == f"{NAMESPACE}/path#1"
    wait(lambda: states[-1]["state"] == "tracking", 5.0, "tracking")
    wait(lambda: states[-1]["state"] == "hold", 15.0, "the path's end")
    assert states[-1]["pose"]["position"] == pytest.approx(target, abs=2e-3)

    good = path([(0.0, target), (1.0, home)], q)
    hostile = [
        (good[:-10], 2, "malformed CDR"),
        (good, None, "no attachment"),
        (path([(0.0, target), (1.0, [float("nan"), 0.0, 1.3])], q), 3, "nan is not a finite"),
        (path([(0.0, target), (1.0, [5.0, 0.0, 1.3])], q), 4, "waypoint 1"),
    ]
    for k, (payload, sequence, _) in enumerate(hostile):
        put(path_key, payload, sequence)
        verdict(2 + k)  # one at a time: the next waits for this one's verdict
    for k, (_, _, reason) in enumerate(hostile):
        refused = verdict(2 + k)
        assert refused["event"] == "trajectory_rejected", refused
        assert reason in refused["error"]["reason"], refused
    time.sleep(0.3)
    assert states[-1]["state"] == "hold" and states[-1]["fault"] is None
    assert states[-1]["pose"]["position"] == pytest.approx(target, abs=2e-3)

    back_key = key(f"{NAMESPACE}/multi_dof_trajectory", MULTI_DOF)
    put(back_key, multi_dof([(0, target), (2, home)], q), 1)
    back = verdict(2 + len(hostile))
    assert back["event"] == "trajectory_accepted", back
    wait(lambda: states[-1]["state"] == "tracking", 5.0, "tracking back")
    wait(lambda: states[-1]["state"] == "hold", 15.0, "home again")
    assert states[-1]["pose"]["position"] == pytest.approx(home, abs=2e-3)


FORGED = b"forged"


@pytest.mark.timeout(150)
def test_under_the_templates_zenoh_section_the_ros2_keys_are_guarded(tmp_path: Path) -> None:
    """`cdprd run --sim` with config/hardware-template.yaml's zenoh section (access
    control, trajectory at 20 Hz) and ROS 2 on, two local zenoh clients of the daemon
    (the daemon routes between them): the one's puts on the node's pose, diagnostics and
    trajectory_status topics and its token of a second node `cdprd` reach not the other;
    a burst of ten Paths gets at most two verdicts (the 20 Hz limit); a 4 MB Path is
    refused by its size."""
    port = free_port()
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"] = yaml.safe_load((ROOT / "config" / "hardware-template.yaml").read_text())[
        "zenoh"
    ]
    endpoint = f"tcp/127.0.0.1:{port}"
    data["zenoh"]["listen"] = [endpoint]
    data["ros2"] = {"enabled": True, "domain_id": DOMAIN, "namespace": NAMESPACE, "rate_hz": 20}
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    outputs = {
        key(f"{NAMESPACE}/pose", POSE),
        key("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
        key(f"{NAMESPACE}/trajectory_status", STATUS),
    }
    proc = start_daemon(config, "--sim")
    try:
        wait(lambda: _listening(port), 60.0, "the daemon to listen")
        listener = zenoh.open(client_zenoh_config([endpoint]))  # routed by the daemon
        seen: list[tuple[str, bytes]] = []
        kept = [
            listener.declare_subscriber(
                f"{DOMAIN}/**", lambda s: seen.append((str(s.key_expr), s.payload.to_bytes()))
            ),
        ]
        status = Inbox(listener, f"{NAMESPACE}/trajectory_status", STATUS)
        joints = key(f"{NAMESPACE}/joint_states", JOINTS)
        wait(lambda: sum(k == joints for k, _ in seen) > 2, 60.0, "the daemon's joints")
        forger = zenoh.open(client_zenoh_config([endpoint]))
        try:
            forged_node = f"@ros2_lv/{DOMAIN}/{forger.info.zid()}/0/0/NN/%/%lab/cdprd"
            kept.append(forger.liveliness().declare_token(forged_node))
            gid_out = bytes(range(16))
            for _ in range(20):
                for key_expr in outputs:
                    extra = ze.z_serialize((ze.Int64(1), ze.Int64(time.time_ns()), gid_out))
                    forger.put(key_expr, FORGED, attachment=extra)
            assert get_json(forger, f"{PREFIX}/cmd/status")["ok"]  # after the puts, one link
            before = sum(k == joints for k, _ in seen)
            wait(lambda: sum(k == joints for k, _ in seen) > before + 3, 10.0, "more joints")
            replies = listener.liveliness().get(f"@ros2_lv/{DOMAIN}/*/*/*/NN/**", timeout=5.0)
            nodes = [str(r.ok.key_expr) for r in replies if r.ok is not None]

            path_key = key(f"{NAMESPACE}/path", PATH)
            for _ in range(10):
                forger.put(path_key, b"not cdr")  # no attachment: refused once let in
            wait(lambda: status.count() >= 1, 10.0, "a verdict")
            time.sleep(0.5)
            burst = status.count()
            time.sleep(0.1)  # the 20 Hz limit's period, twice over
            header = msg("std_msgs/msg/Header", stamp=time_msg(0), frame_id="w" * 4_000_000)
            large = bytes(STORE.serialize_cdr(msg(PATH, header=header, poses=[]), PATH))
            forger.put(path_key, large)
            wait(lambda: status.count() > burst, 10.0, "the large Path's verdict")
            with status.lock:
                refused = json.loads(status.items[-1][0].data)
        finally:
            kept.clear()
            listener.close()
            forger.close()
    finally:
        out = finish(proc)
    assert proc.returncode == 0, out
    assert [k for k, p in seen if p == FORGED] == []
    assert len(nodes) == 1 and forged_node not in nodes, nodes
    assert 1 <= burst <= 2
    assert refused["event"] == "trajectory_rejected", refused
    assert refused["error"]["limit"] == "max_message_bytes", refused


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0
