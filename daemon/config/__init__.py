"""The daemon's config file (DESIGN §11): one YAML per robot, validated at load.

Sections: robot (a path relative to this file, or inline), controller, drives, can,
safety, environment (planes and boxes the platform and the cables must not cross,
daemon.config.environment_config), trajectory (limits), zenoh, logging, recording,
realtime (what the core process asks of the kernel), view (the live 3-D view,
daemon.config.view_config), sim (the simulator used by `run --sim`, `demo` and `sim`).
Every problem is a ConfigError naming the key; the geometry is checked for sense (Λ full
rank at home, the home pose's static wrench in W, the platform clear of the environment).
"""

from __future__ import annotations

import functools
import math
import os
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from cdpr import ConfigError, Robot
from cdpr.control_spec import ControllerSpec, parse_controller
from cdpr.controller import tension_solver
from cdpr.description import (
    PositiveFloat,
    StrictModel,
    Vec3,
    load_yaml,
    show_path,
    validate_section,
)
from cdpr.payload import payload_limits
from cdpr.pose_limits import PoseLimits
from cdpr.pretension import PretensionSpec
from cdpr.trajectory import (
    TrajectoryLimits,
    cable_speed_bounds,
    sampled_pose_limits,
    tracked_length_limits,
)
from daemon.config.environment_config import EnvironmentConfig, environment_of
from daemon.config.feedback_tolerance import FeedbackTolerance, feedback_tolerance
from daemon.config.ros2_config import Ros2Settings
from daemon.config.view_config import ViewConfig
from daemon.config.watchdog_drift import DriftBound, check_drift, drift_bounds
from daemon.config.workspace_config import WorkspaceConfig

if TYPE_CHECKING:
    from cdpr.workspace_check import WorkspaceCheck
from daemon.config.zenoh_config import ZenohSettings
from drivers.cia402.profile import ProfileError, plans, with_eds_from
from drivers.config import CanConfig, CanSection, DrivesConfig, can_buses, parse_drives

Fraction = Annotated[float, Field(gt=0.0, lt=1.0)]


