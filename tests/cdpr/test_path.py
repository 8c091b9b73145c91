"""cdpr.path: paths read from JSON and G-code, made C2 with blends, and timed within the
cables' tensions by TOPP-RA (toppra); the timing held to the daemon's own validation and
to an independent LP (scipy's HiGHS) on the controller's model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import linprog

from cdpr.path import Path, PathPoint, parse_gcode, parse_path
from cdpr.path.geometry import BlendedPath
from cdpr.path.timing import Timing, time_path
from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.trajectory import Trajectory, TrajectoryError, TrajectoryLimits, Waypoint
from daemon.service.planner import path_timer, validate_as_the_daemon
from tests.daemon_stack import config_for
from tuning.scenarios import STANDARD_SET

Q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}


def pose(x: float, y: float, z: float, **options: float) -> dict:
    return {"position": [x, y, z], **options}


SQUARE = {  # home, then a blended square with a slow last side
    "poses": [
        pose(0.0, 0.0, 1.25, quaternion=Q),
        pose(0.3, 0.0, 1.25, blend=0.05),
        pose(0.3, 0.3, 1.35, blend=0.05),
        pose(0.0, 0.3, 1.25, speed=0.2),
    ]
}


# -- reading ------------------------------------------------------------------------------


def test_a_path_keeps_the_last_orientation_and_its_options() -> None:
    path = parse_path(SQUARE)
    assert len(path.points) == 4
    assert path.points[1].blend == 0.05 and path.points[1].speed is None
    assert path.points[3].speed == 0.2
    assert path.points[3].pose.quaternion_tuple == (1.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"poses": [pose(0, 0, 1)]}, r"poses\[0\]: missing key 'quaternion'"),
        ({"poses": [pose(0, 0, 1, quaternion=Q)]}, "two poses or more"),
        ({"poses": [pose(0, 0, 1, quaternion=Q), pose(1, 0, 1, speed=-1)]}, r"poses\[1\].speed"),
        ({"poses": [pose(0, 0, 1, quaternion=Q), pose(1, 0, 1, spd=1)]}, "unknown key"),
        ({"poses": [pose(0, 0, 1, quaternion=Q), pose(1, 0, math.nan)]}, "not a finite"),
        ({"version": 2, "poses": []}, "unsupported path schema version 2"),
        ({"poses": {}}, "poses: expected a list"),
    ],
)
def test_a_bad_path_is_refused_naming_the_pose_and_the_field(data: dict, message: str) -> None:
    with pytest.raises(TrajectoryError, match=message):
        parse_path(data)


def test_too_many_poses_are_refused() -> None:
    many = {"poses": [pose(0, 0, 1, quaternion=Q)] + [pose(k, 0, 1) for k in range(10)]}
    with pytest.raises(TrajectoryError, match="11 poses exceed the limit of 5"):
        parse_path(many, TrajectoryLimits(max_waypoints=5))


START = Pose([0.0, 0.0, 1.25], [1.0, 0.0, 0.0, 0.0])
PROGRAM = """%
; a square, in millimetres
G21 G90
N10 G1 X100 F6000 (100 mm/s)
G4 P500
G1 Y100
G91 G0 X-100 Z50
G20 G1 Y-1 F60
%
"""


def test_gcode_moves_in_metres_with_feeds_as_speed_caps_and_dwells() -> None:
    path = parse_gcode(PROGRAM, START, blend=0.01)
    positions = [p.pose.position.round(6).tolist() for p in path.points]
    assert positions == [
        [0.0, 0.0, 1.25],
        [0.1, 0.0, 1.25],
        [0.1, 0.1, 1.25],
        [0.0, 0.1, 1.3],
        [0.0, 0.1 - 0.0254, 1.3],
    ]
    speeds = [p.speed for p in path.points]
    assert speeds[:3] == [None, pytest.approx(0.1), pytest.approx(0.1)]
    assert speeds[3] is None  # G0: the trajectory's linear speed
    assert speeds[4] == pytest.approx(0.0254)  # 60 inches a minute
    assert path.points[1].dwell == 0.5 and path.points[2].blend == 0.01


@pytest.mark.parametrize(
    ("program", "message"),
    [
        ("G1 X1\nM3 S1000", "line 2: M3 is not supported"),
        ("X10", "line 1: a move before G0 or G1"),
        ("G2 X1 Y1 I1", "line 1: G2 is not supported"),
        ("G1 X1 F-3", "line 1: F-3 must be positive"),
        ("G1 X1e", "line 1: cannot read 'e'"),
        ("G21\nG90", "the program moves nowhere"),
        pytest.param(
            "G20 G91\n" + f"G1 X{'9' * 308}\n" * 100,
            "line 72: the move leaves the numbers' range",
            id="relative-moves-past-the-largest-float",
        ),
    ],
)
def test_gcode_outside_the_subset_is_refused_naming_its_line(program: str, message: str) -> None:
    with pytest.raises(TrajectoryError, match=message):
        parse_gcode(program, START)


# -- the geometric path -------------------------------------------------------------------


def test_the_blended_path_is_twice_continuously_differentiable() -> None:
    poses = [
        Pose([0.0, 0.0, 1.25], [1, 0, 0, 0]),
        Pose.from_rotvec([0.2, 0.0, 1.25], [0.0, 0.0, 0.2]),
        Pose([0.2, 0.2, 1.3], [1, 0, 0, 0]),
    ]
    path = BlendedPath(poses, [0.0, 0.03, 0.0], 0.41)
    s = np.linspace(0.0, path.s_end, 4001)
    q, d1, d2 = path(s), path(s, 1), path(s, 2)
    h = s[1] - s[0]
    assert np.abs(np.gradient(q, h, axis=0) - d1)[1:-1].max() < 1e-4
    assert np.abs(np.gradient(d1, h, axis=0) - d2)[2:-2].max() < 0.05 * np.abs(d2).max()
    for s0, _, _, _ in path._parts[1:]:  # no jump where a line and a blend meet
        before, after = path(s0 - 1e-9, 2), path(s0 + 1e-9, 2)
        assert np.abs(after - before).max() < 1e-4 and np.abs(path(s0, 1)).max() > 0
    # through the poses either side of the blend, within the blend's radius of the corner
    assert np.allclose(path(0.0)[:3], [0.0, 0.0, 1.25])
    assert np.allclose(path(path.s_end)[:3], [0.2, 0.2, 1.3])
    corner = np.concatenate([[0.2, 0.0, 1.25], 0.41 * np.array([0.0, 0.0, 0.2])])
    assert np.linalg.norm(q - corner, axis=1).min() < 0.03


# -- timing -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cia402():
    return config_for("cia402")


def lp_feasible(robot: Robot, w: Waypoint, margin: float) -> bool:
    """An independent LP (HiGHS): tensions within the controller's range less `margin`
    that give the wrench the controller's model needs at w (cdpr.wrench_check's
    quantities, the winches' drag with its friction)."""
    Lam, c, M, mu = robot.model_terms(w.pose, w.twist)
    tau = M @ w.accel + mu
    f0 = robot.m0 * (Lam @ w.accel + c)
    g = f0 + robot.drag(Lam @ w.twist)
    lo = np.maximum(robot.t_min, g - robot.force_max) + margin
    hi = g + robot.force_max - margin
    if np.any(lo > hi):
        return False
    result = linprog(
        np.zeros(robot.n_cables),
        A_eq=Lam.T,
        b_eq=Lam.T @ f0 - tau,
        bounds=list(zip(lo, hi, strict=True)),
        method="highs",
    )
    return result.status == 0


