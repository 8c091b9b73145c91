"""Jump-free transitions from the current reference: `goto` a pose, `approach` a trajectory.

Both are one quintic Hermite segment between two states (pose, twist, accel), the same
segment every Trajectory is made of, so the reference stays C² across the joints.  From
rest to rest the segment is the minimum-jerk profile along the straight line and the
geodesic, and its duration has a closed form; otherwise the shortest duration whose
sampled speeds, accelerations and jerks respect the limits is searched for.  A goto from
rest where the jerk is limited is instead the fastest double-S profile along the line
and the geodesic (cdpr.trajectory.double_s: time-optimal within the speed, acceleration
and jerk limits; the minimum-jerk quintic takes 1.23x as long where the jerk binds, 1.2x
where the acceleration does, up to 1.875x at the speed limit), a waypoint at each of its
phase boundaries.  Where no duration of the one segment keeps the limits (a reference
accelerating hard with the jerk bounded: shorter segments break the jerk limit, longer
ones carry the acceleration past the speed limit), the acceleration is first ramped to
zero at the jerk limits, and the segment follows from there (_ramp_first).

The search checks a few dozen candidate durations, 127 samples each.  `goto_steps` and
`approach_steps` are the same functions as generators that yield after every candidate
(`run_steps` drives one to its result): a daemon planning while its control cycle runs on
the same event loop can return to the loop between candidates.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from typing import TypeVar

import numpy as np

from cdpr.pose import Pose, liediff, retract
from cdpr.trajectory.core import (
    MIN_SEGMENT,
    Reference,
    Trajectory,
    TrajectoryError,
    Waypoint,
    segment_rates,
    segment_table,
)
from cdpr.trajectory.double_s import DoubleS
from cdpr.trajectory.jerk import jerk_excess, jerk_stretch, jerk_violation
from cdpr.trajectory.limits import TrajectoryLimits, first_rate_violation, rate_violation
from cdpr.trajectory.rotation import angular_rates

MIN_BLEND = 1e-3  # s: the shortest transition (a goto to where the reference already is)
_PEAK_SPEED = 15.0 / 8.0  # max of s'(τ) for the minimum-jerk s = 10τ³ - 15τ⁴ + 6τ⁵
_PEAK_ACCEL = 10.0 / math.sqrt(3.0)  # max of |s''(τ)|
_PEAK_JERK = 60.0  # max of |s'''(τ)|, at both ends
_CHECKS = 128  # samples per candidate duration
_SAMPLES = np.arange(1, _CHECKS) / _CHECKS  # the interior samples, as fractions of it
_GROW = 1.25  # candidate durations grow geometrically from a lower bound ...
_BISECTIONS = 6  # ... then the first feasible one is refined to 0.4 % (below _MARGIN)
_MARGIN = 1.02  # final duration stretch: headroom for peaks between the samples
_DIRECT_LONGEST = 10.0  # s: a segment from an accelerating reference tried up to this long
_SHARE = 1.0 - 1e-6  # of a limit a profile or ramp plans to: rounding keeps its peaks below
# of the angular jerk limit a ramp plans to: the world's jerk differs from the chart's by
# the rotation's curvature terms (3e-6 of it on a turn at 1.2 rad/s)
_ANGULAR_RAMP_SHARE = 1.0 - 1e-4

Result = TypeVar("Result")
Steps = Generator[None, None, Result]


def run_steps(steps: Steps[Result]) -> Result:
    """Drive a step generator (goto_steps, approach_steps) to its result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def goto(
    current: Reference, target: Pose, limits: TrajectoryLimits, start: float = 0.0
) -> Trajectory:
    """From the current reference state at time `start` to `target`, arriving at rest."""
    return run_steps(goto_steps(current, target, limits, start))


def goto_steps(
    current: Reference, target: Pose, limits: TrajectoryLimits, start: float = 0.0
) -> Steps[Trajectory]:
    """`goto`, yielding between candidate durations."""
    end = Reference(target, np.zeros(6), np.zeros(6))
    resting = not (np.any(current.twist) or np.any(current.accel))
    if resting and (profiled := _double_s(current.pose, target, limits, start)) is not None:
        return profiled
    leads, T = yield from _ramp_first(current, limits, lambda s, lim: _blend_duration(s, end, lim))
    leads = _placed(leads, start)
    return Trajectory([*leads, Waypoint(leads[-1].t + T, target)])


