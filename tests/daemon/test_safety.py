"""The safety state machine and each brake trigger of the monitor (DESIGN §9), as pure logic."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr.controller import ParallelController
from daemon.config import load_config
from daemon.service.safety import (
    STALE_HISTORY,
    Fault,
    SafetyMonitor,
    SafetyState,
    StateMachine,
    TransitionError,
    Trigger,
    missed_text,
)
from drivers.base import DriveState, Feedback, NodeStatus

CONFIG = Path(__file__).resolve().parents[2] / "config" / "reference8-cia402.yaml"


@pytest.fixture(scope="module")
def config():
    return load_config(CONFIG)


def test_normal_life_cycle_and_reset_needs_faults_gone() -> None:
    sm = StateMachine()
    assert sm.state is SafetyState.INIT and not sm.moving
    with pytest.raises(TransitionError, match="cannot enable while init"):
        sm.go("enable")
    sm.go("started")
    sm.go("enable")
    assert sm.state is SafetyState.HOLD and sm.moving
    sm.go("track")
    sm.go("finish")
    assert sm.state is SafetyState.HOLD
    fault = Fault(Trigger.TRACKING_ERROR, "position error 30 mm")
    assert sm.brake(fault)
    assert not sm.brake(Fault(Trigger.NAN, "later"))  # the first fault is kept
    assert sm.state is SafetyState.BRAKED and sm.fault is fault
    with pytest.raises(TransitionError, match="faults persist: drive 3 hot"):
        sm.reset([Fault(Trigger.DRIVE_FAULT, "drive 3 hot")])
    assert sm.state is SafetyState.BRAKED
    sm.reset([])
    assert sm.state is SafetyState.IDLE and sm.fault is None
    with pytest.raises(TransitionError, match="cannot track while idle"):
        sm.go("track")


def test_fault_line_names_trigger_and_values() -> None:
    line = Fault(Trigger.STALE_FEEDBACK, "drive 2: no feedback for 3 cycles").line()
    assert line == "BRAKE [stale_feedback] drive 2: no feedback for 3 cycles"


def _healthy(n: int, lengths: list[float]) -> tuple[list[Feedback], list[NodeStatus]]:
    feedback = [Feedback(length=ell, rate=0.0, stamp=1.0, count=5) for ell in lengths]
    status = [NodeStatus(state=DriveState.ENABLED, heartbeat_stamp=1.0) for _ in range(n)]
    return feedback, status


def test_drive_checks(config) -> None:
    robot = config.robot
    monitor = SafetyMonitor(config)
    lengths = robot.cable_lengths(robot.home).tolist()
    feedback, status = _healthy(robot.n_cables, lengths)
    assert monitor.check_drives(feedback, status, now=1.1) == []

    status[2] = NodeStatus(DriveState.FAULT, "overcurrent", 0x2310, heartbeat_stamp=1.0)
    (fault,) = monitor.check_drives(feedback, status, now=1.1)
    assert fault.trigger is Trigger.DRIVE_FAULT and "drive 2" in fault.message
    assert "0x2310" in fault.message and "overcurrent" in fault.message

    _, status = _healthy(robot.n_cables, lengths)
    # every drive is 500 ms silent; one fault per drive, the first names drive 0
    faults = monitor.check_drives(feedback, status, now=1.5)
    assert len(faults) == robot.n_cables
    assert faults[0].trigger is Trigger.HEARTBEAT_LOST and "500 ms ago" in faults[0].message

    feedback[4] = Feedback(length=math.nan, rate=0.0, stamp=1.0, count=6)
    faults = monitor.check_drives(feedback, status, now=1.1)
    assert [f.trigger for f in faults] == [Trigger.NAN]

    feedback, _ = _healthy(robot.n_cables, lengths)
    feedback[1] = Feedback(length=robot.length_max[1] + 0.01, rate=0.0, stamp=1.0, count=6)
    (fault,) = monitor.check_drives(feedback, status, now=1.1)
    assert fault.trigger is Trigger.LENGTH_LIMIT and "cable 1" in fault.message


def test_stale_feedback_counts_consecutive_cycles(config) -> None:
    monitor = SafetyMonitor(config)
    n = config.robot.n_cables
    limit = config.safety.stale_cycles
    fresh = [True] * n
    stale = [True] * n
    stale[5] = False
    for _ in range(limit - 1):
        assert monitor.check_freshness(stale) is None
    assert monitor.check_freshness(fresh) is None  # a fresh cycle restarts the count
    for _ in range(limit - 1):
        assert monitor.check_freshness(stale) is None
    fault = monitor.check_freshness(stale)
    assert fault is not None and fault.trigger is Trigger.STALE_FEEDBACK
    assert f"drive 5: no feedback for {limit} consecutive cycles" in fault.message
    assert "too" not in fault.message  # the only one silent

    together = SafetyMonitor(config)  # several silent: the fault says which
    for _ in range(limit):
        fault = together.check_freshness([k not in (2, 6, 7) for k in range(n)])
    assert fault is not None
    assert fault.message.startswith("drive 2: no feedback") and "drives 6, 7 too" in fault.message


def test_a_brake_names_the_drives_that_missed_feedback_within_the_last_second(config) -> None:
    """missed_feedback: per drive, the cycles of the last STALE_HISTORY s it missed its
    feedback in (an isolated miss too, far below stale_cycles); older ones age out."""
    monitor = SafetyMonitor(config)
    n, window = config.robot.n_cables, round(config.controller.rate_hz * STALE_HISTORY)
    assert monitor.missed_feedback() == []
    monitor.check_freshness([k != 3 for k in range(n)])
    for _ in range(5):
        monitor.check_freshness([True] * n)
    monitor.check_freshness([k not in (3, 6) for k in range(n)])
    assert monitor.missed_feedback() == [{"drive": 3, "cycles": 2}, {"drive": 6, "cycles": 1}]
    assert missed_text(monitor.missed_feedback()) == (
        "; feedback missed within 1 s: drive 3 (2 cycles), drive 6 (1 cycles)"
    )
    for _ in range(window - 6):  # the first miss is now a second old
        monitor.check_freshness([True] * n)
    assert monitor.missed_feedback() == [{"drive": 3, "cycles": 1}, {"drive": 6, "cycles": 1}]
    for _ in range(5):
        monitor.check_freshness([True] * n)
    assert len(monitor.missed_feedback()) == 2
    monitor.check_freshness([True] * n)  # and the second
    assert monitor.missed_feedback() == []
    assert missed_text([]) == ""


def test_bus_errors_within_one_second(config) -> None:
    monitor = SafetyMonitor(config)
    limit = config.safety.bus_errors_max
    for i in range(limit):
        assert monitor.bus_error(10.0 + i * 0.01, "error frame") is None
    assert monitor.bus_error(12.0, "error frame") is None  # the old ones aged out
    off = SafetyMonitor(config)
    fault = off.bus_error(0.0, "error frame 0x40", bus_off=True)
    assert fault is not None and fault.trigger is Trigger.BUS_ERROR
    assert "bus-off" in fault.message and "0x40" in fault.message
    assert off.check_bus(0.9) == fault and off.check_bus(1.1) is None


def test_the_bus_condition_is_the_trigger_not_any_recent_error(config) -> None:
    """One error frame is no fault (the daemon braked on it, and refused a reset for a
    second after each sporadic one); more than bus_errors_max within a second is, for as
    long as they stay within the second."""
    monitor = SafetyMonitor(config)
    limit = config.safety.bus_errors_max
    assert monitor.bus_error(5.0, "error frame 0x88") is None
    assert monitor.check_bus(5.002) is None
    for i in range(limit - 1):
        assert monitor.bus_error(5.1 + i * 0.1, "error frame 0x88") is None
    assert monitor.check_bus(5.9) is None  # limit errors within the second: still fine
    fault = monitor.bus_error(5.95, "error frame 0x88")
    assert fault is not None and fault.trigger is Trigger.BUS_ERROR
    assert f"{limit + 1} bus errors in the last second (limit {limit})" in fault.message
    assert monitor.check_bus(6.0) is not None
    assert monitor.check_bus(6.15) is None  # two have aged out: at the limit again
    assert monitor.bus_error(6.2, "error frame 0x88") is None  # sporadic: still no fault


def test_a_lost_bus_is_a_fault_for_good(config) -> None:
    monitor = SafetyMonitor(config)
    lost = monitor.bus_lost("send failed: Network is down")
    assert lost.trigger is Trigger.BUS_LOST and "send failed: Network is down" in lost.message
    assert monitor.check_bus(1e6) == lost
    assert monitor.bus_lost("something later") == lost  # the first cause stays


def test_a_fault_the_daemon_exits_for_supersedes_the_one_on_record() -> None:
    sm = StateMachine()
    sm.go("started")
    stale = Fault(Trigger.STALE_FEEDBACK, "drive 0: no feedback")
    lost = Fault(Trigger.BUS_LOST, "CAN bus lost")
    assert sm.brake(stale)
    assert not sm.brake(lost) and sm.fault == stale  # the first fault stays ...
    assert sm.brake(lost, supersede=True) and sm.fault == lost  # ... unless superseded
    assert not sm.brake(lost, supersede=True)
    assert sm.state is SafetyState.BRAKED


def _output_at(config, pose, reference=None):
    """A real controller output at `pose` holding `reference` (default: the same pose)."""
    robot = config.robot
    ctrl = ParallelController(robot, config.controller)
    ctrl.reset(reference or pose)
    tensions = ctrl.tension.limits.t_ref
    lengths = robot.drum_lengths(robot.cable_lengths(pose), tensions)
    return ctrl.step(0.0, lengths, np.zeros(robot.n_cables))


def test_output_checks(config) -> None:
    from cdpr import Pose

    robot = config.robot
    monitor = SafetyMonitor(config)
    home = robot.home
    assert monitor.check_output(_output_at(config, home)) is None

    off = Pose(home.position + np.array([0.05, 0.0, 0.0]), home.quaternion)
    fault = monitor.check_output(_output_at(config, off, reference=home))
    assert fault is not None and fault.trigger is Trigger.TRACKING_ERROR
    assert "position error" in fault.message and "exceeds 20.00 mm" in fault.message

    half = math.sin(0.35)
    tilted = Pose(home.position, (math.cos(0.35), half, 0.0, 0.0))  # 40 deg about x
    fault = monitor.check_output(_output_at(config, tilted))
    assert fault is not None and fault.trigger in (Trigger.POSE_LIMIT, Trigger.OUT_OF_WORKSPACE)

    out = _output_at(config, home)
    bad = out._replace(commands=np.full(robot.n_cables, np.nan))
    assert monitor.check_output(bad).trigger is Trigger.NAN
    infeasible = out._replace(feasible=False, reason="wrench not in W: cable 3 t >= 20 N")
    fault = monitor.check_output(infeasible)
    assert fault.trigger is Trigger.OUT_OF_WORKSPACE and "cable 3" in fault.message
    lost = out._replace(feasible=False, reason="forward kinematics: residual 5 mm")
    assert monitor.check_output(lost).trigger is Trigger.FK_RESIDUAL


# a box tight enough that random trajectories run the platform's corners along its
# faces (the body is 0.4 x 0.4 x 0.6 m), and the tilt limit
FENCED = {"workspace_min": [-0.5, -0.5, 0.6], "workspace_max": [0.5, 0.5, 1.9], "tilt_max": 0.4}


@pytest.fixture(scope="module")
def fenced():
    return load_config(CONFIG, lambda data: data["safety"].update(FENCED))


def _outward(reference, home, e_p: float, e_r: float):
    """The measured pose that tracks `reference` within (e_p, e_r) and is the worst for
    the pose limits: out through the nearest face of the box, turned on away from home."""
    from cdpr import Pose, liediff
    from cdpr.so3 import exp_so3

    lo, hi = np.array(FENCED["workspace_min"]), np.array(FENCED["workspace_max"])
    p = reference.position
    face = int(np.argmin(np.minimum(p - lo, hi - p)))
    out = np.zeros(3)
    out[face] = -e_p if p[face] - lo[face] < hi[face] - p[face] else e_p
    rv = liediff(home, reference)[3:]
    angle = float(np.linalg.norm(rv))
    turn = rv / angle * e_r if angle > 1e-9 else np.array([e_r, 0.0, 0.0])
    return Pose.from_matrix(p + out, exp_so3(turn) @ reference.rotation)


# of the way across the limits: on a face (but for rounding) or anywhere
fraction = st.one_of(st.just(1e-7), st.just(1.0 - 1e-7), st.floats(0.0, 1.0))


@settings(max_examples=60)
@given(
    corners=st.lists(st.tuples(fraction, fraction, fraction), min_size=2, max_size=4),
    turns=st.lists(st.tuples(fraction, st.floats(-math.pi, math.pi)), min_size=4, max_size=4),
    gaps=st.lists(st.floats(1.5, 3.0), min_size=3, max_size=3),
    stops=st.booleans(),
)
def test_an_accepted_trajectory_never_trips_the_pose_limits(
    fenced, corners, turns, gaps, stops
) -> None:
    """Validated against the config's reference limits, a trajectory followed exactly, or
    by a measured pose as far out as the tracking-error bounds allow, passes every
    runtime output check, sampled at every control cycle.  With `stops` the waypoints are
    at rest (straight segments along the faces), else the spline may overshoot them.
    The waypoints' reference points lie where the unturned body touches the box."""
    from cdpr import Pose, liediff
    from cdpr.trajectory import Trajectory, TrajectoryError, Waypoint, validate

    config = fenced
    limits = config.reference_limits
    extent = np.abs(config.robot.body.points).max(axis=0)
    lo, hi = np.array(limits.lower) + extent, np.array(limits.upper) - extent
    home = config.robot.home
    times = np.cumsum([0.0, *gaps])
    waypoints = []
    for t, corner, (share, azimuth) in zip(times, corners, turns, strict=False):
        axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.3])
        rotvec = axis / np.linalg.norm(axis) * share * limits.tilt_max
        pose = Pose.from_rotvec(lo + np.array(corner) * (hi - lo), rotvec)
        rest = np.zeros(6) if stops else None
        waypoints.append(Waypoint(t, pose, rest, rest))
    trajectory = Trajectory(waypoints)
    try:
        validate(trajectory, config.robot, config.trajectory, pose_limits=limits)
    except TrajectoryError as exc:
        assert exc.limit in (
            "workspace_min",
            "workspace_max",
            "tilt_max",
            "linear_speed",
            "angular_speed",
            "linear_accel",
            "angular_accel",
            "cable_length",
        )
        return
    monitor = SafetyMonitor(config)
    base = _output_at(config, home)
    e_p = config.safety.tracking_error_position * (1.0 - 1e-9)
    e_r = config.safety.tracking_error_orientation * (1.0 - 1e-9)
    period = 1.0 / config.controller.rate_hz
    for t in np.arange(trajectory.start_time, trajectory.end_time + period, period):
        reference = trajectory.sample(float(t)).pose
        for measured in (reference, _outward(reference, home, e_p, e_r)):
            output = base._replace(pose=measured, theta_d=liediff(reference, measured))
            assert monitor.check_output(output) is None, (t, measured)