class SafetyConfig(StrictModel):
    """Brake triggers (DESIGN §9).  Positions in m, angles in rad, world frame.

    workspace_min / workspace_max: lowest and highest corner of the box for the platform
      reference point and every corner of its body (the robot file's platform.body,
      default the attachment points' hull); null: the anchors' bounding box.
    tilt_max: largest rotation angle from the home orientation.
    tracking_error_position / tracking_error_orientation: largest |θ_d| parts (m, rad) while
      tracking or holding.
    Trajectories are validated inside the box, the tilt and clear of the environment
    less these (a corner at r from p: less tracking_error_position + r x
    tracking_error_orientation) and a sampling margin: the measured pose, within them of
    the reference, then stays inside.
    stale_cycles: consecutive cycles an actuator may miss its feedback.
    feedback_deadline: fraction of the period to wait for feedback after the cycle opens.
    bus_errors_max: bus errors (error frames, failed sends) tolerated within one second.
    bus_lost_exit: seconds from losing the bus (socket closed, interface down, socketcand
      server gone) to exiting with code 69, braked, for the service manager to restart
      the daemon; the time lets the fault reach zenoh and systemd.
    max_cable_speed: the fastest a drum pays cable out or winds it in (m/s: the drive's
      top speed through gear and drum).  A reported rate above it, or a length that
      moved faster since the cable's last trusted sample, is implausible feedback
      (daemon.service.trusted_lengths); it must exceed what the trajectory limits allow.
    feedback_tolerance: encoder noise, quantisation and cable stretch allowed between two
      samples (m): the allowance beyond max_cable_speed, and the most one cable may
      disagree with the pose the others give.  "auto": derived from the encoders'
      increments, drives.encoder_noise and the stretch of unplanned_tension
      (daemon.config.feedback_tolerance; `cdprd check-config` prints it); a number
      replaces that, but not below the increments alone.
    unplanned_tension: the most a cable's tension may change between two samples beyond
      what the controller planned (N: a hand on the platform, the drives' force error);
      the cables' stretch (robot file's cable_stiffness) turns it into length.
    companion_hang: seconds the companion process (zenoh, planning, recording) may stay
      silent before the core kills and restarts it.
    companion_lost: seconds a moving robot goes on (its trajectory, then holding) without
      a live companion before it brakes; an idle or braked robot is held anyway.
    max_watchdog_drift: the most a cable may move (m) between the daemon's death and the
      moment its drive notices and holds (daemon.config.watchdog_drift); a config whose
      bound exceeds it is refused.
    rest_force / rest_torque: the largest net force (N) and torque about the reference
      point (N m) the tensions the drives measure at rest may leave unbalanced at the
      pose the lengths say (enable) or the pose named (home) (daemon.service.rest_check):
      more, and the pose is not where the platform is; the command is refused.  An
      undeclared payload or a push leaves a net force too: 30 N (the default) allows a
      3 kg payload on reference8 and refuses a zero 50 mm off in z (43 N).
    """

    workspace_min: Vec3 | None = None
    workspace_max: Vec3 | None = None
    tilt_max: Annotated[float, Field(gt=0.0, le=math.pi)] = 0.6
    tracking_error_position: PositiveFloat = 0.02
    tracking_error_orientation: PositiveFloat = 0.05
    stale_cycles: Annotated[int, Field(ge=1, le=1000)] = 3
    feedback_deadline: Fraction = 0.5
    bus_errors_max: Annotated[int, Field(ge=0)] = 5
    max_cable_speed: PositiveFloat = 3.0
    feedback_tolerance: PositiveFloat | Literal["auto"] = "auto"
    unplanned_tension: Annotated[float, Field(gt=0.0, le=1e4)] = 8.0
    bus_lost_exit: Annotated[float, Field(gt=0.0, le=60.0)] = 1.0
    companion_hang: Annotated[float, Field(ge=0.2, le=60.0)] = 1.0
    companion_lost: Annotated[float, Field(gt=0.0, le=3600.0)] = 10.0
    max_watchdog_drift: PositiveFloat = 0.2
    rest_force: PositiveFloat = 30.0
    rest_torque: PositiveFloat = 5.0


class LoggingConfig(StrictModel):
    level: Literal["debug", "info", "warning", "error"] = "info"  # the least severe level logged


class RecordingConfig(StrictModel):
    """Optional recordings: cycle telemetry to MCAP, raw CAN to a python-can log file
    (format by suffix: .log, .asc, .blf, .csv, .trc).  Relative paths are from the config;
    each file is named after the time it began (daemon.process.recording_files).

    rotate_mb / rotate_minutes: a recording begins a new file once its current one is
      this large (MB, 10^6 bytes) or this old; null: no such limit.
    keep_mb / keep_files: the most each recording's files (this run's and earlier runs')
      take together, the one being written counted at rotate_mb, and the most files it
      keeps; the oldest are deleted first, as each new file begins; null: no limit.
    min_free_mb: below this much free space on its file system a recording pauses (the
      daemon runs on, and says so in its status, state and events) and resumes in a new
      file once there is 10 % (at least 16 MB) more; 0: no floor.
    The defaults hold both recordings (about 0.85 GB an hour at 500 Hz) to 8 GB for as
    long as the service runs.
    """

    telemetry: str | None = None  # MCAP file of the cycle telemetry; null: not recorded
    can_log: str | None = None  # python-can log file of the raw CAN frames; null: not recorded
    rotate_mb: PositiveFloat | None = 256.0
    rotate_minutes: PositiveFloat | None = 60.0
    keep_mb: PositiveFloat | None = 4096.0
    keep_files: Annotated[int, Field(ge=1)] | None = None
    min_free_mb: Annotated[float, Field(ge=0.0)] = 1024.0

    @model_validator(mode="after")
    def _room_for_a_file(self) -> RecordingConfig:
        keep, rotate = self.keep_mb, self.rotate_mb
        if keep is not None and rotate is not None and keep < rotate:
            raise ValueError(
                f"keep_mb ({keep:g}) is less than rotate_mb ({rotate:g}): the file being "
                "written alone may grow to rotate_mb"
            )
        if (keep is not None or self.keep_files is not None) and (
            rotate is None and self.rotate_minutes is None
        ):
            raise ValueError(
                "keep_mb / keep_files need rotate_mb or rotate_minutes: without either, one "
                "file grows for the whole run and nothing can be deleted"
            )
        return self


