"""The control cycle's command kernel (cdpr.command) and the loop's compiled sample
(cdpr.single_actuator.advance) against references computed apart: scipy.signal's
discrete state-space simulation for the loop, numpy for the wrench and the no-load
forces, OSQP without its shortcut (the QP itself) for the tensions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from cdpr import Pose, Robot
from cdpr.command import command, out_size
from cdpr.measurement import ERROR, ERROR_RATE, OUT_SIZE
from cdpr.single_actuator import pid
from cdpr.tension import OsqpTensionSolver, TensionLimits

PERIOD = 2e-3


def test_the_loop_matches_scipy_s_state_space_simulation() -> None:
    """DiscreteController.step (advance) on 6 channels of a PID with a filtered
    derivative, against scipy.signal.dlsim of its (Ad, Bd, Cd, Dd) per channel."""
    loop = pid(400.0, 900.0, 40.0, derivative_filter=0.01).discretise(PERIOD, 6)
    rng = np.random.default_rng(5)
    errors = rng.normal(0.0, 1e-3, (300, 2, 6))  # [e; e'] per sample and channel
    ours = np.array([loop.step(e) for e in errors])
    system = (loop.Ad, loop.Bd, loop.Cd, loop.Dd, PERIOD)
    for ch in range(6):
        _, theirs, _ = signal.dlsim(system, errors[:, :, ch])
        assert np.allclose(ours[:, ch], theirs[:, 0], rtol=1e-9, atol=1e-12)


def inputs(robot: Robot, pose: Pose, twist: np.ndarray, observed: np.ndarray) -> dict:
    n = robot.n_cables
    rng = np.random.default_rng(11)
    measured = np.zeros(OUT_SIZE)
    measured[ERROR] = rng.normal(0.0, 1e-3, 6)
    measured[ERROR_RATE] = rng.normal(0.0, 1e-2, 6)
    table, G = robot.model_tables(pose, twist)
    limits = TensionLimits.from_robot(robot)
    return {
        "loop": pid(400.0, 900.0, 40.0).discretise(PERIOD, 6),
        "measured": measured,
        "accel": rng.normal(0.0, 0.2, 6),
        "table": table,
        "G": G,
        "m0": np.array(robot.m0, dtype=float),
        "observed": observed,
        "f_b": rng.normal(0.0, 2.0, n),
        "limits": limits,
    }


def run(d: dict, solver: OsqpTensionSolver) -> tuple[bool, np.ndarray, np.ndarray]:
    """The kernel's answer, and the loop's output it should have used (from a copy of
    the loop's state, by the loop's own step)."""
    loop = d["loop"]
    before = pid(400.0, 900.0, 40.0).discretise(PERIOD, 6)
    before.state[:] = loop.state
    expected_loop = before.step(np.stack([d["measured"][ERROR], d["measured"][ERROR_RATE]]))
    out = np.full(out_size(d["table"].shape[0]), -7.0)
    K, stack, order = loop.kernel_terms()
    shortcut = solver.shortcut()
    assert shortcut is not None
    inside = command(
        K, stack, order, d["measured"], d["accel"], d["table"], d["G"], d["m0"], d["observed"],
        d["f_b"], *shortcut, True, out,
    )  # fmt: skip
    return inside, out, expected_loop


@pytest.mark.parametrize("observed", [np.zeros(6), np.array([5.0, -3.0, 2.0, 0.1, -0.2, 0.05])])
def test_the_command_matches_numpy_and_the_qp(reference8: Robot, observed: np.ndarray) -> None:
    robot, n = reference8, reference8.n_cables
    pose = Pose(robot.home.position + np.array([0.05, -0.02, 0.03]), robot.home.quaternion)
    twist = np.array([0.1, -0.05, 0.02, 0.01, 0.02, -0.01])
    d = inputs(robot, pose, twist, observed)
    solver = OsqpTensionSolver(d["limits"])
    inside, out, loop_output = run(d, solver)
    assert inside
    Lam, c, M, mu = robot.model_terms(pose, twist)
    alpha = d["accel"] + loop_output
    tau = M.dot(alpha) + mu - observed
    f0 = robot.m0 * (Lam.dot(alpha) + c)
    assert np.allclose(out[0:6], alpha, rtol=1e-12, atol=1e-15)
    assert np.allclose(out[6:12], tau, rtol=1e-12, atol=1e-12)
    assert np.allclose(out[12 : 12 + n], f0, rtol=1e-12, atol=1e-12)
    qp = OsqpTensionSolver(d["limits"], interior_shortcut=False).solve(Lam, tau, d["f_b"], f0)
    assert qp.feasible
    tensions = out[12 + 2 * n : 12 + 3 * n]
    assert np.allclose(tensions, qp.tensions, rtol=0.0, atol=1e-3 * qp.tensions.max())
    assert np.allclose(out[12 + n : 12 + 2 * n], f0 - tensions, rtol=0.0, atol=1e-12)
    assert np.allclose(out[12 + 3 * n :], f0 - tensions + d["f_b"], rtol=0.0, atol=1e-12)


def test_a_bound_met_leaves_the_tensions_to_the_solver(reference8: Robot) -> None:
    """A wrench the least-norm tensions cannot hold within the bounds: False, with the
    wrench and the no-load forces computed for the solver, no forces or commands."""
    robot, n = reference8, reference8.n_cables
    d = inputs(robot, robot.home, np.zeros(6), np.zeros(6))
    d["accel"] = np.array([100.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # 10 g sideways: past force_max
    inside, out, loop_output = run(d, OsqpTensionSolver(d["limits"]))
    assert not inside
    _, _, M, mu = robot.model_terms(robot.home, np.zeros(6))
    alpha = d["accel"] + loop_output
    assert np.allclose(out[6:12], M.dot(alpha) + mu, rtol=1e-12, atol=1e-12)
    assert np.all(out[12 + n : 12 + 2 * n] == -7.0) and np.all(out[12 + 3 * n :] == -7.0)
