"""The helpers and restructured hot paths of the speed work hold the same maths as the
plain forms they replace (no timing here: bench/ prints the figures)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.linalg.lapack import dpotrs

from cdpr import Pose, Robot, liediff, reference, retract
from cdpr.description import load_yaml
from cdpr.pose import liediff6
from cdpr.single_actuator import pid
from cdpr.so3 import quat_to_matrix
from cdpr.tension import OsqpTensionSolver, TensionLimits
from tests.conftest import ROBOTS, load_robot
from tuning.scenarios import STANDARD_SET


def random_poses(
    rng: np.random.Generator, robot: Robot, count: int, reach: float = 0.3, tilt: float = 0.3
) -> list[Pose]:
    return [
        Pose.from_rotvec(
            robot.home.position + rng.uniform(-reach, reach, 3), rng.uniform(-tilt, tilt, 3)
        )
        for _ in range(count)
    ]


def test_liediff6_is_liediff(reference8: Robot) -> None:
    rng = np.random.default_rng(2)
    poses = random_poses(rng, reference8, 20)
    for a, b in itertools.pairwise(poses):
        assert liediff6(a, b) == tuple(liediff(a, b).tolist())


def test_pose_tuples_match_its_arrays() -> None:
    q = np.array([-0.9, 0.1, 0.3, -0.2])
    pose = Pose((0.1, -0.2, 1.3), q / np.linalg.norm(q))
    assert pose.position_tuple == tuple(pose.position.tolist())
    assert pose.quaternion_tuple == tuple(pose.quaternion.tolist())
    assert pose.quaternion_tuple[0] > 0.0  # canonical sign
    np.testing.assert_array_equal(pose.rotation, quat_to_matrix(pose.quaternion))
    for array in (pose.position, pose.quaternion, pose.rotation):
        assert not array.flags.writeable


def test_pose_fast_path_equals_validated_constructor() -> None:
    q = (-0.5, 0.5, -0.5, 0.5)  # w < 0: stored with the other sign
    fast = Pose._from_unit([0.1, 0.2, 0.3], q)
    slow = Pose((0.1, 0.2, 0.3), q)
    assert fast == slow and hash(fast) == hash(slow)
    np.testing.assert_array_equal(fast.quaternion, [0.5, -0.5, 0.5, -0.5])
    assert fast.as_dict() == slow.as_dict()


def test_retract_then_liediff_round_trips(reference8: Robot) -> None:
    rng = np.random.default_rng(3)
    for pose in random_poses(rng, reference8, 10):
        step = rng.normal(scale=0.1, size=6)
        np.testing.assert_allclose(liediff(pose, retract(pose, step)), step, atol=1e-14)


def test_fk_normal_factor_solves_the_least_squares_twist(reference8: Robot) -> None:
    """FKResult.normal_factor is a Cholesky factor of jacobian^T jacobian: one dpotrs
    gives the least-squares solution, as the controller uses it."""
    rng = np.random.default_rng(4)
    for pose in random_poses(rng, reference8, 10):
        lengths = reference8.cable_lengths(pose)
        for move in (1e-6, 1e-3, 0.05):  # chord finish, full iterations, larger start error
            guess = retract(pose, rng.normal(scale=move, size=6))
            fk = reference8.forward_kinematics(lengths, guess)
            assert fk.converged and fk.normal_factor is not None
            J = fk.jacobian
            rates = rng.normal(size=reference8.n_cables)
            x, info = dpotrs(fk.normal_factor, J.T @ rates)
            assert info == 0
            expected = np.linalg.lstsq(J, rates, rcond=None)[0]
            np.testing.assert_allclose(x, expected, rtol=1e-9, atol=1e-12)


def test_fk_failure_has_no_jacobian_or_factor(reference8: Robot) -> None:
    lengths = reference8.cable_lengths(reference8.home)
    bad = reference8.forward_kinematics(lengths + 0.5)  # no pose has these lengths
    assert not bad.converged and bad.jacobian is None and bad.normal_factor is None
    nan = reference8.forward_kinematics(np.where(np.arange(8) == 3, np.nan, lengths))
    assert not nan.converged and "cable 3" in nan.reason


@pytest.mark.parametrize(
    "law",
    [pid(100.0, 50.0, 20.0), pid(100.0), pid(100.0, 0.0, 20.0, 0.01), pid(80.0, 10.0, 20.0, 0.02)],
)
@pytest.mark.parametrize("channels", [1, 6])
def test_discrete_controller_is_the_state_space_recurrence(law, channels: int) -> None:
    rng = np.random.default_rng(5)
    loop = law.discretise(0.002, channels)
    Ad, Bd, Cd, Dd = loop.Ad, loop.Bd, loop.Cd, loop.Dd
    x = np.zeros((Ad.shape[0], channels))
    for _ in range(100):
        error = rng.normal(size=(Dd.shape[1], channels))
        expected = (Dd @ error)[0] + (Cd @ x)[0]
        x = Ad @ x + Bd @ error
        a = loop.step(error)
        np.testing.assert_allclose(a, expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(loop.state, x, rtol=1e-12, atol=1e-12)
    loop.reset()
    assert loop.state.shape == (Ad.shape[0], channels) and not loop.state.any()


def test_platform_terms_equal_the_textbook_form_for_a_general_body() -> None:
    """mass_and_bias uses the inertia about p; the textbook form uses the inertia about
    the centre of mass.  A tilted inertia and an off-axis centre of mass exercise every
    term."""
    rng = np.random.default_rng(6)
    data = load_yaml(ROBOTS / "reference8.yaml")
    data["platform"]["center_of_mass"] = [0.03, -0.02, -0.05]
    data["platform"]["inertia"] = [[0.45, 0.02, -0.01], [0.02, 0.40, 0.03], [-0.01, 0.03, 0.28]]
    robot = Robot.from_dict(data)
    for pose in random_poses(rng, robot, 10):
        twist = rng.normal(scale=2.0, size=6)
        M, mu = robot.dynamics(pose, twist)
        np.testing.assert_allclose(M, reference.mass_matrix(robot, pose), rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            mu, reference.bias_wrench(robot, pose, twist), rtol=0, atol=1e-10
        )


def test_model_terms_jacobian_is_contiguous_and_exact(reference8: Robot) -> None:
    rng = np.random.default_rng(7)
    for pose in random_poses(rng, reference8, 5):
        twist = rng.normal(size=6)
        Lam, c, M, mu = reference8.model_terms(pose, twist)
        assert Lam.flags.c_contiguous
        np.testing.assert_array_equal(Lam, reference8.jacobian(pose))
        np.testing.assert_array_equal(c, reference8.bias_accel(pose, twist))
        M2, mu2 = reference8.dynamics(pose, twist)
        np.testing.assert_array_equal(M, M2)
        np.testing.assert_array_equal(mu, mu2)


def test_trajectory_samples_numpy_times_like_floats(reference8: Robot) -> None:
    trajectory = STANDARD_SET["figure_eight"](reference8)
    for t in np.linspace(trajectory.start_time, trajectory.end_time, 37):
        a, b = trajectory.sample(t), trajectory.sample(float(t))
        assert a.pose == b.pose
        np.testing.assert_array_equal(a.twist, b.twist)
        np.testing.assert_array_equal(a.accel, b.accel)


def test_trajectory_rates_are_derivatives_of_the_samples(reference8: Robot) -> None:
    """The rate and accel columns of the segment tables differentiate the pose."""
    trajectory = STANDARD_SET["edge_move"](reference8)
    h = 1e-5
    for t in np.linspace(0.1, trajectory.end_time - 0.1, 9):
        before, now, after = (trajectory.sample(t + d) for d in (-h, 0.0, h))
        rate = liediff(before.pose, after.pose) / (2.0 * h)
        np.testing.assert_allclose(now.twist, rate, atol=1e-6)
        np.testing.assert_allclose(now.accel, (after.twist - before.twist) / (2.0 * h), atol=1e-4)


def test_osqp_warm_start_waits_for_the_next_osqp_run() -> None:
    """An interior-shortcut cycle leaves its tensions as the next OSQP start (applied
    when OSQP runs); a solver alternating between both kinds of cycle answers like a
    fresh one."""
    rng = np.random.default_rng(8)
    robot = load_robot("reference8")
    limits = TensionLimits.from_robot(robot, t_ref=robot.t_min + 50.0)  # bounds at times
    solver = OsqpTensionSolver(limits)
    iterations = []
    for k, pose in enumerate(random_poses(rng, robot, 12, reach=0.2, tilt=0.1)):
        twist = rng.normal(scale=0.5, size=6)
        L = robot.jacobian(pose)
        M, mu = robot.dynamics(pose, twist)
        alpha = rng.normal(scale=3.0 if k % 2 else 0.1, size=6)  # large ones activate bounds
        tau = M @ alpha + mu
        f0 = robot.m0 * (L @ alpha + robot.bias_accel(pose, twist))
        f_b = robot.k0 * (L @ twist)
        result = solver.solve(L, tau, f_b, f0)
        fresh = OsqpTensionSolver(limits).solve(L, tau, f_b, f0)
        assert result.feasible == fresh.feasible
        if result.feasible:
            np.testing.assert_allclose(result.tensions, fresh.tensions, rtol=0, atol=1e-4)
            # the start is pending after a shortcut and consumed by an OSQP run
            assert (solver._start is not None) == (result.iterations == 0)
        iterations.append(result.iterations)
    assert 0 in iterations and max(iterations) > 0  # both kinds of cycle, interleaved
