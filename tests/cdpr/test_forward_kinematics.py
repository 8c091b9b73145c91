"""Forward kinematics Y(l): exact recovery, noise behaviour, and bad measurements."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr import Pose, Robot, liediff, retract
from tests.conftest import pose_near_home, workspace_poses


def pose_error(a, b) -> tuple[float, float]:
    d = liediff(a, b)
    return float(np.linalg.norm(d[:3])), float(np.linalg.norm(d[3:]))


@given(offset=workspace_poses(reach=0.4, tilt=0.25))
def test_cold_start_from_home_recovers_the_pose(robot: Robot, offset) -> None:
    truth = pose_near_home(robot, offset)
    result = robot.forward_kinematics(robot.cable_lengths(truth))
    assert result.converged, result.reason
    dp, dw = pose_error(truth, result.pose)
    assert dp < 1e-9 and dw < 1e-9
    assert result.residual < 1e-9


@given(
    offset=workspace_poses(),
    step=st.lists(st.floats(-1, 1), min_size=6, max_size=6).filter(
        lambda v: np.linalg.norm(v[:3]) > 1e-3 and np.linalg.norm(v[3:]) > 1e-3
    ),
)
def test_warm_start_after_a_cycle_recovers_the_pose(robot: Robot, offset, step) -> None:
    """The previous pose, 1 mm and 0.5 deg away, as the guess (the daemon's case)."""
    truth = pose_near_home(robot, offset)
    s = np.array(step)
    move = np.concatenate(
        [1e-3 * s[:3] / np.linalg.norm(s[:3]), np.deg2rad(0.5) * s[3:] / np.linalg.norm(s[3:])]
    )
    result = robot.forward_kinematics(robot.cable_lengths(truth), guess=retract(truth, move))
    assert result.converged, result.reason
    dp, dw = pose_error(truth, result.pose)
    assert dp < 1e-9 and dw < 1e-9
    assert result.iterations <= 4


def test_noise_gives_the_least_squares_estimate(reference8: Robot) -> None:
    """With 0.1 mm encoder noise n, Y(L + n) - eta is the linear least-squares estimate
    (Lambda^T Lambda)^-1 Lambda^T n up to second-order terms, and its Mahalanobis norm follows
    chi^2 with 6 degrees of freedom; the residual is that of the projection of n."""
    robot = reference8
    rng = np.random.default_rng(7)
    sigma = 1e-4
    chi2 = []
    for _ in range(300):
        truth = retract(
            robot.home, np.concatenate([rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.15, 0.15, 3)])
        )
        lengths, Lam = robot.lengths_and_jacobian(truth)
        noise = rng.normal(0.0, sigma, robot.n_cables)
        result = robot.forward_kinematics(lengths + noise, guess=truth)
        assert result.converged, result.reason
        err = liediff(truth, result.pose)
        linear = np.linalg.lstsq(Lam, noise, rcond=None)[0]
        # equal up to second-order terms, which are ~ noise / length relative to it
        assert np.linalg.norm(err - linear) < 1e-2 * np.linalg.norm(linear)
        misfit = robot.cable_lengths(result.pose) - (lengths + noise)
        assert result.residual == pytest.approx(np.sqrt(misfit @ misfit / 8), rel=1e-9, abs=1e-15)
        projected = noise - Lam @ linear
        assert result.residual == pytest.approx(np.sqrt(projected @ projected / 8), rel=0.05)
        chi2.append(err @ (Lam.T @ Lam) @ err / sigma**2)
    # mean of chi^2(6) is 6; the mean of 300 samples has standard deviation sqrt(12/300) = 0.2
    assert 5.3 < np.mean(chi2) < 6.7


def test_six_cables_solve_exactly_with_zero_residual(robot: Robot) -> None:
    truth = retract(robot.home, [0.1, -0.05, 0.08, 0.05, -0.02, 0.1])
    result = robot.forward_kinematics(robot.cable_lengths(truth) + 1e-4 * np.arange(robot.n_cables))
    assert result.converged
    if robot.n_cables == 6:  # square system: any nearby lengths fit exactly
        assert result.residual < 1e-12
    else:
        assert result.residual > 1e-6


