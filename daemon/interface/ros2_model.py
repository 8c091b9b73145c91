"""The robot as RViz shows it (docs/guide/ros2.md, "RViz"): what the ROS 2 bridge
publishes beside the state when it knows the robot.

- `robot_description` (std_msgs/msg/String, transient local, keep last 1, as
  robot_state_publisher publishes it): the URDF (daemon.interface.urdf);
- `/tf_static` (tf2_msgs/msg/TFMessage, transient local, keep last 1, as tf2's static
  broadcaster publishes it): world -> anchor<k> and platform -> attachment<k>, the URDF's
  fixed joints;
- `cables` (visualization_msgs/msg/MarkerArray, volatile, at the state rate): one line
  per cable from its anchor to its attachment point at the measured pose, coloured and
  sized as the live view draws it (daemon.process.scene.cable_styles); while there is no
  pose (idle, braked) a single DELETEALL of the namespace instead.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cdpr import Robot
from daemon.config.ros2_config import Ros2Settings
from daemon.interface.robot_drawing import attachments_at, cable_faults, cable_styles
from daemon.interface.ros2_convert import TF, header
from daemon.interface.ros2_wire import message
from daemon.interface.urdf import fixed_frames, robot_urdf

STRING = "std_msgs/msg/String"
MARKER = "visualization_msgs/msg/Marker"
MARKERS = "visualization_msgs/msg/MarkerArray"
LINE_LIST, ADD, DELETEALL = 5, 0, 3  # Marker.msg's type and action constants
NAMESPACE = "cables"  # the markers' ns
# setting naming the topic -> its type, QoS depth and whether transient local
TOPICS = {
    "robot_description_topic": (STRING, 1, True),
    "tf_static_topic": (TF, 1, True),
    "cables_topic": (MARKERS, 10, False),
}
LIFETIME_PERIODS = 3  # a line outlives its publication by this many periods (at least 1 s)
CABLES_MAX_HZ = 30.0  # the markers at most this often: RViz draws no faster, and at the
# loop's rate (ros2.rate_hz up to 1000) their ~0.8 ms each would take most of a core


class RobotModel:
    """The messages above for `robot`, with the frame names of `settings`."""

    def __init__(self, robot: Robot, settings: Ros2Settings) -> None:
        self.robot = robot
        self.settings = settings
        self.urdf = robot_urdf(robot, settings)
        self.cables_period_ns = round(1e9 / min(settings.rate_hz, CABLES_MAX_HZ))
        self._cables_ns = -self.cables_period_ns  # when they last went out
        lifetime = max(1.0, LIFETIME_PERIODS * self.cables_period_ns / 1e9)
        empty = np.zeros(0, dtype=np.uint8)
        self._constant = {  # the fields every marker shares, built once
            "pose": message(
                "geometry_msgs/msg/Pose",
                position=message("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                orientation=message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            "lifetime": message(
                "builtin_interfaces/msg/Duration",
                sec=int(lifetime),
                nanosec=round(lifetime % 1.0 * 1e9),
            ),
            "frame_locked": False,
            "colors": [],
            "texture_resource": "",
            "texture": message(
                "sensor_msgs/msg/CompressedImage", header=header(0, ""), format="", data=empty
            ),
            "uv_coordinates": [],
            "text": "",
            "mesh_resource": "",
            "mesh_file": message("visualization_msgs/msg/MeshFile", filename="", data=empty),
            "mesh_use_embedded_materials": False,
        }

    def latched(self, ns: int) -> dict[str, Any]:
        """robot_description and /tf_static, by setting name, /tf_static stamped `ns`."""
        return {
            "robot_description_topic": message(STRING, data=self.urdf),
            "tf_static_topic": message(
                TF,
                transforms=[
                    message(
                        "geometry_msgs/msg/TransformStamped",
                        header=header(ns, frame.parent),
                        child_frame_id=frame.child,
                        transform=message(
                            "geometry_msgs/msg/Transform",
                            translation=message("geometry_msgs/msg/Vector3", **_xyz(frame.xyz)),
                            rotation=message(
                                "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0
                            ),
                        ),
                    )
                    for frame in fixed_frames(self.robot, self.settings)
                ],
            ),
        }

    def cables_due(self, ns: int) -> bool:
        """Whether a snapshot at `ns` publishes the cables (at most CABLES_MAX_HZ; a
        snapshot a little early, by the loop's jitter, still counts), and if so, mark it."""
        if ns - self._cables_ns < 0.9 * self.cables_period_ns:
            return False
        self._cables_ns = ns
        return True

    def cables(self, state: dict[str, Any], ns: int) -> Any:
        """The cables of one state snapshot as a MarkerArray stamped `ns`: a line each
        while the state has a pose, else one DELETEALL."""
        stamp = header(ns, self.settings.world_frame)
        if "pose" not in state:
            return message(MARKERS, markers=[self._marker(stamp, 0, DELETEALL)])
        body = state["pose"]
        q = body["quaternion"]
        ends = attachments_at(
            self.robot.geometry.attachments, body["position"], (q["w"], q["x"], q["y"], q["z"])
        )
        tensions = [math.nan if t is None else t for t in state.get("tensions", [])]
        n = self.robot.n_cables
        tensions = (tensions + [math.nan] * n)[:n]
        styles = cable_styles(self.robot, tensions, cable_faults(state, n))
        markers = [
            self._marker(stamp, k, ADD, (a, b), color, width)
            for k, (a, b, (color, width, _label)) in enumerate(
                zip(self.robot.geometry.anchors, ends, styles, strict=True)
            )
        ]
        return message(MARKERS, markers=markers)

    def _marker(
        self,
        stamp: Any,
        ident: int,
        action: int,
        ends: tuple[np.ndarray, np.ndarray] | None = None,
        color: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
        width: float = 0.0,
    ) -> Any:
        r, g, b, a = (float(c) for c in color)
        return message(
            MARKER,
            header=stamp,
            ns=NAMESPACE,
            id=ident,
            type=LINE_LIST,
            action=action,
            scale=message("geometry_msgs/msg/Vector3", x=float(width), y=0.0, z=0.0),
            color=message("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a),
            points=[message("geometry_msgs/msg/Point", **_xyz(p)) for p in ends or ()],
            **self._constant,
        )


def _xyz(v: Any) -> dict[str, float]:
    x, y, z = (float(c) for c in v)
    return {"x": x, "y": y, "z": z}
