"""The cable-length bounds validation holds a reference to (DESIGN §7): inside them, the
lengths the drives measure stay inside the robot's [length_min, length_max], which the
runtime brakes on, however the measured pose strays within the tracking bounds and
however hard the cables pull."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot
from cdpr.so3 import exp_so3
from cdpr.trajectory import (
    LengthLimits,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    Waypoint,
    tracked_length_limits,
    validate,
)
from tests.conftest import ROBOTS

LIMITS = TrajectoryLimits()
E_P, E_R = 0.02, 0.05  # the example configs' tracking-error bounds (m, rad)


def robot_with_lengths(lo: float, hi: float) -> Robot:
    """reference8 with every cable limited to [lo, hi] m."""
    data = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    data["actuator"].update(length_min=lo, length_max=hi)
    return Robot.from_dict(data)


def test_the_margins_are_the_pose_the_samples_and_the_stretch(reference8: Robot) -> None:
    bounds = tracked_length_limits(reference8, E_P, E_R, LIMITS)
    b = np.linalg.norm(reference8.geometry.attachments, axis=1)
    lo, hi = reference8.length_min, reference8.length_max
    accel = LIMITS.linear_accel + b * LIMITS.angular_accel
    accel += (LIMITS.linear_speed + b * LIMITS.angular_speed) ** 2 / lo
    margin = E_P + b * E_R + accel * LIMITS.sample_period**2 / 8
    stretch = 1.0 + reference8.compliance * reference8.force_max
    assert np.allclose(bounds.upper, hi - margin)
    assert np.allclose(bounds.lower, (lo + margin) * stretch)
    assert np.all(np.array(bounds.lower) > lo) and np.all(np.array(bounds.upper) < hi)


def test_violation_names_the_first_cable_outside_and_widened_to_holds_a_start() -> None:
    bounds = LengthLimits((1.0, 1.0, 1.0), (2.0, 2.0, 2.0))
    assert bounds.violation([1.5, 1.5, 1.5]) is None
    assert bounds.violation([1.5, 2.1, 0.9]) == (1, 2.1, 1.0, 2.0)
    wide = bounds.widened_to([1.5, 2.1, 0.9])
    assert wide.lower == (1.0, 1.0, 0.9) and wide.upper == (2.0, 2.1, 2.0)
    assert wide.violation([1.5, 2.1, 0.9]) is None
    assert wide.violation([1.5, 2.11, 0.9]) == (1, 2.11, 1.0, 2.1)  # no further out


def test_a_reference_inside_the_raw_limits_but_not_the_margins_is_refused(
    reference8: Robot,
) -> None:
    home = reference8.home
    away = Pose.from_rotvec(home.position + np.array([0.12, 0.12, 0.0]), (0.0, 0.0, 0.0))
    longest = float(reference8.cable_lengths(away).max())
    robot = robot_with_lengths(0.3, longest + 0.01)  # 1 cm to spare: the runtime is fine
    tr = Trajectory([Waypoint(0.0, home), Waypoint(3.0, away)])
    validate(tr, robot, LIMITS)  # the raw limits let it through
    bounds = tracked_length_limits(robot, E_P, E_R, LIMITS)
    with pytest.raises(TrajectoryError) as info:
        validate(tr, robot, LIMITS, length_limits=bounds)
    err = info.value
    assert err.limit == "cable_length" and err.waypoint == 0  # the segment it ends on
    assert "less the tracking, sampling and stretch margins" in str(err)
    assert max(bounds.upper) < err.value <= longest


@settings(max_examples=200, deadline=None)
@given(
    offset=st.tuples(*[st.floats(-0.3, 0.3)] * 3),
    turn=st.tuples(*[st.floats(-0.2, 0.2)] * 3),
    direction=st.tuples(*[st.floats(-1.0, 1.0)] * 6),
    tensions=st.lists(st.floats(0.0, 1.0), min_size=8, max_size=8),
)
@pytest.mark.slow  # over 5 s of the default run's 10 minutes
def test_measured_lengths_stay_inside_the_raw_limits(
    offset: tuple, turn: tuple, direction: tuple, tensions: list
) -> None:
    """A reference whose lengths are inside the bounds, a measured pose at the tracking
    bounds in any direction, any tension up to force_max: the drum lengths the drives
    report stay inside [length_min, length_max].  The limits are drawn tight around the
    reference (a cable at each bound), so the margins alone decide."""
    robot = robot_with_lengths(0.3, 4.2)
    ref = Pose.from_rotvec(robot.home.position + np.array(offset), turn)
    ell = robot.cable_lengths(ref)
    bounds = tracked_length_limits(robot, E_P, E_R, LIMITS)
    stretch = 1.0 + robot.compliance * robot.force_max
    low_margin = np.array(bounds.lower) / stretch - robot.length_min
    high_margin = robot.length_max - np.array(bounds.upper)
    # the tightest robot limits that keep this reference inside the bounds (its margins
    # only shrink with a longer length_min): a cable sits on each bound
    tight = robot_with_lengths(
        float(np.min(ell / stretch - low_margin)), float(np.max(ell + high_margin))
    )
    assert tracked_length_limits(tight, E_P, E_R, LIMITS).violation(ell.tolist()) is None
    d = np.array(direction)
    dp = d[:3] / max(np.linalg.norm(d[:3]), 1e-12) * E_P
    dr = d[3:] / max(np.linalg.norm(d[3:]), 1e-12) * E_R
    measured = Pose.from_matrix(ref.position + dp, exp_so3(dr) @ ref.rotation)
    geometric = tight.cable_lengths(measured)
    drum = tight.drum_lengths(geometric, np.array(tensions) * tight.force_max)
    assert np.all(drum >= tight.length_min - 1e-12), (drum.min(), tight.length_min[0])
    assert np.all(drum <= tight.length_max + 1e-12), (drum.max(), tight.length_max[0])