MAX_CPUS = 8192  # the kernel's largest NR_CPUS
MAX_CPU_LATENCY_US = 2**31 - 1  # /dev/cpu_dma_latency takes a signed 32-bit value
CpuIndex = Annotated[int, Field(ge=0, lt=MAX_CPUS)]


class RealtimeConfig(StrictModel):
    """What the core process (the control cycle) asks of the kernel at start-up
    (daemon.process.realtime; docs/explanation/realtime.md).  Where it is not permitted the core
    runs on at normal service, with a warning that names what to allow.

    priority: SCHED_FIFO priority, 1..99; 0 or null: normal scheduling, nothing asked.
    cpus: the CPUs the core may run on (indices as in /proc/cpuinfo), or null: any.
    lock_memory: mlockall(MCL_CURRENT | MCL_FUTURE), so that no page the cycle touches is
      paged out or first faulted in while the drives' watchdogs wait.
    cpu_latency_us: the CPUs' wake-up latency (us) held while the core runs (the kernel's
      CPU latency QoS, /dev/cpu_dma_latency): 0 keeps idle CPUs in their shallowest idle
      state (x86's cpuidle polls: more power; ARM waits in WFI), so that no wake-up of
      the cycle waits for a CPU to leave a deeper one; null: the idle states as they are.
    """

    priority: Annotated[int, Field(ge=0, le=99)] | None = 50
    cpus: tuple[CpuIndex, ...] | None = None
    lock_memory: bool = True
    cpu_latency_us: Annotated[int, Field(ge=0, le=MAX_CPU_LATENCY_US)] | None = 0

    @field_validator("cpus")
    @classmethod
    def _each_cpu_once(cls, cpus: tuple[int, ...] | None) -> tuple[int, ...] | None:
        if cpus == ():
            raise ValueError("an empty list: give CPU indices, or null for any CPU")
        twice = sorted(c for c, n in Counter(cpus or ()).items() if n > 1)
        if twice:
            raise ValueError(f"CPU {', '.join(map(str, twice))} listed more than once")
        return cpus


class FileConfig(StrictModel):
    """The config file as read, before the robot is built: one YAML mapping per robot,
    these keys at its top level, each section's keys in the tables that follow.  Paths
    are relative to the config file."""

    robot: str | dict[str, Any]  # a robot file (relative to this file) or the description inline
    controller: dict[str, Any] = Field(default_factory=dict)  # the control law (below)
    drives: dict[str, Any]  # the motor drives: protocol, node ids, scaling, braking (below)
    can: CanSection = CanConfig()  # the CAN bus (python-can arguments), or a list of buses
    safety: SafetyConfig = SafetyConfig()  # brake triggers and the workspace (below)
    environment: EnvironmentConfig = EnvironmentConfig()  # obstacles: planes and boxes (below)
    workspace: WorkspaceConfig = WorkspaceConfig()  # capacity margin, interference, map (below)
    trajectory: TrajectoryLimits = TrajectoryLimits()  # limits every trajectory keeps (below)
    zenoh: dict[str, Any] = Field(default_factory=dict)  # the zenoh session (below)
    logging: LoggingConfig = LoggingConfig()  # the daemon's log output (below)
    recording: RecordingConfig = RecordingConfig()  # telemetry and raw CAN recordings (below)
    realtime: RealtimeConfig = RealtimeConfig()  # what the control cycle asks of the kernel (below)
    view: ViewConfig = ViewConfig()  # the live 3-D view (below)
    sim: dict[str, Any] = Field(default_factory=dict)  # the simulator; sim_bus.config validates it
    ros2: dict[str, Any] = Field(default_factory=dict)  # ROS 2 bridge; Ros2Settings validates it
    # directory of the homing and calibration state (daemon.service.calibration_state),
    # relative to this file; null: systemd's $STATE_DIRECTORY (the unit's
    # StateDirectory=cdprd, /var/lib/cdprd), else none (the state is kept in memory only)
    state_dir: Annotated[str, Field(min_length=1)] | None = None
    # bring-up from slack cables on a docking fixture (cdpr.pretension, `cdprd pretension`)
    pretension: PretensionSpec = PretensionSpec()