def test_the_runtime_check_brakes_just_outside_what_validation_allows(fenced) -> None:
    """The margins are not more than needed: a corner at the edge of what validation
    accepts, moved out by its whole margin (tracking_error_position + its distance from
    p x tracking_error_orientation, the most a tracking error may move it) and a little
    more, trips the runtime pose check, naming the corner."""
    from cdpr import Pose, liediff

    config = fenced
    limits = config.reference_limits
    body = config.robot.body
    monitor = SafetyMonitor(config)
    base = _output_at(config, config.robot.home)
    corner = int(np.argmin(body.points[:, 0]))  # a corner on the -x side
    margin = limits.margin[0] + limits.turn * float(body.radii[corner])
    x = limits.lower[0] + limits.turn * float(body.radii[corner]) - body.points[corner, 0]
    edge = Pose((x, 0.0, 1.3), (1.0, 0.0, 0.0, 0.0))
    assert limits.violation(edge) is None
    over = Pose(edge.position - np.array([margin + 1e-4, 0.0, 0.0]), edge.quaternion)
    fault = monitor.check_output(base._replace(pose=over, theta_d=liediff(edge, over)))
    assert fault.trigger is Trigger.POSE_LIMIT and f"platform corner {corner} (" in fault.message
    assert "at x = -0.5001 m outside [-0.5000, 0.5000] m" in fault.message
    within = Pose(edge.position - np.array([margin - 1e-4, 0.0, 0.0]), edge.quaternion)
    output = base._replace(pose=within, theta_d=liediff(edge, within))
    assert monitor.pose_limits.violation(within) is None and output.feasible


def test_the_states_that_follow_plans_are_hold_and_tracking() -> None:
    """daemon.service.api.MOVING (what the interfaces may know) is SafetyState's."""
    from daemon.service.api import MOVING

    assert (SafetyState.HOLD.value, SafetyState.TRACKING.value) == MOVING
