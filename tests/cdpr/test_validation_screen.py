"""The trajectory validation's batch screen: the compiled model (cdpr.compiled_model)
against the numpy reference, the wrench screen against an independent LP (scipy's
HiGHS) and the scalar check, the batch sampling and the pose and length screens against
their scalar forms, and a screened validation against one that checks every sample one
by one: the same verdicts, the same messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdpr import Pose, Robot, reference
from cdpr.body import Environment, Plane
from cdpr.compiled_model import platform_rows
from cdpr.control_spec import ControllerSpec
from cdpr.controller import tension_solver
from cdpr.kinematics import cable_rows
from cdpr.pose_limits import PoseLimits
from cdpr.so3 import quats_to_matrices
from cdpr.trajectory import (
    LengthLimits,
    Samples,
    Trajectory,
    TrajectoryError,
    Waypoint,
    validate,
)
from cdpr.trajectory.core import Curve
from cdpr.wrench_check import ModelWrenchCheck, wrench_check
from daemon.config import load_config
from daemon.service.planner import validate_as_the_daemon
from tests.cdpr.test_path import lp_feasible

CONFIGS = Path(__file__).resolve().parents[2] / "config"
SPREAD = 8.0  # of the random twists and accels: about half the states lie outside W


def random_samples(robot: Robot, count: int, seed: int, scale: float = 1.0) -> Samples:
    """Poses within 0.15 m and ~0.1 rad of home, twists and accels of `scale`."""
    rng = np.random.default_rng(seed)
    positions = robot.home.position + rng.normal(scale=0.08, size=(count, 3))
    quats = np.array(robot.home.quaternion) + rng.normal(scale=0.03, size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1)[:, None]
    twists = rng.normal(scale=0.3 * scale, size=(count, 6))
    accels = rng.normal(scale=2.0 * scale, size=(count, 6))
    times = np.arange(count, dtype=float)
    return Samples(times, positions, quats, quats_to_matrices(quats), twists, accels)


def test_the_compiled_model_is_the_references(robot: Robot) -> None:
    """Lambda, c, the lengths and M, mu (with the drums' m0) at random states, with and
    without pulleys (the `robot` fixture's two robots)."""
    s = random_samples(robot, 200, seed=1)
    Lam, c, M, mu = reference.model_terms(robot, s.positions, s.rotations, s.twists)
    lengths = reference.cable_segments(robot, s.positions, s.rotations)[0]
    cables, platform = robot.geometry.rows, robot.platform.rows
    n = robot.n_cables
    table, length, rows = np.empty((n, 7)), np.empty(n), np.empty((6, 7))
    for i in range(len(s.times)):
        cable_rows(cables, s.positions[i], s.rotations[i], s.twists[i], table, length)
        platform_rows(platform, s.rotations[i], s.twists[i], rows)
        np.testing.assert_allclose(table[:, :6], Lam[i], atol=1e-12)
        np.testing.assert_allclose(table[:, 6], c[i], atol=1e-12)
        np.testing.assert_allclose(length, lengths[i], atol=1e-12)
        weighted = Lam[i].T * robot.m0
        np.testing.assert_allclose(rows[:, :6] + weighted @ Lam[i], M[i], atol=1e-10)
        np.testing.assert_allclose(rows[:, 6] + weighted @ c[i], mu[i], atol=1e-10)


def lp_in_w(robot: Robot, s: Samples, i: int, margin: float = 0.0) -> bool:
    """tests.cdpr.test_path's independent LP (HiGHS) at sample i."""
    pose = Pose(s.positions[i], s.quaternions[i])
    return lp_feasible(robot, Waypoint(0.0, pose, s.twists[i], s.accels[i]), margin)


@pytest.mark.parametrize("friction", [0.0, 8.0])
def test_a_cleared_wrench_is_in_w_by_an_independent_lp_and_by_the_check(
    robot: Robot, friction: float
) -> None:
    """Never clear outside W; clear for most states well inside it (else the screen buys
    nothing); the Jacobians and lengths it hands on are the model's."""
    data = robot.spec.model_dump()
    data["actuator"]["friction"] = friction or None  # the drag's Coulomb part, a tanh
    robot = Robot.from_dict(data)
    check = wrench_check(robot, tension_solver(robot, ControllerSpec()))
    s = random_samples(robot, 300, seed=2, scale=SPREAD)
    screened = check.screen(s)
    clear = screened.clear.tolist()
    for i, cleared in enumerate(clear):
        pose = Pose(s.positions[i], s.quaternions[i])
        if cleared:
            assert lp_in_w(robot, s, i), f"sample {i}: cleared, but no tensions exist"
            assert check(pose, s.twists[i], s.accels[i]) is None
    inside = [i for i in range(len(clear)) if lp_in_w(robot, s, i, margin=10.0)]
    assert 0 < len(inside) < len(clear)  # the set spans both sides of W's boundary
    assert sum(clear[i] for i in inside) >= 0.8 * len(inside)
    np.testing.assert_allclose(
        screened.jacobians, reference.jacobians(robot, s.positions, s.rotations), atol=1e-12
    )
    lengths = reference.cable_segments(robot, s.positions, s.rotations)[0]
    np.testing.assert_allclose(screened.lengths, lengths, atol=1e-12)


def test_nothing_non_finite_or_singular_is_cleared(reference8: Robot) -> None:
    check = wrench_check(reference8, tension_solver(reference8, ControllerSpec()))
    s = random_samples(reference8, 4, seed=3)
    s.accels[1, 2] = np.nan
    s.twists[2, 0] = np.inf
    s.positions[3] = reference8.geometry.anchors[0]  # cable 0 of zero length
    with np.errstate(all="ignore"):
        clear = check.screen(s).clear
    assert clear.tolist() == [True, False, False, False]


def blended(robot: Robot) -> Trajectory:
    """A trajectory shifted in time and joined by a blend segment from a moving state."""
    home = robot.home.position
    turned = (0.999, 0.0, 0.0, 0.0447)
    rest = np.zeros(6)
    base = Trajectory(
        [
            Waypoint(0.0, Pose(home)),
            Waypoint(1.0, Pose(home + np.array([0.05, 0.02, 0.0]), turned)),
            Waypoint(2.5, Pose(home + np.array([0.1, 0.0, -0.03])), rest, rest),
        ]
    ).shifted(3.0)
    moving = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.01])
    lead = Waypoint(2.6, Pose(home + np.array([-0.01, 0.0, 0.0])), moving, rest)
    return base.after_blend([lead], 0.0)


