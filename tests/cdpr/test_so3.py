"""SO(3)/SE(3) helpers: exp/log round trips (near 0 and near pi), quaternions, liediff."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr import Pose, liediff, retract, so3

unit = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: np.array(v) / np.linalg.norm(v))
)


def is_rotation(R: np.ndarray) -> bool:
    return np.allclose(R @ R.T, np.eye(3), atol=1e-12) and abs(np.linalg.det(R) - 1) < 1e-12


def test_hat_is_cross_product_and_vee_inverts_it() -> None:
    w, v = np.array([0.3, -1.2, 2.0]), np.array([-0.7, 0.1, 0.4])
    np.testing.assert_allclose(so3.hat(w) @ v, np.cross(w, v), atol=1e-15)
    np.testing.assert_allclose(so3.vee(so3.hat(w)), w, atol=0)


@given(axis=unit, angle=st.floats(0.0, math.pi - 1e-9))
def test_exp_log_round_trip(axis: np.ndarray, angle: float) -> None:
    w = angle * axis
    R = so3.exp_so3(w)
    assert is_rotation(R)
    np.testing.assert_allclose(so3.log_so3(R), w, atol=1e-12)


@given(axis=unit, eps=st.floats(0.0, 1e-6))
def test_log_is_accurate_within_1e6_of_pi(axis: np.ndarray, eps: float) -> None:
    """arccos-based logs lose ~sqrt(eps) digits here; ours must not."""
    angle = math.pi - eps
    w = so3.log_so3(so3.exp_so3(angle * axis))
    # near pi, w and -w (angle 2 pi - angle) only coincide at exactly pi
    if eps < 1e-12:
        w = w if w @ axis >= 0 else -w
    np.testing.assert_allclose(w, angle * axis, atol=1e-12)


@given(axis=unit, angle=st.floats(0.0, 1e-5))
def test_exp_log_accurate_near_zero(axis: np.ndarray, angle: float) -> None:
    w = angle * axis
    R = so3.exp_so3(w)
    # first-order truth: R = I + [w]x + O(angle^2)
    np.testing.assert_allclose(
        R, np.eye(3) + so3.hat(w) + 0.5 * so3.hat(w) @ so3.hat(w), atol=1e-18
    )
    np.testing.assert_allclose(so3.log_so3(R), w, atol=1e-18, rtol=1e-12)


@given(axis=unit, angle=st.floats(0.0, math.pi))
def test_quaternion_matrix_round_trip_and_sign(axis: np.ndarray, angle: float) -> None:
    q = so3.quat_from_rotvec(angle * axis)
    assert q[0] >= 0.0
    R = so3.quat_to_matrix(q)
    np.testing.assert_allclose(so3.quat_to_matrix(-q), R, atol=0)  # q and -q: same rotation
    q2 = so3.quat_from_matrix(R)
    # the same quaternion up to the sign ambiguity at exactly w == 0
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-12
    np.testing.assert_allclose(R, so3.exp_so3(angle * axis), atol=1e-14)


def test_pose_canonicalises_sign_and_rejects_non_unit() -> None:
    a = Pose((0, 0, 1), (-0.5, -0.5, -0.5, -0.5))
    b = Pose((0, 0, 1), (0.5, 0.5, 0.5, 0.5))
    assert a == b
    np.testing.assert_array_equal(a.rotation, b.rotation)
    with pytest.raises(ValueError, match="norm"):
        Pose((0, 0, 0), (1.0, 0.1, 0.0, 0.0))
    with pytest.raises(ValueError, match="non-finite"):
        Pose((0, float("nan"), 0))
    with pytest.raises(ValueError, match="3 components"):
        Pose((0, 0))


def test_pose_arrays_are_read_only() -> None:
    pose = Pose((1, 2, 3))
    with pytest.raises(ValueError):
        pose.position[0] = 5.0
    assert pose.as_dict() == {
        "position": [1.0, 2.0, 3.0],
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
    }


@given(
    p1=st.tuples(*[st.floats(-2, 2)] * 3),
    p2=st.tuples(*[st.floats(-2, 2)] * 3),
    a1=unit,
    a2=unit,
    t1=st.floats(0, 3.0),
    t2=st.floats(0, 3.0),
)
def test_liediff_and_retract_are_inverse(p1, p2, a1, a2, t1, t2) -> None:
    eta1 = Pose.from_rotvec(p1, t1 * a1)
    eta2 = Pose.from_rotvec(p2, t2 * a2)
    theta = liediff(eta1, eta2)
    back = retract(eta1, theta)
    np.testing.assert_allclose(back.position, eta2.position, atol=1e-12)
    np.testing.assert_allclose(back.rotation, eta2.rotation, atol=1e-12)
    assert np.linalg.norm(theta[3:]) <= math.pi + 1e-12


def test_liediff_convention_is_mixed_world_frame() -> None:
    """liediff(eta1, eta2) = (p2 - p1, log(R2 R1^T)): a world-frame rotation vector."""
    R1 = so3.exp_so3([0.0, 0.0, math.pi / 2])
    eta1 = Pose.from_matrix((1, 0, 0), R1)
    w = np.array([0.1, 0.0, 0.0])  # a rotation about the WORLD x axis
    eta2 = Pose.from_matrix((1, 2, 0), so3.exp_so3(w) @ R1)
    np.testing.assert_allclose(liediff(eta1, eta2), [0, 2, 0, 0.1, 0, 0], atol=1e-15)


def test_batched_rotations_match_scipy_and_the_single_call() -> None:
    """exp_so3 and quat_from_matrix over an array of rotations (the path timing's grid)
    give scipy's Rotation (an independent implementation) and what each gives alone:
    random turns up to nearly pi, zero, one below the series' threshold and pi itself."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    w = rng.normal(size=(500, 3))
    w *= rng.uniform(0.0, 3.1, (500, 1)) / np.linalg.norm(w, axis=1)[:, None]
    w[:3] = [[0.0, 0.0, 0.0], [1e-6, 0.0, 0.0], [np.pi, 0.0, 0.0]]
    R = so3.exp_so3(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    q = so3.quat_from_matrix(R)
    theirs = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]  # scalar last there
    theirs *= np.where(theirs[:, :1] < 0.0, -1.0, 1.0)
    np.testing.assert_allclose(q[3:], theirs[3:], atol=1e-14)  # w > 0: one sign
    np.testing.assert_allclose(np.abs(q[2]), [0.0, 1.0, 0.0, 0.0], atol=1e-15)  # pi
    for k in (0, 1, 2, 250):
        np.testing.assert_array_equal(R[k], so3.exp_so3(w[k]))
        np.testing.assert_array_equal(q[k], so3.quat_from_matrix(R[k]))