def _double_s(
    pose: Pose, target: Pose, limits: TrajectoryLimits, start: float
) -> Trajectory | None:
    """From rest at `pose` to rest at `target` along the straight line and the geodesic,
    each the fastest double-S profile within its speed, acceleration and jerk limits
    (cdpr.trajectory.double_s), the quicker one slowed to the other's duration, with a
    waypoint at each phase boundary of either.  None where nothing moves or a coordinate
    that moves has no jerk limit (its profile would step its acceleration)."""
    step = liediff(pose, target)
    moves = []
    for part, speed, accel, jerk in (
        (slice(0, 3), limits.linear_speed, limits.linear_accel, limits.linear_jerk),
        (slice(3, 6), limits.angular_speed, limits.angular_accel, limits.angular_jerk),
    ):
        distance = float(np.linalg.norm(step[part]))
        if distance == 0.0:
            continue
        if jerk is None:
            return None
        profile = DoubleS.fastest(distance, speed * _SHARE, accel * _SHARE, jerk * _SHARE)
        moves.append((part, step[part] / distance, profile))
    if not moves:
        return None
    duration = max(profile.duration for *_, profile in moves)
    moves = [(part, axis, profile.lasting(duration)) for part, axis, profile in moves]
    kept = [0.0]  # the boundaries at least MIN_SEGMENT apart, the end's too
    for t in sorted({t for *_, profile in moves for t in profile.boundaries()}):
        if t - kept[-1] >= MIN_SEGMENT and duration - t >= MIN_SEGMENT:
            kept.append(t)
    states = []
    for t in kept:
        state = np.zeros((3, 6))  # the step so far, the twist, the accel
        for part, axis, profile in moves:
            state[:, part] = np.outer(profile.at(t), axis)
        states.append((t, retract(pose, state[0]), state[1], state[2]))
    trajectory = _through(states, start, duration, target, 1.0)
    # a phase shorter than MIN_SEGMENT has no waypoint of its own, and the quintic across
    # it passes the jerk limit by a few millionths: slowed down by what it leaves (the
    # jerk falls with the cube of the stretch)
    excess = jerk_excess(trajectory, limits.linear_jerk, limits.angular_jerk)
    if excess <= 1.0:
        return trajectory
    return _through(states, start, duration, target, jerk_stretch(excess))


def _through(
    states: list[tuple[float, Pose, np.ndarray, np.ndarray]],
    start: float,
    duration: float,
    target: Pose,
    stretch: float,
) -> Trajectory:
    """The trajectory from `start` through (t, pose, twist, accel) `states` to rest at
    `target` at `duration`, its time stretched by `stretch` (>= 1)."""
    waypoints = [
        Waypoint(start + t * stretch, pose, twist / stretch, accel / stretch**2)
        for t, pose, twist, accel in states
    ]
    return Trajectory([*waypoints, Waypoint(start + duration * stretch, target)])


def approach(
    current: Reference, trajectory: Trajectory, limits: TrajectoryLimits, start: float | None = None
) -> Trajectory:
    """`trajectory` preceded by a blend from the current reference state into its start.

    The blend begins at `start` (default: so that `trajectory` keeps its own times) and
    the trajectory follows unchanged, shifted to begin where the blend ends.  No blend
    is added when the current state already is the trajectory's start state.
    """
    return run_steps(approach_steps(current, trajectory, limits, start))


def approach_steps(
    current: Reference, trajectory: Trajectory, limits: TrajectoryLimits, start: float | None = None
) -> Steps[Trajectory]:
    """`approach`, yielding between candidate durations."""
    knot = trajectory.knot(0)
    end = Reference(knot.pose, knot.twist, knot.accel)
    if current.same_as(end):
        return trajectory if start is None else trajectory.shifted(start - trajectory.start_time)
    leads, T = yield from _ramp_first(current, limits, lambda s, lim: _blend_duration(s, end, lim))
    span = leads[-1].t + T
    t0 = trajectory.start_time - span if start is None else start
    return trajectory.after_blend(_placed(leads, t0), t0 + span - trajectory.start_time)


def stop_steps(
    current: Reference, limits: TrajectoryLimits, start: float = 0.0
) -> Steps[Trajectory]:
    """From the current reference state at `start` to rest, as soon as the limits allow,
    without turning back (a step after each candidate duration checked).

    The rest pose is where the velocity, as the cubic Hermite from the current (twist,
    accel) to zero, carries it: twist T/2 + accel T²/12 in the chart of the segment.  The
    segment is then that cubic's integral (its fifth-power term is zero), so each
    coordinate's speed keeps its sign unless the reference is already braking hard; a
    fixed rest pose nearer than that makes the shortest segment overshoot and come back.
    A reference still accelerating may leave no such duration (below it the jerk, above
    it the speed is too high): its acceleration is then first brought to zero
    (_ramp_first)."""
    leads, (T, rest) = yield from _ramp_first(current, limits, lambda s, lim: _stop(s, lim))
    leads = _placed(leads, start)
    return Trajectory([*leads, Waypoint(leads[-1].t + T, rest)])


