"""Pose limits (cdpr.pose_limits) and trajectory validation against them (DESIGN §7, §9):
the box and the tilt, the margins that make a validated reference safe for the runtime
check on the measured pose, the sampling margin, and the messages."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot, liediff
from cdpr.pose_limits import ROUNDING, PoseLimits, tilt
from cdpr.so3 import exp_so3
from cdpr.trajectory import (
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    Waypoint,
    check_start_delay,
    sampled_pose_limits,
    validate,
)

LIMITS = TrajectoryLimits()
IDENTITY = (1.0, 0.0, 0.0, 0.0)
# the reference8 frame's box, lowered to a 1.6 m fence, and 0.6 rad of tilt
BOX = PoseLimits((-1.5, -1.5, 0.0), (1.5, 1.5, 1.6), IDENTITY, 0.6)
HOME = np.array([0.0, 0.0, 1.25])


def at(position, rotvec=(0.0, 0.0, 0.0)) -> Pose:
    return Pose.from_rotvec(np.asarray(position, dtype=float), rotvec)


def rejected(tr: Trajectory, robot: Robot, pose_limits: PoseLimits) -> TrajectoryError:
    with pytest.raises(TrajectoryError) as info:
        validate(tr, robot, LIMITS, pose_limits=pose_limits)
    return info.value


# -- the limits ---------------------------------------------------------------------------


def test_the_box_names_the_side_the_axis_and_the_value() -> None:
    assert BOX.violation(at(HOME)) is None
    assert BOX.violation(at([1.5, -1.5, 0.0])) is None  # the faces belong to the box
    low = BOX.violation(at([0.0, 0.0, -0.5]))
    assert (low.limit, low.value) == ("workspace_min", -0.5)
    assert low.detail == "position z = -0.5000 m outside [0.0000, 1.6000] m"
    high = BOX.violation(at([0.0, 1.7, 1.25]))
    assert (high.limit, high.value) == ("workspace_max", 1.7)
    assert "position y = 1.7000 m" in high.detail


def test_the_tilt_is_the_rotation_angle_from_home_about_any_axis() -> None:
    for axis in np.eye(3):
        assert BOX.violation(at(HOME, 0.59 * axis)) is None
        bad = BOX.violation(at(HOME, 0.61 * axis))
        assert bad.limit == "tilt_max" and bad.value == pytest.approx(0.61)
        assert bad.detail == "rotation 34.95 deg from home exceeds 34.38 deg"
    # from a home that is not the identity
    home = at(HOME, (0.0, 0.0, 1.0))
    limits = PoseLimits(BOX.lower, BOX.upper, home.quaternion_tuple, 0.6)
    assert limits.violation(home) is None
    assert limits.violation(at(HOME)).limit == "tilt_max"  # 1 rad from that home


def test_the_box_is_checked_before_the_tilt() -> None:
    assert BOX.violation(at([0.0, 0.0, 2.0], (1.0, 0.0, 0.0))).limit == "workspace_max"


def test_shrunk_moves_every_face_in_and_says_so() -> None:
    inner = BOX.shrunk(0.02, 0.05)
    assert inner.lower == pytest.approx((-1.48, -1.48, 0.02), abs=1e-8)
    assert inner.upper == pytest.approx((1.48, 1.48, 1.58), abs=1e-8)
    assert inner.tilt_max == pytest.approx(0.55, abs=1e-8)
    assert inner.margin == pytest.approx((0.02, 0.05), abs=1e-8)
    bad = inner.violation(at([0.0, 0.0, 1.59]))
    assert bad.limit == "workspace_max"
    assert "(the configured limit less a margin of 0.02 m)" in bad.detail
    bad = inner.violation(at(HOME, (0.56, 0.0, 0.0)))
    assert "(the configured limit less a margin of 0.05 rad)" in bad.detail
    assert BOX.shrunk(0.9, 0.0).violation(at(HOME)) is not None  # z in [0.9, 0.7]: empty


def test_widened_to_holds_the_pose_and_the_limits_and_no_more() -> None:
    inner = BOX.shrunk(0.02, 0.05)
    low = at([0.0, 0.0, 0.01], (0.0, 0.57, 0.0))  # below the shrunk floor, tilted beyond
    wide = inner.widened_to(low)
    assert wide.violation(low) is None
    assert wide.violation(at([0.0, 0.0, 0.009])).limit == "workspace_min"
    assert wide.violation(at(HOME, (0.0, 0.58, 0.0))).limit == "tilt_max"
    assert wide.upper == inner.upper and inner.widened_to(at(HOME)) == inner


unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)


@settings(max_examples=300)
@given(
    inside=st.tuples(*[st.floats(0.0, 1.0)] * 3),
    rotvec=st.tuples(*[st.floats(-0.3, 0.3)] * 3),  # |rotvec| < 0.55
    towards=unit,
    about=unit,
    scale=st.floats(0.0, 1.0),
)
def test_within_the_margins_of_a_pose_inside_shrunk_is_inside(
    inside, rotvec, towards, about, scale
) -> None:
    """The soundness of shrunk: any pose within (position, orientation) of a pose inside
    the shrunk limits passes the unshrunk check, the worst direction included."""
    e_p, e_r = 0.02, 0.05
    inner = BOX.shrunk(e_p, e_r)
    lo, hi = np.array(inner.lower), np.array(inner.upper)
    reference = Pose.from_rotvec(lo + np.array(inside) * (hi - lo), rotvec)
    assert inner.violation(reference) is None
    dp = np.array(towards) / np.linalg.norm(towards) * e_p * scale
    dr = np.array(about) / np.linalg.norm(about) * e_r * scale
    measured = Pose.from_matrix(reference.position + dp, exp_so3(dr) @ reference.rotation)
    assert np.linalg.norm(liediff(reference, measured)[3:]) <= e_r + 1e-12
    assert BOX.violation(measured) is None
    # the worst case: straight out through the nearest face, turned on away from home
    p = reference.position
    face = int(np.argmin(np.minimum(p - lo, hi - p)))
    out = np.zeros(3)
    out[face] = -e_p if p[face] - lo[face] < hi[face] - p[face] else e_p
    rv = np.asarray(rotvec)
    angle = np.linalg.norm(rv)
    turn = rv / angle * e_r if angle > 1e-6 else np.array([e_r, 0.0, 0.0])
    worst = Pose.from_matrix(p + out, exp_so3(turn) @ reference.rotation)
    assert BOX.violation(worst) is None
    assert tilt(worst, IDENTITY) == pytest.approx(max(angle, 1e-6) + e_r, abs=2e-6)


# -- validation -----------------------------------------------------------------------------


def test_a_waypoint_below_the_floor_is_named(reference8: Robot) -> None:
    inner = BOX.shrunk(0.02, 0.05)
    tr = Trajectory(
        [
            Waypoint(0.0, at(HOME)),
            Waypoint(3.0, at([0.0, 0.0, 0.5])),
            Waypoint(6.0, at([0.0, 0.0, -0.5])),
        ]
    )
    err = rejected(tr, reference8, inner)
    assert (err.waypoint, err.limit, err.value) == (2, "workspace_min", -0.5)
    assert str(err).startswith("waypoint 2: workspace_min: position z = -0.5000 m outside [")
    assert str(err).endswith("0.02 m) at t=6 s")
    validate(tr, reference8, LIMITS)  # every other limit lets it through


def test_a_path_overshooting_between_its_waypoints_names_the_segment(reference8: Robot) -> None:
    """Every waypoint inside, the spline between two of them beyond the fence: named by
    the segment (the waypoint that starts it) and the instant."""
    inner = BOX.shrunk(0.02, 0.05)
    zs = [1.25, 1.57, 1.57, 1.25]
    tr = Trajectory(
        [Waypoint(t, at([0.0, 0.0, z])) for t, z in zip([0, 1, 1.4, 3], zs, strict=True)]
    )
    peak = max(tr.sample(t).pose.position[2] for t in np.linspace(1.0, 1.4, 401))
    assert peak > inner.upper[2]  # the premise: it overshoots
    err = rejected(tr, reference8, inner)
    assert (err.waypoint, err.limit) == (1, "workspace_max")
    assert inner.upper[2] < err.value <= peak
    assert "at t=1." in str(err)


def test_a_turn_beyond_the_tilt_is_named(reference8: Robot) -> None:
    inner = BOX.shrunk(0.02, 0.05)
    tr = Trajectory([Waypoint(0.0, at(HOME)), Waypoint(3.0, at(HOME, (0.8, 0.0, 0.0)))])
    err = rejected(tr, reference8, inner)
    assert (err.waypoint, err.limit) == (1, "tilt_max") and err.value == pytest.approx(0.8)
    assert "rotation 45.84 deg from home exceeds 31.51 deg" in str(err)
    assert "less a margin of 0.05 rad" in str(err) and "at t=3 s" in str(err)


def test_sampling_margin_follows_the_accel_limits() -> None:
    h = LIMITS.sample_period
    sampled = sampled_pose_limits(BOX, LIMITS)
    lin = LIMITS.linear_accel * h * h / 8
    assert sampled.upper[2] == pytest.approx(BOX.upper[2] - lin - ROUNDING, abs=1e-12)
    delta = (LIMITS.angular_accel / 2 + LIMITS.angular_speed**2 / 4) * h * h / 8
    expected = 2 * math.acos(math.cos(BOX.tilt_max / 2) + delta)
    assert sampled.tilt_max == pytest.approx(expected - ROUNDING, abs=1e-12)
    assert 0.0 < BOX.tilt_max - sampled.tilt_max < 1e-3  # small at the defaults


@settings(max_examples=40)
@given(
    zs=st.lists(st.floats(1.0, 1.6), min_size=2, max_size=5),
    angles=st.lists(st.floats(-0.6, 0.6), min_size=5, max_size=5),
    gaps=st.lists(st.floats(0.3, 1.5), min_size=5, max_size=5),
)
def test_between_the_samples_the_path_stays_inside(reference8: Robot, zs, angles, gaps) -> None:
    """What validation accepts with the sampled limits stays inside the path limits at
    every instant, not only at the samples (checked 20 times finer)."""
    times = np.cumsum([0.0, *gaps[: len(zs) - 1]])
    tr = Trajectory(
        [
            Waypoint(t, at([0.0, 0.0, z], (a, 0.3 * a, 0.0)))
            for t, z, a in zip(times, zs, angles, strict=False)
        ]
    )
    sampled = sampled_pose_limits(BOX, LIMITS)
    try:
        validate(tr, reference8, LIMITS, pose_limits=sampled)
    except TrajectoryError:
        return
    for t in np.arange(tr.start_time, tr.end_time, LIMITS.sample_period / 20):
        assert BOX.violation(tr.sample(float(t)).pose) is None


def test_validation_yields_while_it_checks_the_waypoints(reference8: Robot) -> None:
    """The waypoints' poses are checked CHUNK at a time, a step each (a long trajectory
    must not hold the event loop), before the first sample."""
    from cdpr.trajectory import validation_steps
    from cdpr.trajectory.limits import CHUNK

    count = 2 * CHUNK + 1
    tr = Trajectory(
        [Waypoint(0.1 * k, at(HOME + np.array([0.0001 * k, 0.0, 0.0]))) for k in range(count)]
    )
    steps = list(validation_steps(tr, reference8, LIMITS, None, BOX))
    plain = list(validation_steps(tr, reference8, LIMITS))
    assert len(steps) == len(plain) + 3
    assert steps[:3] == [tr.waypoints[CHUNK - 1].t, tr.waypoints[2 * CHUNK - 1].t, tr.end_time]


def test_a_start_too_far_ahead_is_refused() -> None:
    check_start_delay(60.0, LIMITS)
    with pytest.raises(TrajectoryError) as info:
        check_start_delay(11.6 * 86400, LIMITS)
    err = info.value
    assert (err.limit, err.waypoint, err.value) == ("max_start_delay", 0, 11.6 * 86400)
    assert str(err) == (
        "waypoint 0: max_start_delay: the start lies 1.00224e+06 s ahead, beyond the limit 60 s"
    )
    with pytest.raises(TrajectoryError):
        check_start_delay(math.nan, LIMITS)


@pytest.mark.parametrize("value", [True, "60", math.inf, 0.0, -1.0])
def test_max_start_delay_is_strictly_a_positive_number(value) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="max_start_delay"):
        TrajectoryLimits.model_validate({"max_start_delay": value})
    assert TrajectoryLimits.model_validate({"max_start_delay": 5}).max_start_delay == 5.0