class DaemonConfig:
    """A loaded, checked config: the robot and every section as validated objects.
    `source` names the file in error messages."""

    def __init__(self, raw: FileConfig, robot: Robot, base: Path, source: str = "config") -> None:
        self.raw = raw
        self.robot = robot
        self.base = base
        self.source = source
        self.controller: ControllerSpec = parse_controller(raw.controller, source)
        if self.controller.adaptation.enabled:
            try:
                payload_limits(robot, self.controller.adaptation)
            except ValueError as exc:
                raise ConfigError(f"{source}: controller.{exc}") from None
        self.drives: DrivesConfig = parse_drives(raw.drives, source)
        if len(self.drives.nodes) != robot.n_cables:
            raise ConfigError(
                f"{source}: drives.nodes: lists {len(self.drives.nodes)} drives for "
                f"{robot.n_cables} cables"
            )
        if self.drives.streamed and self.drives.feedback_rate_hz < self.controller.rate_hz:
            raise ConfigError(
                f"{source}: drives.feedback_rate_hz ({self.drives.feedback_rate_hz:g}) is below "
                f"controller.rate_hz ({self.controller.rate_hz:g}): most cycles would find no "
                "fresh feedback"
            )
        # CiA 402: the drive profile checked against the drive's EDS now, not at start-up
        # (the plan itself is not kept: the config crosses to the companion by pickle)
        # the drives' watchdog and what it lets a cable do (check_drift, after the limits)
        self.watchdog_drift: list[DriftBound] = []
        if self.drives.protocol == "cia402":
            self.drives = with_eds_from(self.drives, base)
            try:
                period, consumer = self.drives.host_heartbeat(self.controller.period)
            except ValueError as exc:
                raise ConfigError(f"{source}: drives.{exc}") from None
            self.drives = self.drives.model_copy(
                update={"host_heartbeat_period": period, "consumer_heartbeat_time": consumer}
            )
            try:
                checked = plans(self.drives)
            except ProfileError as exc:
                bus = f" (bus {exc.bus})" if exc.bus else ""
                raise ConfigError(f"{source}: drives.{exc}{bus}") from None
            if self.controller.velocity == "drive" and not all(
                p.velocity for p in checked.values()
            ):
                raise ConfigError(
                    f"{source}: controller.velocity: drive, but no TPDO on SYNC of "
                    "drives.profile maps velocity actual 0x606C: set controller.velocity: "
                    "differentiate (the twist from successive poses)"
                )
            detection = max(p.detection for p in checked.values())
            self.watchdog_drift = drift_bounds(robot, self.drives.nodes, raw.trajectory, detection)
        # the buses of `can:` (one, or a list), the first the only one in a single-bus config
        self.buses: list[CanConfig] = can_buses(raw.can, self.drives, source)
        configured = raw.safety.feedback_tolerance
        try:
            self.feedback_tolerance: FeedbackTolerance = feedback_tolerance(
                robot, self.drives, raw.safety.unplanned_tension,
                None if configured == "auto" else configured,
            )  # fmt: skip
        except ConfigError as exc:
            raise exc.within(source) from None
        self.safety = raw.safety
        self.trajectory = raw.trajectory
        self.zenoh: ZenohSettings = validate_section(ZenohSettings, raw.zenoh, source, "zenoh")
        self.logging = raw.logging
        self.recording = raw.recording
        self.realtime = raw.realtime
        self.view: ViewConfig = raw.view
        self.sim = raw.sim
        self.ros2: Ros2Settings = validate_section(Ros2Settings, raw.ros2, source, "ros2")
        # the ROS 2 bridge's own client session to the ROS 2 graph's router, if any
        self.ros2_router: ZenohSettings | None = None
        if self.ros2.enabled and self.ros2.router is not None:
            section = {
                "mode": "client",
                "connect": [self.ros2.router],
                "expose": self.zenoh.expose,  # off loopback as zenoh.connect may be
                # with the daemon's transport settings (TLS certificates for tls/ ones)
                "config": {k: v for k, v in self.zenoh.config.items() if k == "transport"},
                "max_message_bytes": self.ros2.max_message_bytes or self.zenoh.max_message_bytes,
            }
            where = f"{source}: ros2.router (a client session of the ROS 2 bridge's own)"
            self.ros2_router = validate_section(ZenohSettings, section, where, "zenoh")
        if self.ros2.ingress_limit_hz is not None and "downsampling" in self.zenoh.config:
            raise ConfigError(
                f"{source}: ros2.ingress_limit_hz: a raw zenoh.config downsampling is set "
                "too and both set zenoh's downsampling: use one of them"
            )
        self.state_dir = _state_dir(self, raw.state_dir)
        self.pretension: PretensionSpec = raw.pretension
        try:
            lo, hi = workspace_box(robot, raw.safety)
            environment = environment_of(robot, raw.environment)
        except ConfigError as exc:
            raise exc.within(source) from None
        # the runtime check on the measured pose, and what validation holds each sampled
        # reference to: less the tracking-error bounds, then the sampling margin
        self.pose_limits = PoseLimits(
            tuple(lo.tolist()),
            tuple(hi.tolist()),
            robot.home.quaternion_tuple,
            raw.safety.tilt_max,
            body=robot.body,
            environment=environment,
        )
        tracked = self.pose_limits.shrunk(
            raw.safety.tracking_error_position, raw.safety.tracking_error_orientation
        )
        self.reference_limits = sampled_pose_limits(tracked, raw.trajectory)
        # and the cable lengths validation holds each sampled reference to
        self.reference_lengths = tracked_length_limits(
            robot,
            raw.safety.tracking_error_position,
            raw.safety.tracking_error_orientation,
            raw.trajectory,
        )
        fastest = max(cable_speed_bounds(robot, raw.trajectory))
        if raw.safety.max_cable_speed <= fastest:
            raise ConfigError(
                f"{source}: safety.max_cable_speed: {raw.safety.max_cable_speed:g} m/s must "
                f"exceed the fastest cable rate the trajectory limits allow ({fastest:.3g} m/s: "
                "linear_speed + angular_speed x the farthest attachment)"
            )
        check_drift(self.watchdog_drift, raw.safety.max_watchdog_drift, source)
        self.workspace = raw.workspace
        self.environment = environment
        self.workspace_box = (lo, hi)

    @functools.cached_property
    def workspace_check(self) -> WorkspaceCheck:
        """What validation holds every sampled reference to beyond the pose limits
        (cdpr.workspace_check).  Built on first use, by the companion and the offline
        tools: it compiles with numba, which the real-time core never loads."""
        from cdpr.workspace_check import WorkspaceCheck

        return WorkspaceCheck.of(self.robot, self.workspace.margin, self.workspace.interference)

    def workspace_map_path(self) -> Path | None:
        """Where the workspace map lives: workspace.map, else STATE_DIR/ROBOT.workspace,
        else None (no state directory)."""
        if self.workspace.map is not None:
            return self.path(self.workspace.map)
        if self.state_dir is None:
            return None
        return self.state_dir / f"{self.robot.name}.workspace"

    @property
    def channels(self) -> str:
        """The buses' channels, for log lines: "can0", or "can0, can1"."""
        return ", ".join(bus.channel for bus in self.buses)

    def path(self, relative: str) -> Path:
        """A path from the config, resolved against the config file's directory."""
        p = Path(relative)
        return p if p.is_absolute() else self.base / p