@pytest.mark.parametrize(
    ("corrupt", "reason"),
    [
        (lambda L: L * 3.0, "exceeds max_residual"),
        (lambda L: L + np.r_[0.5, np.zeros(len(L) - 1)], "exceeds max_residual"),
        (lambda L: np.r_[np.nan, L[1:]], "non-finite length nan at cable 0"),
        (lambda L: np.r_[L[:-1], np.inf], "non-finite length inf at cable"),
        (lambda L: -L, ""),
        (lambda L: np.zeros_like(L), ""),
    ],
)
def test_bad_measurements_are_reported_not_raised(reference8: Robot, corrupt, reason) -> None:
    lengths = corrupt(reference8.cable_lengths(reference8.home))
    result = reference8.forward_kinematics(lengths)
    assert not result.converged
    assert reason in result.reason and result.reason
    assert np.all(np.isfinite(result.pose.position))


def test_unreachable_lengths_for_the_suspended_robot_do_not_converge() -> None:
    from tests.conftest import load_robot

    robot = load_robot("suspended6")
    # corners 2.7 m apart, platform attachments 0.5 m apart: 0.5 m cables cannot reach
    lengths = np.full(robot.n_cables, 0.5)
    result = robot.forward_kinematics(lengths)
    assert not result.converged
    assert result.reason


def test_wrong_number_of_lengths_is_a_programming_error(reference8: Robot) -> None:
    with pytest.raises(ValueError, match="expected 8 cable lengths, got 7"):
        reference8.forward_kinematics(np.ones(7))


def test_result_carries_the_jacobian_of_its_last_linearisation(reference8: Robot) -> None:
    """FKResult.jacobian is Lambda within one (tiny) step of the pose: the controller's
    least-squares twist uses it instead of evaluating Lambda again."""
    pose = Pose.from_rotvec(
        reference8.home.position + np.array([0.05, -0.03, 0.02]), [0.02, 0.01, -0.03]
    )
    guess = Pose.from_rotvec(pose.position + 1e-3, [0.021, 0.01, -0.03])
    result = reference8.forward_kinematics(reference8.cable_lengths(pose), guess)
    assert result.converged and result.jacobian is not None
    np.testing.assert_allclose(result.jacobian, reference8.jacobian(result.pose), atol=1e-4)
    bad = reference8.forward_kinematics(np.full(8, np.nan))
    assert not bad.converged and bad.jacobian is None


def test_a_prepared_linearisation_gives_what_the_guess_gives(robot: Robot) -> None:
    """linearise_at(guess) computes the guess's part of the first evaluation before the
    lengths are known; Y(l) from it equals Y(l) from the guess itself (within 1e-9): the
    same iterations, and the Jacobian and normal factor the twist uses.  Guesses within
    the step tolerance, the chord finish's range, Gauss-Newton's and far off, and bad
    lengths."""
    rng = np.random.default_rng(3)
    for k in range(40):
        truth = retract(robot.home, np.r_[rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)])
        distance = (1e-10, 1e-5, 1e-3, 0.1)[k % 4]
        guess = retract(truth, distance * rng.standard_normal(6))
        noise = 1e-5 * rng.standard_normal(robot.n_cables) if k % 4 else 0.0
        lengths = robot.cable_lengths(truth) + noise
        if k % 10 == 9:
            lengths = [np.r_[np.nan, lengths[1:]], 3 * lengths, -lengths, 0 * lengths][k // 10]
        cold = robot.forward_kinematics(lengths, guess)
        warm = robot.forward_kinematics(lengths, robot.linearise_at(guess))
        assert (warm.converged, warm.reason, warm.iterations) == (
            cold.converged, cold.reason, cold.iterations
        )  # fmt: skip
        dp, dw = pose_error(cold.pose, warm.pose)
        assert dp < 1e-9 and dw < 1e-9
        assert abs(warm.residual - cold.residual) < 1e-9 or warm.residual == cold.residual
        if cold.converged:
            np.testing.assert_allclose(warm.jacobian, cold.jacobian, rtol=0, atol=1e-9)
            factors = np.triu(warm.normal_factor), np.triu(cold.normal_factor)  # the upper
            np.testing.assert_allclose(*factors, rtol=0, atol=1e-9)
        else:
            assert warm.jacobian is None and warm.normal_factor is None
