"""Jerk limits (cdpr.trajectory.jerk): the jerk each segment reaches, held to the rate of
the accelerations the trajectory samples; validation names a segment over a limit; a goto
from rest is the time-optimal double-S profile Ruckig finds; goto, approach and stop keep
the limits from any state of motion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot, liediff
from cdpr.trajectory import (
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    Waypoint,
    approach,
    goto,
    run_steps,
    stop_steps,
    validate,
    validation_steps,
)
from cdpr.trajectory.jerk import JERK_SAMPLES, segment_jerks
from tests.cdpr.test_trajectory import (
    HOME,
    TRAJECTORIES,
    assert_arrives_at_rest,
    assert_same_state,
    assert_within,
    at_rest,
    line,
    moving_state,
    peak_rates,
    planned,
)

JERKY = TrajectoryLimits(linear_jerk=30.0, angular_jerk=60.0)


def sampled_jerks(tr: Trajectory, per_segment: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Per segment, the largest rate of the accelerations `sample` gives (central
    differences at `per_segment` instants across it): the independent route."""
    starts, _, durations = tr.curve.segments()
    linear, angular = [], []
    for t0, h in zip(starts, durations, strict=True):
        d = 1e-6 * h  # the ends too, each difference inside its own segment
        times = t0 + 2 * d + (h - 4 * d) * np.linspace(0.0, 1.0, per_segment)
        rates = np.array(
            [(tr.sample(t + d).accel - tr.sample(t - d).accel) / (2 * d) for t in times]
        )
        linear.append(np.linalg.norm(rates[:, :3], axis=1).max())
        angular.append(np.linalg.norm(rates[:, 3:], axis=1).max())
    return np.array(linear), np.array(angular)


@pytest.mark.parametrize("name", sorted(TRAJECTORIES))
def test_each_segment_s_jerk_is_the_rate_of_the_sampled_accelerations(name: str) -> None:
    tr = TRAJECTORIES[name]()
    ours = segment_jerks(*tr.curve.segments()[1:])
    dense = sampled_jerks(tr)
    for mine, theirs in zip(ours, dense, strict=True):
        # JERK_SAMPLES + 1 instants per segment against 200: the same peaks, or a little below
        assert np.all(mine <= theirs * (1 + 1e-4) + 1e-6)
        np.testing.assert_allclose(mine, theirs, rtol=0.5 / JERK_SAMPLES, atol=1e-9)


def test_a_rest_to_rest_segment_peaks_at_sixty_times_distance_over_duration_cubed() -> None:
    """The minimum-jerk s = 10τ³ - 15τ⁴ + 6τ⁵ has s''' = 60 at both ends."""
    start = Pose.from_rotvec(HOME, (0.0, 0.0, 0.0))
    moved = Pose.from_rotvec(HOME + np.array([0.12, -0.05, 0.0]), (0.0, 0.0, 0.0))
    turned = Pose.from_rotvec(HOME, (0.0, 0.3, 0.4))
    for target, distance in ((moved, 0.13), (turned, 0.5)):
        tr = Trajectory([Waypoint(0.0, start), Waypoint(0.8, target)])
        linear, angular = segment_jerks(*tr.curve.segments()[1:])
        peak = linear if target is moved else angular
        assert peak[0] == pytest.approx(60.0 * distance / 0.8**3, rel=1e-7)


def test_validation_names_the_segment_over_a_jerk_limit(reference8: Robot) -> None:
    tr = line(reference8, [0.0, 2.0, 3.0, 5.0], [0.0, 0.02, 0.32, 0.32], stop=True)
    linear, _ = segment_jerks(*tr.curve.segments()[1:])
    assert linear.argmax() == 1  # 0.3 m in 1 s: 18 m/s³
    validate(tr, reference8, TrajectoryLimits(linear_jerk=linear.max() * 1.001))
    with pytest.raises(TrajectoryError) as info:
        validate(tr, reference8, TrajectoryLimits(linear_jerk=linear.max() * 0.999))
    err = info.value
    assert (err.waypoint, err.limit) == (1, "linear_jerk")
    assert err.value == pytest.approx(linear.max()) and "between t=2 s and t=3 s" in str(err)
    turns = line(reference8, [0.0, 1.0], [0.0, 0.0], [(0.0, 0.0, 0.0), (0.0, 0.0, 0.4)])
    _, angular = segment_jerks(*turns.curve.segments()[1:])
    with pytest.raises(TrajectoryError, match="angular_jerk") as info:
        validate(turns, reference8, TrajectoryLimits(angular_jerk=angular.max() * 0.999))
    assert f"{angular.max():.6g} rad/s³ exceeds the limit" in str(info.value)


def ruckig_profile(distances: list[float], limits: TrajectoryLimits):
    """Ruckig's time-optimal rest-to-rest trajectory of the line's distance and the
    geodesic's angle within `limits` (the independent reference)."""
    from ruckig import InputParameter, Result, Ruckig
    from ruckig import Trajectory as RuckigTrajectory

    inp = InputParameter(2)
    inp.current_position, inp.target_position = [0.0, 0.0], distances
    inp.max_velocity = [limits.linear_speed, limits.angular_speed]
    inp.max_acceleration = [limits.linear_accel, limits.angular_accel]
    inp.max_jerk = [limits.linear_jerk, limits.angular_jerk]
    out = RuckigTrajectory(2)
    assert Ruckig(2).calculate(inp, out) == Result.Working
    return out


