"""The daemon's state as ROS 2 messages, and ROS 2 trajectories as the daemon's
(docs/guide/ros2.md).

Out: geometry_msgs/msg/PoseStamped (measured pose; reference pose = the measured pose
less the tracking error, cdpr.pose.liediff's inverse), sensor_msgs/msg/JointState (one
joint per cable: length m, rate m/s, commanded actuator force N), tf2_msgs/msg/TFMessage
(world -> platform, world -> reference) and diagnostic_msgs/msg/DiagnosticArray (the
safety state and fault).  Poses exist only while the robot is held or tracking.

In: nav_msgs/msg/Path (each pose's header stamp is its time, relative to the first) and
trajectory_msgs/msg/MultiDOFJointTrajectory (one joint: the platform; time_from_start,
optional world-frame velocities and accelerations), in the world frame (frame_id empty or
the configured world frame).  They become the daemon's trajectory form
(cdpr/trajectory/parse.py), which validates them like any other trajectory.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from cdpr.path import Path
from cdpr.pose import Pose, retract
from cdpr.trajectory import Trajectory, TrajectoryLimits
from daemon.config.ros2_config import Ros2Settings
from daemon.interface.messages import (
    TrajectoryMessage,
    TrajectoryRequest,
    encode,
    parse_waypoints,
    time_path_message,
)
from daemon.interface.ros2_wire import message
from daemon.service.api import CommandError

log = logging.getLogger(__name__)

POSE = "geometry_msgs/msg/PoseStamped"
JOINTS = "sensor_msgs/msg/JointState"
TF = "tf2_msgs/msg/TFMessage"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
STATUS = "std_msgs/msg/String"
PATH = "nav_msgs/msg/Path"
MULTI_DOF = "trajectory_msgs/msg/MultiDOFJointTrajectory"
OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/msg/DiagnosticStatus levels
_LEVELS = {"braked": ERROR, "init": WARN}


def stamp(ns: int) -> Any:
    return message("builtin_interfaces/msg/Time", sec=ns // 10**9, nanosec=ns % 10**9)


def header(ns: int, frame: str) -> Any:
    return message("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame)


def state_messages(state: dict[str, Any], settings: Ros2Settings, ns: int) -> dict[str, Any]:
    """The messages for one state snapshot, by setting name (pose_topic, ...), stamped
    `ns` (unix time in ns)."""
    out: dict[str, Any] = {
        "joint_states_topic": _joints(state, ns),
        "diagnostics_topic": _diagnostics(state, settings, ns),
    }
    if "pose" in state:
        measured = _pose(state["pose"])
        reference = retract(measured, -np.asarray(state["tracking_error"], dtype=float))
        world = settings.world_frame
        out["pose_topic"] = pose_stamped(measured, ns, world)
        out["reference_pose_topic"] = message(
            POSE, header=header(ns, world), pose=_ros_pose(reference)
        )
        out["tf_topic"] = message(
            TF,
            transforms=[
                _transform(measured, ns, world, settings.platform_frame),
                _transform(reference, ns, world, settings.reference_frame),
            ],
        )
    return out


def pose_stamped(pose: Pose, ns: int, frame: str) -> Any:
    """`pose` as a geometry_msgs/msg/PoseStamped in `frame`, stamped `ns`."""
    return message(POSE, header=header(ns, frame), pose=_ros_pose(pose))


def state_pose(state: dict[str, Any]) -> Pose | None:
    """The measured pose of a state snapshot (none unless the robot holds or tracks)."""
    return _pose(state["pose"]) if "pose" in state else None


def answer_text(body: dict[str, Any], ok: bool) -> str:
    """A daemon reply `body` (messages.reply_ok / reply_error) as a ROS 2 answer's text:
    the result as JSON, or the refusal as "<code>: <reason>"."""
    if ok:
        return encode(body["result"]).decode()
    return f"{body['error']['code']}: {body['error']['reason']}"


def status_message(text: str) -> Any:
    return message(STATUS, data=text)


def _pose(body: dict[str, Any]) -> Pose:
    q = body["quaternion"]
    return Pose(body["position"], (q["w"], q["x"], q["y"], q["z"]))


def _ros_pose(pose: Pose) -> Any:
    x, y, z = pose.position_tuple
    w, qx, qy, qz = pose.quaternion_tuple
    return message(
        "geometry_msgs/msg/Pose",
        position=message("geometry_msgs/msg/Point", x=x, y=y, z=z),
        orientation=message("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=w),
    )


def _transform(pose: Pose, ns: int, parent: str, child: str) -> Any:
    ros = _ros_pose(pose)
    p = ros.position
    return message(
        "geometry_msgs/msg/TransformStamped",
        header=header(ns, parent),
        child_frame_id=child,
        transform=message(
            "geometry_msgs/msg/Transform",
            translation=message("geometry_msgs/msg/Vector3", x=p.x, y=p.y, z=p.z),
            rotation=ros.orientation,
        ),
    )


def _joints(state: dict[str, Any], ns: int) -> Any:
    lengths = state.get("lengths", [])
    return message(
        JOINTS,
        header=header(ns, ""),
        name=[f"cable{k}" for k in range(len(lengths))],
        position=_floats(lengths),
        velocity=_floats(state.get("rates", [])),
        effort=_floats(state.get("forces", [])),
    )


def _floats(values: list[Any]) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], dtype=np.float64)


def _diagnostics(state: dict[str, Any], settings: Ros2Settings, ns: int) -> Any:
    name = state.get("state", "init")
    fault = state.get("fault")
    level = ERROR if fault else _LEVELS.get(name, OK)
    text = name if not fault else f"{name}: {fault['trigger']}: {fault['message']}"
    values = {"state": name}
    if fault:
        values.update(fault_trigger=fault["trigger"], fault_message=fault["message"])
    values.update(
        (f"cycle.{key}", str(value))
        for key, value in state.get("cycle", {}).items()
        if isinstance(value, int | float | str)
    )
    return message(
        DIAGNOSTICS,
        header=header(ns, ""),
        status=[
            message(
                "diagnostic_msgs/msg/DiagnosticStatus",
                level=level,
                name=f"{settings.node_name}: safety",
                message=text,
                hardware_id=settings.node_name,
                values=[
                    message("diagnostic_msgs/msg/KeyValue", key=k, value=v)
                    for k, v in values.items()
                ],
            )
        ],
    )


# -- in ---------------------------------------------------------------------------------


def trajectory_body(msg: Any, settings: Ros2Settings, max_waypoints: int) -> dict[str, Any]:
    """A received Path or MultiDOFJointTrajectory in the daemon's trajectory form, or a
    Path whose poses all carry one stamp (none: a planner's path, no times) in the path
    form, {"poses": ...}, which the daemon times; CommandError names what does not fit
    (the trajectory's or path's own rules are checked when the form is parsed)."""
    items = msg.poses if msg.__msgtype__ == PATH else msg.points
    _check_frame(msg.header.frame_id, "header.frame_id", settings)
    check_waypoint_count(len(items), msg.__msgtype__, max_waypoints)
    if msg.__msgtype__ == PATH:
        waypoints = _path_waypoints(msg, settings)
        if len(waypoints) > 1 and all(w["t"] == 0.0 for w in waypoints):
            return {"poses": [{k: v for k, v in w.items() if k != "t"} for w in waypoints]}
        return {"waypoints": waypoints}
    return {"waypoints": _multi_dof_waypoints(msg, settings)}


def trajectory_request(
    msg: Any,
    ident: str | None,
    settings: Ros2Settings,
    limits: TrajectoryLimits,
    timer: Callable[[Path], Trajectory] | None = None,
) -> TrajectoryRequest | CommandError:
    """A decoded Path or MultiDOFJointTrajectory (a topic's sample, an action's goal)
    parsed as request `ident`, or a stampless Path's poses timed by `timer`; or why not:
    every bad input gets a CommandError that names the problem, never another exception."""
    try:
        body = trajectory_body(msg, settings, limits.max_waypoints)
        if "poses" not in body:
            head = TrajectoryMessage(ident, None, body, len(body["waypoints"]))
            return parse_waypoints(head, limits)
        if timer is None:
            why = "poses without times are a path, and this interface times none"
            return CommandError("rejected", f"{msg.__msgtype__}: {why}")
        head = TrajectoryMessage(ident, None, body, len(body["poses"]), path=True)
        return time_path_message(head, limits, timer)
    except CommandError as exc:
        return exc
    except Exception as exc:  # a bug must not reach the sender as silence
        log.exception("decoding a ROS 2 trajectory failed")
        return CommandError("internal", f"decoding failed: {type(exc).__name__}")


def check_waypoint_count(count: int, msgtype: str, max_waypoints: int) -> None:
    """Refuse a Path of more poses, or a MultiDOFJointTrajectory of more points, than
    `max_waypoints`."""
    if count > max_waypoints:
        what = "poses" if msgtype == PATH else "points"
        raise CommandError(
            "rejected",
            f"{count} {what} exceed the limit of {max_waypoints} waypoints",
            limit="max_waypoints",
            value=count,
            field=what,
        )


def _check_frame(frame: str, where: str, settings: Ros2Settings) -> None:
    if frame not in ("", settings.world_frame):
        raise CommandError(
            "rejected",
            f"{where}: frame {frame[:100]!r} is not the robot's world frame "
            f"{settings.world_frame!r} (cdprd transforms no frames)",
            field=where,
        )


def _path_waypoints(msg: Any, settings: Ros2Settings) -> list[dict[str, Any]]:
    if not msg.poses:
        raise CommandError("bad_request", "a Path without poses", field="poses")
    first = msg.poses[0].header.stamp
    waypoints = []
    for i, stamped in enumerate(msg.poses):
        _check_frame(stamped.header.frame_id, f"poses[{i}].header.frame_id", settings)
        s = stamped.header.stamp
        t = (s.sec - first.sec) + (s.nanosec - first.nanosec) * 1e-9
        waypoints.append({"t": t, **_pose_fields(stamped.pose.position, stamped.pose.orientation)})
    return waypoints


def _multi_dof_waypoints(msg: Any, settings: Ros2Settings) -> list[dict[str, Any]]:
    if len(msg.joint_names) != 1:
        raise CommandError(
            "bad_request",
            f"joint_names: cdprd moves one platform, got {len(msg.joint_names)} joints",
            field="joint_names",
        )
    if not msg.points:
        raise CommandError("bad_request", "a trajectory without points", field="points")
    waypoints = []
    for i, point in enumerate(msg.points):
        where = f"points[{i}]"
        for name in ("transforms", "velocities", "accelerations"):
            count = len(getattr(point, name))
            if count > 1 or (name == "transforms" and count != 1):
                raise CommandError(
                    "bad_request",
                    f"{where}.{name}: {count} entries for the one joint",
                    field=f"{where}.{name}",
                )
        transform = point.transforms[0]
        d = point.time_from_start
        waypoint = {"t": d.sec + d.nanosec * 1e-9}
        waypoint.update(_pose_fields(transform.translation, transform.rotation))
        if point.velocities:
            waypoint["twist"] = _six(point.velocities[0])
        if point.accelerations:
            waypoint["accel"] = _six(point.accelerations[0])
        waypoints.append(waypoint)
    return waypoints


def _pose_fields(position: Any, q: Any) -> dict[str, Any]:
    return {
        "position": [position.x, position.y, position.z],
        "quaternion": {"w": q.w, "x": q.x, "y": q.y, "z": q.z},
    }


def _six(twist: Any) -> dict[str, list[float]]:
    lin, ang = twist.linear, twist.angular
    return {"linear": [lin.x, lin.y, lin.z], "angular": [ang.x, ang.y, ang.z]}