def _stop(current: Reference, limits: TrajectoryLimits) -> Steps[tuple[float, Pose]]:
    """stop_steps's one segment to rest: its duration and the rest pose."""
    _check_rates(current, "current reference", limits)

    def rest(T: float) -> tuple[Reference, np.ndarray]:
        step = current.twist * (T / 2.0) + current.accel * (T * T / 12.0)
        return Reference(retract(current.pose, step), np.zeros(6), np.zeros(6)), step

    def violation(T: float) -> tuple[str, float, str] | None:
        end, step = rest(T)
        return _violation(current, end, step, T, limits)

    # with no acceleration the peak deceleration is 1.5 speed / T: a lower bound on T
    speed = float(np.linalg.norm(current.twist[:3]))
    spin = float(np.linalg.norm(current.twist[3:]))
    lower = max(MIN_BLEND, 1.5 * speed / limits.linear_accel, 1.5 * spin / limits.angular_accel)
    T = yield from _shortest(violation, lower, limits)
    return T, rest(T)[0].pose


def _ramp_first(
    current: Reference,
    limits: TrajectoryLimits,
    plan: Callable[[Reference, TrajectoryLimits], Steps[Result]],
) -> Steps[tuple[list[Waypoint], Result]]:
    """The waypoints a transition leads with (times from 0: the current state, then
    perhaps a ramp's end) and `plan`'s one segment from the last of them, within `limits`.

    `plan` from the current state first; where no duration of that segment keeps the
    limits, a ramp that brings the current acceleration linearly to zero at the jerk
    limits, and `plan` from its end.  A reference accelerating hard (a double-S goto's
    first phase) leaves one segment no duration at all: shorter ones break the jerk
    limit, longer ones carry its acceleration on past the speed limit, so that first
    attempt searches durations up to _DIRECT_LONGEST only where a ramp could follow (a
    hold plans while the robot moves on).  The ramp's speed moves along a line from the
    current twist to its end's, so it keeps the speed limit where its end does.  If both
    fail, the first is searched over every duration the limits allow, and its error
    stands."""
    first = Waypoint(0.0, current.pose, current.twist, current.accel)
    if np.any(current.accel):  # a ramp can follow
        longest = min(limits.max_duration, _DIRECT_LONGEST)
        try:
            return [first], (
                yield from plan(current, limits.model_copy(update={"max_duration": longest}))
            )
        except TrajectoryError:
            pass
        try:
            ramps = _ramps(current, limits)
            end = ramps[-1]
            return [first, *ramps], (
                yield from plan(Reference(end.pose, end.twist, end.accel), limits)
            )
        except TrajectoryError:
            pass
    return [first], (yield from plan(current, limits))


def _ramps(current: Reference, limits: TrajectoryLimits) -> list[Waypoint]:
    """Where the acceleration, brought linearly to zero at the jerk limits, leaves the
    reference (times from 0): the linear and the angular part each ramps for as long as
    its own jerk limit needs (MIN_BLEND at least), so a waypoint where the sooner one
    ends and one where the other does (one where they end together or one has none).
    Each part is a cubic in each segment's chart, as a double-S profile's jerk phase:
    from inside a double-S's first phase its speed ends where the profile's would, at
    most its peak (its jerk a millionth below the limit, as the profile's)."""
    accel = current.accel
    parts = (slice(0, 3), slice(3, 6))
    ends = [0.0, 0.0]  # when each part's acceleration reaches zero (0: it has none)
    for k, (jerk, share) in enumerate(
        ((limits.linear_jerk, _SHARE), (limits.angular_jerk, _ANGULAR_RAMP_SHARE))
    ):
        norm = float(np.linalg.norm(accel[parts[k]]))
        if norm > 0.0:
            ends[k] = MIN_BLEND if jerk is None else max(MIN_BLEND, norm / (jerk * share))
    # no segment shorter than MIN_SEGMENT: a part ending just before the other ramps on
    # with it (its jerk a little lower)
    last = max(ends)
    ends = [last if 0.0 < last - end < MIN_SEGMENT else end for end in ends]
    leads, state, t = [], current, 0.0
    for end in sorted(set(ends) - {0.0}):
        h = end - t
        step, rate, rate_dot = np.zeros(6), np.zeros(6), np.zeros(6)
        for part, part_end in zip(parts, ends, strict=True):
            v, a = state.twist[part], state.accel[part]
            jerk = -a / (part_end - t) if part_end > t else 0.0  # a reaches 0 at part_end
            step[part] = v * h + a * (h * h / 2.0) + jerk * (h**3 / 6.0)
            rate[part] = v + a * h + jerk * (h * h / 2.0)
            rate_dot[part] = a + jerk * h
        omega, omega_dot = angular_rates(step[3:], rate[3:], rate_dot[3:])
        state = Reference(
            retract(state.pose, step),
            np.array([*rate[:3], *omega]),
            np.array([*rate_dot[:3], *omega_dot]),
        )
        t = end
        leads.append(Waypoint(t, state.pose, state.twist, state.accel))
    return leads