def samples(trajectory: Trajectory, count: int) -> list[Waypoint]:
    times = np.linspace(trajectory.start_time, trajectory.end_time, count)
    out = []
    for t in times:
        ref = trajectory.sample(float(t))
        out.append(Waypoint(float(t), ref.pose, ref.twist, ref.accel))
    return out


def test_a_timed_path_passes_the_daemons_validation_and_an_independent_lp(cia402) -> None:
    robot = cia402.robot
    trajectory = time_path(parse_path(SQUARE), robot, cia402.trajectory, Timing(margin=5.0))
    validate_as_the_daemon(trajectory, cia402)
    for w in samples(trajectory, 300):
        assert lp_feasible(robot, w, margin=4.0), f"t={w.t:.3f}: no tensions"
    # it goes where the path goes: the unblended ends exactly, the corners within the blend
    start, end = trajectory.sample(trajectory.start_time), trajectory.sample(trajectory.end_time)
    assert np.allclose(start.pose.position, [0.0, 0.0, 1.25])
    assert np.allclose(end.pose.position, [0.0, 0.3, 1.25])
    track = np.array([w.pose.position for w in samples(trajectory, 2000)])
    assert np.linalg.norm(track - [0.3, 0.0, 1.25], axis=1).min() < 0.05


def test_a_long_blended_path_stays_within_the_acceleration_limit(cia402) -> None:
    """A climbing square spiral of 40 blended corners: the trajectory between TOPP-RA's
    knots stays within linear_accel and the daemon's validation passes (each knot once
    took one interval's acceleration and the quintic overshot the limit by 5 %)."""
    poses = [pose(0.0, 0.0, 1.0, quaternion=Q)]
    for k in range(1, 40):
        x, y = 0.25 * ((k % 4) in (1, 2)), 0.25 * ((k % 4) >= 2)
        poses.append(pose(x, y, 1.0 + 0.005 * k, blend=0.03))
    trajectory = time_path(parse_path({"poses": poses}), cia402.robot, cia402.trajectory)
    accels = [np.linalg.norm(w.accel[:3]) for w in samples(trajectory, 20_000)]
    assert max(accels) <= cia402.trajectory.linear_accel
    validate_as_the_daemon(trajectory, cia402)


