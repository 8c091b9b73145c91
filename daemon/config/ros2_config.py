"""The `ros2:` config section: ROS 2 over rmw_zenoh's wire format (opt-in; docs/guide/ros2.md).

The bridge joins a ROS 2 graph's zenoh router such as `ros2 run rmw_zenoh_cpp rmw_zenohd`
as a client (`ros2: {enabled: true, router: tcp/127.0.0.1:7447}`), or runs on the
daemon's own zenoh session, where ROS 2 nodes connect to the daemon's listen endpoint.
Topic and service names follow ROS 2: a name that starts with "/" is absolute, any other
is under `namespace`.
"""

from __future__ import annotations

from pydantic import Field

from cdpr.description import PositiveFloat, StrictModel

_NAME = r"[A-Za-z][A-Za-z0-9_]*"  # a ROS 2 name token (no "~", no substitutions)
_TOPIC = rf"^/?{_NAME}(/{_NAME})*$"
_NAMESPACE = rf"^/({_NAME}(/{_NAME})*)?$"


class Ros2Settings(StrictModel):
    """Every key optional; nothing is published or accepted unless `enabled`."""

    enabled: bool = False
    """Run the ROS 2 bridge on the daemon's zenoh session."""
    router: str | None = Field(None, max_length=200)
    """The ROS 2 graph's zenoh router, e.g. tcp/127.0.0.1:7447 where `ros2 run
    rmw_zenoh_cpp rmw_zenohd` listens: the node runs on a client session of its own that
    connects there (tried every 2 s until the router answers), under the same loopback
    rule as zenoh.connect and with zenoh.config's `transport` settings (a tls/ router's
    certificates); the daemon's session keeps its own endpoint (zenoh.listen, 7448 by
    default).  None: the node is on the daemon's session, where ROS 2 nodes connect."""
    domain_id: int = Field(0, ge=0, le=232)  # the ROS 2 domain (ROS_DOMAIN_ID) of its topics
    node_name: str = Field("cdprd", pattern=rf"^{_NAME}$", max_length=100)
    """The ROS 2 node's name; the diagnostics status is named after it too."""
    namespace: str = Field("/", pattern=_NAMESPACE, max_length=200)
    """The node's namespace ("/" or "/a/b"); a topic name without a leading "/" is under it."""
    rate_hz: PositiveFloat = Field(30.0, le=1000.0)
    """Publication rate of the pose, joint, tf, diagnostic and cable marker topics."""
    world_frame: str = Field("world", pattern=rf"^{_NAME}$")
    """The frame of every pose sent and the frame_id an incoming trajectory must name
    (or leave empty)."""
    platform_frame: str = Field("platform", pattern=rf"^{_NAME}$")
    """The tf frame of the measured platform pose (child of world_frame)."""
    reference_frame: str = Field("platform_reference", pattern=rf"^{_NAME}$")
    """The tf frame of the reference pose, where the platform should be (child of
    world_frame)."""
    pose_topic: str = Field("pose", pattern=_TOPIC)
    """geometry_msgs/msg/PoseStamped out: the measured platform pose."""
    reference_pose_topic: str = Field("reference_pose", pattern=_TOPIC)
    """geometry_msgs/msg/PoseStamped out: the reference pose."""
    joint_states_topic: str = Field("joint_states", pattern=_TOPIC)
    """sensor_msgs/msg/JointState out: per cable its length (m), rate (m/s) and commanded
    force (N)."""
    tf_topic: str = Field("/tf", pattern=_TOPIC)
    """tf2_msgs/msg/TFMessage out: platform_frame and reference_frame in world_frame."""
    diagnostics_topic: str = Field("/diagnostics", pattern=_TOPIC)
    """diagnostic_msgs/msg/DiagnosticArray out: the safety state and fault."""
    path_topic: str = Field("path", pattern=_TOPIC)
    """nav_msgs/msg/Path in: a trajectory to fly."""
    multi_dof_trajectory_topic: str = Field("multi_dof_trajectory", pattern=_TOPIC)
    """trajectory_msgs/msg/MultiDOFJointTrajectory in: a trajectory to fly."""
    robot_description_topic: str = Field("robot_description", pattern=_TOPIC)
    """std_msgs/msg/String out, transient local (keep last 1, as robot_state_publisher's):
    the robot file as a URDF, for RViz's RobotModel display."""
    tf_static_topic: str = Field("/tf_static", pattern=_TOPIC)
    """tf2_msgs/msg/TFMessage out, transient local (keep last 1, as tf2's static
    broadcaster's): world_frame -> anchor<k> at each cable's anchor and platform_frame ->
    attachment<k> at each attachment point."""
    cables_topic: str = Field("cables", pattern=_TOPIC)
    """visualization_msgs/msg/MarkerArray out at rate_hz, at most 30 Hz: each cable a
    line from its anchor to its attachment point at the measured pose, coloured by
    tension; deleted while there is no pose."""
    status_topic: str = Field("trajectory_status", pattern=_TOPIC)
    """std_msgs/msg/String: the verdict on each trajectory received (JSON text)."""
    enable_service: str = Field("enable", pattern=_TOPIC)
    """std_srvs/srv/Trigger: the `enable` command (success and the reply or the refusal)."""
    hold_service: str = Field("hold", pattern=_TOPIC)
    """std_srvs/srv/Trigger: the `hold` command."""
    brake_service: str = Field("brake", pattern=_TOPIC)
    """std_srvs/srv/Trigger: the `brake` command."""
    reset_service: str = Field("reset", pattern=_TOPIC)
    """std_srvs/srv/Trigger: the `reset` command."""
    disable_service: str = Field("disable", pattern=_TOPIC)
    """std_srvs/srv/Trigger: the `disable` command."""
    observer_hold_service: str = Field("hold_observer", pattern=_TOPIC)
    """std_srvs/srv/SetBool: the `observer` command, the wrench observer held (data true)
    or let back in (false)."""
    payload_freeze_service: str = Field("freeze_payload", pattern=_TOPIC)
    """std_srvs/srv/SetBool: the `payload` command, the payload estimate frozen (data
    true) or unfrozen (false)."""
    fly_path_action: str = Field("fly_path", pattern=_TOPIC)
    """cdprd_interfaces/action/FlyPath: a nav_msgs/Path flown as the `path` topic's is,
    with feedback (progress, time remaining, tracking error, pose) at `rate_hz`; a cancel
    holds the robot.  One goal at a time: a new one replaces the one flying (which ends
    aborted).  The interface package is daemon/interface/cdprd_interfaces (colcon
    build it where ROS 2 nodes run)."""
    max_message_bytes: int | None = Field(None, ge=1024, le=256 * 1024 * 1024)
    """An incoming trajectory above this size is refused unread; None: the zenoh
    interface's zenoh.max_message_bytes, the cap of every way a trajectory comes in."""
    ingress_limit_hz: PositiveFloat | None = None
    """Per trajectory topic: zenoh drops samples that come sooner than 1/limit after the
    last one it let through, before the daemon sees them; None: the limit
    zenoh.ingress_limits_hz puts on `trajectory` (no limit if it puts none)."""
    queue_depth: int = Field(4, ge=1, le=64)
    """Trajectories waiting to be decoded and validated; more are refused "busy"."""

    def topic(self, name: str) -> str:
        """The fully qualified name of topic or service `name` (absolute, or under the
        namespace)."""
        if name.startswith("/"):
            return name
        return f"{self.namespace.rstrip('/')}/{name}"