def _placed(leads: list[Waypoint], start: float) -> list[Waypoint]:
    """`leads` (times from 0) moved to begin at `start`."""
    return [Waypoint(start + w.t, w.pose, w.twist, w.accel) for w in leads]


def _check_rates(state: Reference, name: str, limits: TrajectoryLimits) -> None:
    """TrajectoryError if `state` itself is above a rate limit (no segment from or to it
    can keep them)."""
    bad = rate_violation(state, limits)
    if bad is not None:
        limit, value, unit = bad
        raise TrajectoryError(
            limit,
            f"the {name} has {value:.6g} {unit}, above the limit {getattr(limits, limit):g} {unit}",
            value=value,
        )


def _blend_duration(s0: Reference, s1: Reference, limits: TrajectoryLimits) -> Steps[float]:
    """The shortest duration of the s0 -> s1 segment that keeps the rate limits (a step
    after each candidate checked)."""
    _check_rates(s0, "current reference", limits)
    _check_rates(s1, "target state", limits)
    step = liediff(s0.pose, s1.pose)
    if not (np.any(s0.twist) or np.any(s0.accel) or np.any(s1.twist) or np.any(s1.accel)):
        dist, angle = float(np.linalg.norm(step[:3])), float(np.linalg.norm(step[3:]))
        span = max(
            MIN_BLEND,
            _PEAK_SPEED * dist / limits.linear_speed,
            math.sqrt(_PEAK_ACCEL * dist / limits.linear_accel),
            _PEAK_SPEED * angle / limits.angular_speed,
            math.sqrt(_PEAK_ACCEL * angle / limits.angular_accel),
            _jerk_span(dist, limits.linear_jerk),
            _jerk_span(angle, limits.angular_jerk),
        )
        return span * (1.0 + 1e-6)  # the peaks sit exactly at a limit: keep rounding below it
    # the mean acceleration |Δv| / span can never exceed the limit: a lower bound on span
    span = max(
        MIN_BLEND,
        float(np.linalg.norm(s1.twist[:3] - s0.twist[:3])) / limits.linear_accel,
        float(np.linalg.norm(s1.twist[3:] - s0.twist[3:])) / limits.angular_accel,
    )
    return (yield from _shortest(lambda T: _violation(s0, s1, step, T, limits), span, limits))


def _shortest(
    violation: Callable[[float], tuple[str, float, str] | None],
    span: float,
    limits: TrajectoryLimits,
) -> Steps[float]:
    """The shortest duration from `span` up that `violation` accepts: grown geometrically
    to the first feasible one, then bisected, then stretched by _MARGIN where that stays
    feasible (a step after each candidate checked)."""
    infeasible = None
    while (bad := violation(span)) is not None:
        yield
        if span > limits.max_duration:
            limit, value, unit = bad
            raise TrajectoryError(
                limit,
                f"no transition of up to {limits.max_duration:g} s from the current "
                f"reference keeps within the limits (at {span:.4g} s: {value:.6g} {unit} above "
                f"{getattr(limits, limit):g} {unit})",
                value=value,
            )
        infeasible, span = span, span * _GROW
    if infeasible is not None:
        lo = infeasible
        for _ in range(_BISECTIONS):
            yield
            mid = 0.5 * (lo + span)
            if violation(mid) is None:
                span = mid
            else:
                lo = mid
    return span * _MARGIN if violation(span * _MARGIN) is None else span


def _violation(
    s0: Reference, s1: Reference, step: np.ndarray, T: float, limits: TrajectoryLimits
) -> tuple[str, float, str] | None:
    """The first rate or jerk limit the s0 -> s1 segment of duration T exceeds inside,
    else None."""
    table = segment_table(s0.pose, s0.twist, s0.accel, s1.twist, s1.accel, step, T)
    hit = first_rate_violation(*segment_rates(table, T * _SAMPLES), limits)
    if hit is not None:
        return hit[1:]
    jerk = jerk_violation(table, np.array([T]), limits.linear_jerk, limits.angular_jerk)
    return None if jerk is None else jerk[1:]


def _jerk_span(distance: float, jerk: float | None) -> float:
    """The shortest minimum-jerk rest-to-rest move over `distance` whose jerk stays
    within `jerk` (None: not limited, 0)."""
    return 0.0 if jerk is None else (_PEAK_JERK * distance / jerk) ** (1.0 / 3.0)