def test_samples_in_a_batch_are_the_samples_one_by_one(reference8: Robot) -> None:
    """Before the start, in the blend, on the segments (and on their knots) and after the
    end, turns within and beyond the rotation rates' series; the curve as built and as
    carried between processes (packed, unpacked)."""
    home = reference8.home.position
    turn = Pose.from_rotvec(home, np.array([0.3, -0.5, 1.1]))  # 1.25 rad: past the series
    turning = Trajectory([Waypoint(0.0, Pose(home)), Waypoint(2.0, turn)])
    for trajectory in (blended(reference8), turning):
        curve = trajectory.curve
        knots = [w.t for w in trajectory.waypoints]
        ends = (curve.start_time, curve.end_time + 0.5)
        times = np.concatenate([[curve.start_time - 1.0], np.linspace(*ends, 401), knots])
        unpacked = Curve.unpacked(*curve.packed())
        for source in (curve, unpacked):
            batch = source.sample_many(times)
            for i, t in enumerate(times.tolist()):
                one = curve.sample(t)
                np.testing.assert_allclose(batch.positions[i], one.pose.position, atol=1e-14)
                np.testing.assert_allclose(batch.rotations[i], one.pose.rotation, atol=1e-14)
                np.testing.assert_allclose(batch.twists[i], one.twist, atol=1e-13)
                np.testing.assert_allclose(batch.accels[i], one.accel, atol=1e-12)


def test_the_pose_and_length_screens_clear_only_what_the_checks_pass(reference8: Robot) -> None:
    """Poses near the box's faces, the tilt limit and an environment's plane: a pose the
    screen clears passes the scalar check (and the screen clears most of those that
    pass)."""
    anchors = reference8.geometry.anchors
    environment = Environment(
        (Plane("wall", (-1.0, 0.0, 0.0), -0.4),),  # free side x <= 0.4
        (),  # a box in the frame is near every pose's cables: the scalar check decides
        tuple(tuple(a) for a in anchors.tolist()),
    )
    home = reference8.home
    rng = np.random.default_rng(4)
    count = 2000
    positions = home.position + rng.uniform(-0.9, 0.9, size=(count, 3))
    quats = np.array(home.quaternion) + rng.normal(scale=0.1, size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1)[:, None]
    box = (tuple(anchors.min(axis=0).tolist()), tuple(anchors.max(axis=0).tolist()))
    for limits in (
        PoseLimits(*box, home.quaternion_tuple, 0.3),
        PoseLimits(*box, home.quaternion_tuple, 0.3, body=reference8.body, turn=0.1),
        PoseLimits(*box, home.quaternion_tuple, 0.3, body=reference8.body, environment=environment),
    ):
        clear = limits.clear(positions, quats)
        poses = [Pose(p, q) for p, q in zip(positions, quats, strict=True)]
        passes = [limits.violation(pose) is None for pose in poses]
        assert not np.any(clear & ~np.array(passes))
        assert 0.5 * sum(passes) <= clear.sum() <= sum(passes)
    lengths = reference.cable_segments(reference8, positions, quats_to_matrices(quats))[0]
    bounds = LengthLimits((1.6,) * 8, (3.3,) * 8)  # the lengths here: 1.25 to 3.5 m
    clear = bounds.clear(lengths)
    passes = np.array([bounds.violation(row.tolist()) is None for row in lengths])
    assert not np.any(clear & ~passes) and 0 < clear.sum() == passes.sum()