def _state_dir(config: DaemonConfig, configured: str | None) -> Path | None:
    """Where homing and calibration state lives: `state_dir` (from the config's directory),
    else the first of systemd's $STATE_DIRECTORY, else None (kept in memory only)."""
    if configured is not None:
        return config.path(configured)
    systemd = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(systemd) if systemd else None


def workspace_box(robot: Robot, safety: SafetyConfig) -> tuple[np.ndarray, np.ndarray]:
    """The configured workspace box, else the anchors' bounding box."""
    anchors = robot.geometry.anchors
    lo = np.asarray(safety.workspace_min) if safety.workspace_min else anchors.min(axis=0)
    hi = np.asarray(safety.workspace_max) if safety.workspace_max else anchors.max(axis=0)
    if np.any(lo >= hi):
        raise ConfigError(
            f"safety.workspace_min: {lo.tolist()} must lie below workspace_max {hi.tolist()}"
        )
    return lo.astype(float), hi.astype(float)


def load_config(
    path: str | Path, edit: Callable[[dict[str, Any]], None] | None = None
) -> DaemonConfig:
    """Read, validate and sanity-check a daemon config file; `edit` may change the
    mapping first (the demo's loopback port, a benchmark's rate, a test's section)."""
    path = Path(path)
    data = load_yaml(path)
    if edit is not None:
        if not isinstance(data, dict):
            raise ConfigError(f"{show_path(path)}: expected a mapping at the top level")
        edit(data)
    return parse_config(data, path.resolve().parent, show_path(path))