@pytest.mark.parametrize(
    ("dp", "rotvec"),
    [
        ((0.05, 0.0, 0.0), (0.0, 0.0, 0.0)),  # the jerk binds
        ((0.3, 0.4, -0.2), (0.0, 0.0, 0.0)),  # the acceleration too
        ((1.2, 0.9, 0.0), (0.0, 0.0, 0.0)),  # and the speed
        ((0.0, 0.0, 0.0), (0.25, 0.0, 0.5)),  # a turn
        ((0.2, -0.1, 0.05), (0.1, 0.3, 0.0)),  # both, the slower one sets the time
    ],
)
def test_a_goto_from_rest_under_jerk_limits_is_time_optimal_as_ruckig_finds(dp, rotvec) -> None:
    """From rest with the jerk limited, a goto is the double-S profile along the line and
    the geodesic: as long as Ruckig's time-optimal trajectory (an independent
    implementation) of the distance and the angle within the same limits, and where one
    of them sets that time, the same profile as Ruckig's along it; within every limit."""
    start = Pose.from_rotvec(HOME, (0.0, 0.0, 0.0))
    target = Pose.from_rotvec(HOME + np.array(dp), rotvec)
    tr = goto(at_rest(start), target, JERKY, start=2.0)
    assert tr.start_time == 2.0
    assert_arrives_at_rest(tr, target)
    step = liediff(start, target)
    distances = [float(np.linalg.norm(step[:3])), float(np.linalg.norm(step[3:]))]
    reference = ruckig_profile(distances, JERKY)
    assert tr.duration == pytest.approx(reference.duration, rel=1e-5)  # limits x (1 - 1e-6)
    alone = [ruckig_profile([d if i == k else 0.0 for i, d in enumerate(distances)], JERKY)
             for k in range(2)]  # fmt: skip
    binding = int(alone[1].duration > alone[0].duration)
    part = slice(0, 3) if binding == 0 else slice(3, 6)
    axis = step[part] / distances[binding]
    for t in np.linspace(0.0, tr.duration, 57):
        ours = tr.sample(2.0 + t)
        position, speed, accel = (x[binding] for x in reference.at_time(t))
        assert liediff(start, ours.pose)[part] == pytest.approx(position * axis, abs=1e-5)
        assert ours.twist[part] == pytest.approx(speed * axis, abs=1e-5)
        assert ours.accel[part] == pytest.approx(accel * axis, abs=1e-4)
        assert np.linalg.norm(np.cross(liediff(start, ours.pose)[3:], step[3:])) < 1e-12
    assert_within(peak_rates(tr, 20001), JERKY)
    linear, angular = sampled_jerks(tr, 50)
    assert linear.max() <= JERKY.linear_jerk and angular.max() <= JERKY.angular_jerk


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 10**6), st.floats(0.0, 0.9))
def test_transitions_from_any_state_of_motion_keep_the_jerk_limits(seed: int, speed: float) -> None:
    """goto and approach (a new target mid-motion: no stop first) and a stop, each from a
    moving, accelerating reference: C2 at the start, within the jerk limits throughout
    (dense samples; the check takes JERK_SAMPLES + 1 instants: 2 % allowed between)."""
    current = moving_state(seed, speed)
    target = Pose.from_rotvec(HOME + np.array([0.1, -0.2, 0.05]), (0.3, 0.0, -0.2))
    flights = (
        goto(current, target, JERKY, start=1.0),
        approach(current, planned(seed + 1), JERKY, start=1.0),
        run_steps(stop_steps(current, JERKY, start=1.0)),
    )
    for tr in flights:
        assert_same_state(tr.sample(1.0), current, 1e-12)
        assert_same_state(tr.sample(math.nextafter(1.0, 2.0)), current, 1e-9)
        linear, angular = sampled_jerks(tr, 200)
        assert linear[0] <= JERKY.linear_jerk * 1.02 and angular[0] <= JERKY.angular_jerk * 1.02
    assert_arrives_at_rest(flights[0], target)


def test_a_jerk_limited_approach_passes_validation(reference8: Robot) -> None:
    tr = approach(moving_state(3, 0.8), planned(4), JERKY)
    list(validation_steps(tr, reference8, JERKY, segments=1))  # the blend, where it lies


def test_a_goto_whose_profile_has_a_phase_too_short_for_a_waypoint_keeps_the_jerk_limit() -> None:
    """A double-S phase shorter than MIN_SEGMENT gets no waypoint of its own, and the
    quintic across it passed the jerk limit by a few millionths (0.3 m at 1 m/s, 5 m/s²,
    50 m/s³: 50.0002 m/s³, which the daemon's validation refused in its own goto): the
    profile is slowed down by what it leaves.  Validation's measure on 0.01-0.6 m."""
    limits = TrajectoryLimits(linear_speed=1.0, linear_accel=5.0, linear_jerk=50.0)
    start = Pose.from_rotvec(HOME, (0.0, 0.0, 0.0))
    for distance in np.linspace(0.01, 0.6, 60):
        target = Pose.from_rotvec(HOME + np.array([distance, 0.0, 0.0]), (0.0, 0.0, 0.0))
        tr = goto(at_rest(start), target, limits)
        linear, _ = segment_jerks(*tr.curve.segments()[1:])
        assert linear.max() <= 50.0, f"{distance:.3f} m: {linear.max()} m/s³"
        assert_arrives_at_rest(tr, target)
