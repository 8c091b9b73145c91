"""Kinematics: Lambda and c against finite differences of L, fast path against reference."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given

from cdpr import Pose, Robot, retract
from cdpr import reference as ref
from cdpr.so3 import exp_so3
from tests.conftest import pose_near_home, twists, workspace_poses


def lengths_along(robot: Robot, pose: Pose, twist: np.ndarray, accel: np.ndarray, t: float):
    """L at time t on the path p(t) = p + v t + a t^2/2, R(t) = exp(w t + wd t^2/2) R.

    Its velocity at t = 0 is the twist and its acceleration is accel (mixed coordinates)."""
    p = pose.position + twist[:3] * t + 0.5 * accel[:3] * t * t
    R = exp_so3(twist[3:] * t + 0.5 * accel[3:] * t * t) @ pose.rotation
    return robot.cable_lengths(Pose.from_matrix(p, R))


@given(offset=workspace_poses(), direction=twists())
def test_jacobian_matches_finite_differences(robot: Robot, offset, direction) -> None:
    pose = pose_near_home(robot, offset)
    h = 1e-6
    fd = (
        robot.cable_lengths(retract(pose, h * direction))
        - robot.cable_lengths(retract(pose, -h * direction))
    ) / (2 * h)
    np.testing.assert_allclose(robot.jacobian(pose) @ direction, fd, atol=1e-8)


@given(offset=workspace_poses(), twist=twists(), accel=twists(2.0))
def test_lddot_is_lambda_alpha_plus_c(robot: Robot, offset, twist, accel) -> None:
    """Second central difference of L along a path with known velocity and acceleration."""
    pose = pose_near_home(robot, offset)
    h = 1e-4
    l_plus = lengths_along(robot, pose, twist, accel, h)
    l_minus = lengths_along(robot, pose, twist, accel, -h)
    l0 = robot.cable_lengths(pose)
    lddot_fd = (l_plus - 2 * l0 + l_minus) / (h * h)
    lddot = robot.jacobian(pose) @ accel + robot.bias_accel(pose, twist)
    np.testing.assert_allclose(lddot, lddot_fd, atol=2e-5)
    ldot_fd = (l_plus - l_minus) / (2 * h)
    np.testing.assert_allclose(robot.jacobian(pose) @ twist, ldot_fd, atol=1e-6)


@given(offset=workspace_poses(reach=0.5, tilt=0.4), twist=twists())
def test_fast_path_equals_reference(robot: Robot, offset, twist) -> None:
    pose = pose_near_home(robot, offset)
    lengths, Lam = robot.lengths_and_jacobian(pose)
    ref_lengths, _ = ref.lengths_directions(robot, pose)
    np.testing.assert_allclose(lengths, ref_lengths, rtol=0, atol=1e-13)
    np.testing.assert_allclose(Lam, ref.jacobian(robot, pose), rtol=0, atol=1e-13)
    np.testing.assert_allclose(
        robot.bias_accel(pose, twist), ref.bias_accel(robot, pose, twist), rtol=0, atol=1e-12
    )


def test_lengths_at_home_are_the_geometric_distances(reference8: Robot) -> None:
    home = reference8.home
    d = home.position + reference8.geometry.attachments - reference8.geometry.anchors
    np.testing.assert_allclose(reference8.cable_lengths(home), np.linalg.norm(d, axis=1))


def test_pulley_adds_the_wrapped_arc() -> None:
    """A cable running up the axis into a 0.1 m pulley and straight down beside it wraps
    half the pulley: l = pi r + the vertical drop, leaving at 2 r from the axis."""
    from cdpr.kinematics import CableGeometry

    r = 0.1
    geometry = CableGeometry(np.zeros((1, 3)), np.zeros((1, 3)), [(r, (0.0, 0.0, 1.0))])
    table, lengths = geometry.table((2 * r, 0.0, -1.0), (1.0, 0.0, 0.0, 0.0))
    assert lengths[0] == pytest.approx(np.pi * r + 1.0, abs=1e-12)
    np.testing.assert_allclose(table[0, :3], [0, 0, -1], atol=1e-12)


def test_stretch_correction_inverts_the_cable_law(reference8: Robot) -> None:
    """L = l (1 + t/EA), the plant's cable law solved for L; drum_lengths inverts it."""
    drum = np.linspace(1.0, 3.0, 8)
    tensions = np.linspace(20.0, 500.0, 8)
    stretched = reference8.stretched_lengths(drum, tensions)
    np.testing.assert_allclose((stretched - drum) / drum * 1e5, tensions)
    np.testing.assert_allclose(reference8.drum_lengths(stretched, tensions), drum)
