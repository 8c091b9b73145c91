"""Dynamics: M SPD, Lemma 1, and tau = M alpha + mu against a numerical Newton-Euler."""

from __future__ import annotations

import numpy as np
from hypothesis import given

from cdpr import Pose, Robot
from cdpr import reference as ref
from cdpr.so3 import exp_so3
from tests.conftest import pose_near_home, twists, workspace_poses


@given(offset=workspace_poses(reach=0.5, tilt=0.4))
def test_mass_matrix_is_symmetric_positive_definite(robot: Robot, offset) -> None:
    M = robot.mass_matrix(pose_near_home(robot, offset))
    np.testing.assert_allclose(M, M.T, atol=1e-12)
    assert np.linalg.eigvalsh(M)[0] > 0.0


@given(offset=workspace_poses(reach=0.5, tilt=0.4))
def test_lemma1_eigenvalues_in_zero_to_one_over_m0(robot: Robot, offset) -> None:
    pose = pose_near_home(robot, offset)
    M, Lam = robot.mass_matrix(pose), robot.jacobian(pose)
    eig = np.linalg.eigvals(np.linalg.solve(M, Lam.T @ Lam))
    assert np.all(np.abs(eig.imag) < 1e-9)  # a basis of real eigenvectors
    assert np.all(eig.real > -1e-12) and np.all(eig.real < 1.0 / robot.m0.min())
    masses = robot.modal_masses(pose)
    assert np.all(masses >= robot.m0.min()) and np.all(np.diff(masses) >= 0)
    np.testing.assert_allclose(np.sort(1.0 / masses), np.sort(eig.real), rtol=1e-9)


def test_modal_masses_are_infinite_for_a_direction_no_cable_sees() -> None:
    """A platform with two collinear cable pairs cannot feel some motions: m_i = inf."""
    from tests.conftest import load_robot

    robot = load_robot("reference8")
    M = robot.mass_matrix(robot.home)
    Lam = robot.jacobian(robot.home)
    Lam[:, 5] = 0.0  # pretend no cable resists the z rotation
    from cdpr.dynamics import modal_masses

    masses = modal_masses(M, Lam)
    assert np.isinf(masses[-1]) and np.all(np.isfinite(masses[:-1]))