class OneByOne:
    """The daemon's wrench check without its batch screen: every sample checked alone."""

    def __init__(self, check: ModelWrenchCheck) -> None:
        self.check = check

    def __call__(self, pose: Pose, twist: np.ndarray, accel: np.ndarray) -> str | None:
        return self.check(pose, twist, accel)


@pytest.fixture(scope="module")
def cia402():
    return load_config(CONFIGS / "reference8-cia402.yaml")


def verdict(trajectory: Trajectory, config, screened: bool) -> str:
    """What validation says, with the config's limits but the jerk's (checked before any
    sample, it would refuse every case here first)."""
    check = wrench_check(config.robot, tension_solver(config.robot, config.controller))
    limits = config.trajectory.model_copy(update={"linear_jerk": None, "angular_jerk": None})
    try:
        validate(
            trajectory,
            config.robot,
            limits,
            check if screened else OneByOne(check),
            config.reference_limits,
            config.reference_lengths,
            workspace=config.workspace_check,
        )
    except TrajectoryError as exc:
        return str(exc)
    return "accepted"


def test_a_screened_validation_names_what_a_sample_by_sample_one_names(cia402) -> None:
    """Accepted, or refused for the same limit at the same instant with the same message:
    a speed, an acceleration, the wrench set, the workspace margin (straight moves between
    two points, from a search of random ones)."""
    home = cia402.robot.home.position

    def move(start: list[float], end: list[float], seconds: float) -> Trajectory:
        a, b = Pose(home + np.array(start)), Pose(home + np.array(end))
        return Trajectory([Waypoint(0.0, a), Waypoint(seconds, b)])

    cases = {
        "accepted": move([0.482, 0.391, 0.383], [-0.289, -0.949, 0.459], 3.174),
        "linear_speed": move([0.245, -0.421, -0.299], [1.015, -0.709, 0.233], 1.144),
        "linear_accel": move([0.768, -0.437, -0.635], [0.586, -0.063, -0.857], 0.554),
        "wrench_set": move([0.597, -0.843, 0.785], [0.108, -0.521, -0.228], 1.237),
        "workspace.margin": move([0.336, 1.111, -0.187], [1.182, 0.0, -0.222], 3.13),
    }
    for expected, trajectory in cases.items():
        one_by_one = verdict(trajectory, cia402, screened=False)
        assert verdict(trajectory, cia402, screened=True) == one_by_one
        assert expected in one_by_one, (expected, one_by_one)


def test_a_long_trajectory_is_validated_in_batches_as_the_daemon_does(cia402) -> None:
    """1,000 waypoints (100 s, ~11,000 samples): accepted, and in far fewer steps than
    samples (a step a batch phase, each a fraction of a millisecond)."""
    from cdpr.trajectory import validation_steps

    angle = 2.0 * np.pi * np.arange(1000) * 0.1 / 60.0
    home = cia402.robot.home.position
    waypoints = [
        Waypoint(0.1 * k, Pose(home + 0.03 * np.array([np.sin(a), 1.0 - np.cos(a), 0.0])))
        for k, a in enumerate(angle)
    ]
    waypoints[-1] = Waypoint(waypoints[-1].t, waypoints[-1].pose, np.zeros(6), np.zeros(6))
    trajectory = Trajectory(waypoints)
    validate_as_the_daemon(trajectory, cia402)
    check = wrench_check(cia402.robot, tension_solver(cia402.robot, cia402.controller))
    steps = list(
        validation_steps(
            trajectory,
            cia402.robot,
            cia402.trajectory,
            check,
            cia402.reference_limits,
            cia402.reference_lengths,
            workspace=cia402.workspace_check,
        )
    )
    assert steps[-1] == trajectory.end_time
    assert len(steps) < 1000 + 200  # the waypoints' pose checks, then ~3 per 256 samples