@pytest.mark.parametrize("name", ["figure_eight", "vertical_lift", "edge_move"])
def test_the_standard_paths_timed_as_the_daemon_times_them_pass_its_validation(
    cia402, name: str
) -> None:
    """The standard trajectories' poses without their times, corners blended 5 cm, timed
    by the daemon's own path timer: its validation accepts them.  At the full limits the
    quintics between grid points went 0.1-0.3 % over the speed limit and 4-15 % over the
    acceleration limit on blends (refused: the daemon would have refused its own timing),
    and the figure-eight's close poses put grid points less than a trajectory's shortest
    segment apart (a times_increasing error)."""
    poses = [w.pose for w in STANDARD_SET[name](cia402.robot).waypoints]
    blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
    path = Path(tuple(PathPoint(p, blend=b) for p, b in zip(poses, blends, strict=True)))
    trajectory = path_timer(cia402)(path)
    validate_as_the_daemon(trajectory, cia402)
    speeds = [np.linalg.norm(w.twist[:3]) for w in samples(trajectory, 20_000)]
    assert max(speeds) <= cia402.trajectory.linear_speed


@pytest.mark.parametrize(("jerk", "reached"), [(None, 0.95), (50.0, 0.8)], ids=["free", "jerk"])
def test_the_speed_cap_holds_on_its_segment_and_is_reached(
    cia402, jerk: float | None, reached: float
) -> None:
    """The last side's 0.2 m/s cap holds, and the time-optimal timing reaches it.  With
    the jerk bounded it is reached at 0.85 of it: the averaged time law enters the slow
    side faster than the cap, and the motion is slowed down uniformly to bring it back
    (cdpr.path.timing), the capped side with it."""
    angular = None if jerk is None else 100.0
    limits = cia402.trajectory.model_copy(update={"linear_jerk": jerk, "angular_jerk": angular})
    trajectory = time_path(parse_path(SQUARE), cia402.robot, limits)
    on_last = [w for w in samples(trajectory, 3000) if w.pose.position[0] < 0.25 - 1e-3]
    on_last = [w for w in on_last if w.pose.position[1] > 0.29]
    speeds = [np.linalg.norm(w.twist[:3]) for w in on_last]
    assert max(speeds) <= 0.2 * 1.01
    assert max(speeds) > 0.2 * reached


def test_the_timing_is_at_the_tensions_limit_where_they_bind(cia402) -> None:
    """With the kinematic limits lifted, a fast vertical lift is limited by the cables
    alone: at every grid point the timing keeps the tensions in range (the LP, within
    0.5 N), and the same path 4 % faster does not: the timing is time-optimal within
    them."""
    robot = cia402.robot
    limits = TrajectoryLimits(linear_speed=20.0, linear_accel=200.0, angular_accel=500.0)
    lift = Path(
        (
            PathPoint(Pose([0.0, 0.0, 1.0], [1, 0, 0, 0])),
            PathPoint(Pose([0.0, 0.0, 1.6], [1, 0, 0, 0])),
        )
    )
    trajectory = time_path(lift, robot, limits, Timing(margin=0.0, step=0.005))
    knots = trajectory.knots
    assert all(lp_feasible(robot, w, margin=-0.5) for w in knots)
    faster = [Waypoint(w.t / 1.04, w.pose, w.twist * 1.04, w.accel * 1.04**2) for w in knots]
    assert not all(lp_feasible(robot, w, margin=-0.5) for w in faster)


def test_a_dwell_rests_the_platform_there(cia402) -> None:
    data = {
        "poses": [
            pose(0, 0, 1.25, quaternion=Q),
            pose(0.2, 0, 1.25, dwell=0.5),
            pose(0.2, 0.2, 1.25),
        ]
    }
    trajectory = time_path(parse_path(data), cia402.robot, cia402.trajectory)
    there = [0.2, 0.0, 1.25]
    rests = [w.t for w in trajectory.knots if np.allclose(w.pose.position, there, atol=1e-12)]
    assert len(rests) == 2 and rests[1] - rests[0] == pytest.approx(0.5)
    during = [w for w in samples(trajectory, 4000) if rests[0] < w.t < rests[1]]
    assert during and all(np.allclose(w.pose.position, there, atol=1e-12) for w in during)
    assert all(np.allclose(w.twist, 0.0) for w in during)


def test_a_path_the_cables_cannot_hold_is_refused_naming_where(cia402) -> None:
    """Up to a point beside an anchor: no tension distribution holds the platform there."""
    anchor = cia402.robot.geometry.anchors[0]
    data = {"poses": [pose(0, 0, 1.25, quaternion=Q), pose(*(0.9 * anchor + [0, 0, -0.05]))]}
    with pytest.raises(TrajectoryError, match=r"path_infeasible: motion 0: no speed holds"):
        time_path(parse_path(data), cia402.robot, cia402.trajectory)