def momentum_wrench(robot: Robot, pose: Pose, twist: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The wrench (force, torque about p) the cables must apply to the platform, by
    differentiating its linear momentum and its angular momentum about the fixed point
    p(0) numerically along a path with the given twist and acceleration; plus the
    actuators' m0 l_ddot mapped through Lambda^T, with l_ddot also differentiated."""
    m = robot.platform.mass
    g = np.array(robot.platform.gravity)
    cb = np.array(robot.platform.center_of_mass)
    o = pose.position.copy()

    def state(t: float):
        p = pose.position + twist[:3] * t + 0.5 * accel[:3] * t * t
        R = exp_so3(twist[3:] * t + 0.5 * accel[3:] * t * t) @ pose.rotation
        v = twist[:3] + accel[:3] * t
        # angular velocity of R(t) = exp(a(t)) R0: w = J_l(a) a_dot (left Jacobian of SO(3))
        a, a_dot = twist[3:] * t + 0.5 * accel[3:] * t * t, twist[3:] + accel[3:] * t
        h = 1e-7
        W = (exp_so3(a + h * a_dot) - exp_so3(a - h * a_dot)) / (2 * h) @ exp_so3(a).T
        w = np.array([W[2, 1], W[0, 2], W[1, 0]])
        c = R @ cb
        v_com = v + np.cross(w, c)
        I_c = R @ robot.platform.inertia @ R.T
        H_o = np.cross(p + c - o, m * v_com) + I_c @ w
        lengths = robot.cable_lengths(Pose.from_matrix(p, R))
        return m * v_com, H_o, p + c, lengths

    dt = 1e-4
    P1, H1, _, l1 = state(dt)
    _, _, com0, l0 = state(0.0)
    Pm, Hm, _, lm = state(-dt)
    force = (P1 - Pm) / (2 * dt) - m * g
    torque = (H1 - Hm) / (2 * dt) - np.cross(com0 - o, m * g)
    lddot = (l1 - 2 * l0 + lm) / dt**2
    return np.concatenate([force, torque]) + robot.jacobian(pose).T @ (robot.m0 * lddot)


@given(offset=workspace_poses(), twist=twists(1.5), accel=twists(3.0))
def test_tau_matches_numerical_newton_euler(robot: Robot, offset, twist, accel) -> None:
    pose = pose_near_home(robot, offset)
    M, mu = robot.dynamics(pose, twist)
    np.testing.assert_allclose(
        M @ accel + mu, momentum_wrench(robot, pose, twist, accel), atol=2e-4 * robot.platform.mass
    )


@given(offset=workspace_poses(), twist=twists(1.5))
def test_kinetic_energy_is_half_phi_m_phi(robot: Robot, offset, twist) -> None:
    pose = pose_near_home(robot, offset)
    c = pose.rotation @ np.array(robot.platform.center_of_mass)
    v_com = twist[:3] + np.cross(twist[3:], c)
    I_c = pose.rotation @ robot.platform.inertia @ pose.rotation.T
    ldot = robot.jacobian(pose) @ twist
    energy = (
        0.5 * robot.platform.mass * v_com @ v_com
        + 0.5 * twist[3:] @ I_c @ twist[3:]
        + 0.5 * np.sum(robot.m0 * ldot**2)
    )
    np.testing.assert_allclose(0.5 * twist @ robot.mass_matrix(pose) @ twist, energy, rtol=1e-12)


def test_gravity_is_compensated_by_mu_at_rest(reference8: Robot) -> None:
    """At rest, mu = (-m g, -m c x g): the wrench that holds the platform up (DESIGN §3)."""
    pose = Pose.from_rotvec(reference8.home.position, [0.2, 0.0, 0.0])
    mu = reference8.bias_wrench(pose, np.zeros(6))
    m, g = reference8.platform.mass, np.array(reference8.platform.gravity)
    c = pose.rotation @ np.array(reference8.platform.center_of_mass)
    np.testing.assert_allclose(mu, np.concatenate([-m * g, -m * np.cross(c, g)]), atol=1e-12)
    assert mu[2] > 0


@given(offset=workspace_poses(reach=0.5, tilt=0.4), twist=twists(2.0))
def test_fast_dynamics_equals_reference(robot: Robot, offset, twist) -> None:
    pose = pose_near_home(robot, offset)
    M, mu = robot.dynamics(pose, twist)
    np.testing.assert_allclose(M, ref.mass_matrix(robot, pose), rtol=0, atol=1e-12)
    np.testing.assert_allclose(mu, ref.bias_wrench(robot, pose, twist), rtol=0, atol=1e-10)
    np.testing.assert_allclose(robot.bias_wrench(pose, twist), mu, rtol=0, atol=0)


def test_the_batched_model_is_the_fast_one_at_every_pose(robot: Robot) -> None:
    """cdpr.reference.model_terms over many poses at once (the path timing's grid) gives
    at each pose what Robot.model_terms gives for it alone."""
    rng = np.random.default_rng(3)
    poses = [
        Pose.from_rotvec(robot.home.position + rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.3, 0.3, 3))
        for _ in range(25)
    ]
    twists = rng.normal(0.0, 0.5, (25, 6))
    positions = np.array([p.position for p in poses])
    rotations = np.array([p.rotation for p in poses])
    batched = ref.model_terms(robot, positions, rotations, twists)
    for k, (pose, twist) in enumerate(zip(poses, twists, strict=True)):
        for ours, alone in zip(batched, robot.model_terms(pose, twist), strict=True):
            np.testing.assert_allclose(ours[k], alone, rtol=0, atol=1e-10)