def parse_config(data: Any, base: Path, source: str = "config") -> DaemonConfig:
    """Validate a config mapping; relative paths in it are taken from `base`.  `source`
    (the file) starts every line of a ConfigError."""
    raw = validate_section(FileConfig, data, source)
    config = DaemonConfig(raw, Robot.from_reference(raw.robot, base, source), base, source)
    check_geometry(config)
    return config


def check_workspace(config: DaemonConfig) -> None:
    """The home pose inside the workspace trajectories must keep (the capacity margin, no
    interference: cdpr.workspace_check), else ConfigError.  Apart from check_geometry:
    it compiles with numba, which `check-config`, the companion and the offline tools
    load and the real-time core does not."""
    home = config.robot.home
    refused = config.workspace_check.first_refusal(home.position[None], home.rotation)
    if refused is not None:
        raise ConfigError(
            f"{config.source}: {refused.limit}: at the home pose {refused.detail}, which "
            "trajectories must keep"
        )


def check_geometry(config: DaemonConfig) -> None:
    """The home pose's static wrench in W and the home pose inside the limits trajectories
    are validated against (ConfigError if not); Robot itself refuses a rank-deficient Λ
    at home."""
    robot = config.robot
    home = robot.home
    Lam = robot.jacobian(home)
    solver = tension_solver(robot, config.controller)
    zero = np.zeros(robot.n_cables)
    result = solver.solve(Lam, robot.bias_wrench(home, np.zeros(6)), zero, zero)
    if not result.feasible:
        raise ConfigError(
            f"{config.source}: robot: the home pose is not in the wrench set W: {result.reason}"
        )
    short = config.reference_lengths.violation(robot.cable_lengths(home).tolist())
    if short is not None:
        k, ell, lo, hi = short
        raise ConfigError(
            f"{config.source}: robot: cable {k} at the home pose is {ell:.4g} m, outside "
            f"[{lo:.4g}, {hi:.4g}] m: its length_min/length_max less the margins of "
            "safety.tracking_error_position/_orientation and cable stretch, inside which "
            "trajectories must stay"
        )
    bad = config.reference_limits.violation(home)
    if bad is None:
        return
    safety, where = config.safety, f"{config.source}: safety:"
    if bad.limit == "environment":
        raise ConfigError(
            f"{config.source}: environment: at the home pose {bad.detail}, which trajectories "
            "must keep clear of"
        )
    if bad.limit == "tilt_max":
        raise ConfigError(
            f"{where} tilt_max ({safety.tilt_max:g} rad) leaves no room for a trajectory "
            f"once tracking_error_orientation ({safety.tracking_error_orientation:g} rad) "
            f"is kept from it: {bad.detail}"
        )
    what = (
        f"the home position {home.position.tolist()} lies"
        if bad.detail.startswith("position")
        else "at the home pose a corner of the platform lies"
    )
    raise ConfigError(
        f"{where} {what} outside the workspace box (workspace_min/workspace_max, default "
        "the anchors' bounding box) shrunk by tracking_error_position "
        f"({safety.tracking_error_position:g} m), inside which trajectories must stay: "
        f"{bad.detail}"
    )
