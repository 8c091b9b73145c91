"""The control cycle's measurement kernel (cdpr.measurement) against references computed
apart: the pose by forward kinematics of the stretched lengths (cdpr.robot), the twist by
scipy's least squares on the lengths' Jacobian, the pose error by cdpr.pose.liediff, the
filters by their formulas in numpy; and what it leaves alone when a measurement fails."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import lstsq

from cdpr import Pose, Robot
from cdpr.forward_kinematics import CONVERGED, fit_start
from cdpr.measurement import (
    DIFFERENTIATED,
    ERROR,
    ERROR_RATE,
    FILTERED_RATES,
    FROM_RATES,
    MEMORY_SIZE,
    OUT_SIZE,
    POSE,
    TWIST,
    measure,
)
from cdpr.pose import liediff

SCALE = 1.3  # a compliance scale away from 1, so that the kernel must apply it
TENSIONS = np.linspace(150.0, 400.0, 8)


def numbers(pose: Pose) -> np.ndarray:
    return np.array((*pose.position_tuple, *pose.quaternion_tuple))


def run(
    robot: Robot,
    drums: np.ndarray,
    rates: np.ndarray,
    guess: Pose,
    memory: np.ndarray,
    reference: np.ndarray,
    mode: int = FROM_RATES,
    stretch_rate: np.ndarray | None = None,
    smoothing: float = 0.2,
    interval: float = 2e-3,
) -> tuple[tuple, np.ndarray]:
    settings = robot.fk_settings
    out = np.full(OUT_SIZE, -7.0)
    kind, lengths0, J0, L0 = fit_start(robot.linearise_at(guess))
    result = measure(
        robot.geometry.rows, drums, np.array(robot.compliance), TENSIONS, SCALE, kind,
        numbers(guess), lengths0, J0, L0, settings.max_iterations,
        settings.step_tolerance**2, settings.max_residual, rates,
        np.empty(0) if stretch_rate is None else stretch_rate, mode, smoothing, interval,
        memory, reference, out,
    )  # fmt: skip
    return result, out


@pytest.fixture
def flight(reference8: Robot) -> dict:
    """A pose off home, the drums' lengths there under TENSIONS at SCALE, the last pose
    a step before it, and a moving reference."""
    robot = reference8
    home = robot.home
    pose = Pose.from_rotvec(home.position + np.array((0.05, -0.03, 0.02)), (0.02, -0.01, 0.03))
    last = Pose.from_rotvec(
        home.position + np.array((0.049, -0.0305, 0.0201)), (0.0199, -0.01, 0.03)
    )
    stretch = np.array(robot.compliance) * TENSIONS * SCALE
    drums = robot.cable_lengths(pose) / (1.0 + stretch)
    reference = np.concatenate((numbers(Pose(home.position, home.quaternion)),
                                (0.1, -0.05, 0.02, 0.01, 0.0, -0.02)))  # fmt: skip
    memory = np.zeros(MEMORY_SIZE)
    memory[POSE] = numbers(last)
    memory[7:13] = (0.3, -0.1, 0.05, 0.01, 0.02, -0.01)  # the last twist
    memory[13:19] = (0.2, -0.2, 0.0, 0.0, 0.01, 0.0)  # the last drive twist
    memory[19:25] = (0.01, 0.0, -0.01, 0.001, 0.0, 0.002)  # the rate bias
    rates = np.random.default_rng(3).normal(0.0, 0.05, robot.n_cables)
    return {"robot": robot, "pose": pose, "last": last, "drums": drums, "rates": rates,
            "reference": reference, "memory": memory}  # fmt: skip


def test_pose_twist_and_error_match_their_references(flight: dict) -> None:
    robot, pose, reference = flight["robot"], flight["pose"], flight["reference"]
    memory = flight["memory"].copy()
    stretch_rate = np.linspace(-1e-4, 1e-4, robot.n_cables)
    (status, finite, *_), out = run(robot, flight["drums"], flight["rates"], flight["last"],
                                    memory, reference, stretch_rate=stretch_rate)  # fmt: skip
    assert status == CONVERGED and finite
    measured = Pose(out[0:3], out[3:7])
    assert np.allclose(measured.position, pose.position, atol=1e-9)
    assert np.allclose(liediff(pose, measured), 0.0, atol=1e-9)
    # phi = Lambda^+ (l' + stretch rate), Lambda at the measured pose, by LAPACK's lstsq
    twist = lstsq(robot.jacobian(measured), flight["rates"] + stretch_rate)[0]
    assert np.allclose(out[TWIST], twist, rtol=1e-6, atol=1e-9)
    target = Pose(reference[0:3], reference[3:7])
    assert np.allclose(out[ERROR], liediff(target, measured), atol=1e-12)
    assert np.allclose(out[ERROR_RATE], out[TWIST] - reference[7:13], atol=1e-15)
    assert np.array_equal(memory[POSE], out[POSE]) and np.array_equal(memory[7:13], out[TWIST])
    assert np.array_equal(memory[13:25], flight["memory"][13:25])  # no filter in this mode


def test_the_filtered_rates_follow_the_complementary_filter(flight: dict) -> None:
    robot, memory = flight["robot"], flight["memory"].copy()
    s, interval = 0.2, 2e-3
    (status, finite, *_), out = run(robot, flight["drums"], flight["rates"], flight["last"],
                                    memory, flight["reference"], FILTERED_RATES, None, s,
                                    interval)  # fmt: skip
    assert status == CONVERGED and finite
    measured = Pose(out[0:3], out[3:7])
    drive = lstsq(robot.jacobian(measured), flight["rates"])[0]
    last_drive, bias = flight["memory"][13:19], flight["memory"][19:25]
    moved = liediff(flight["last"], measured) / interval
    bias = bias + s * (moved - 0.5 * (drive + last_drive) - bias)
    assert np.allclose(out[TWIST], drive + bias, rtol=1e-6, atol=1e-9)
    assert np.allclose(memory[13:19], drive, rtol=1e-6, atol=1e-9)
    assert np.allclose(memory[19:25], bias, rtol=1e-6, atol=1e-9)


def test_the_differentiated_twist_filters_the_poses_difference(flight: dict) -> None:
    robot, memory = flight["robot"], flight["memory"].copy()
    s, interval = 0.3, 1e-3
    (status, finite, *_), out = run(robot, flight["drums"], np.full(8, np.nan), flight["last"],
                                    memory, flight["reference"], DIFFERENTIATED, None, s,
                                    interval)  # fmt: skip
    assert status == CONVERGED and finite  # the rates are not read
    measured = Pose(out[0:3], out[3:7])
    last_twist = flight["memory"][7:13]
    expected = last_twist + s * (liediff(flight["last"], measured) / interval - last_twist)
    assert np.allclose(out[TWIST], expected, rtol=1e-9, atol=1e-9)


def test_a_non_finite_rate_leaves_the_pose_and_twist_as_they_were(flight: dict) -> None:
    memory = flight["memory"].copy()
    rates = flight["rates"].copy()
    rates[5] = math.inf
    (status, finite, *_), out = run(flight["robot"], flight["drums"], rates, flight["last"],
                                    memory, flight["reference"])  # fmt: skip
    assert status == CONVERGED and not finite
    assert np.array_equal(memory, flight["memory"]) and np.all(out == -7.0)


def test_a_failed_fit_leaves_everything_as_it_was(flight: dict) -> None:
    memory = flight["memory"].copy()
    drums = flight["drums"].copy()
    drums[2] += 0.05  # 5 cm: beyond max_residual
    (status, finite, *_), out = run(flight["robot"], drums, flight["rates"], flight["last"],
                                    memory, flight["reference"], FILTERED_RATES)  # fmt: skip
    assert status != CONVERGED and not finite
    assert np.array_equal(memory, flight["memory"]) and np.all(out == -7.0)
