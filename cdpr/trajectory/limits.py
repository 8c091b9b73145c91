"""Trajectory limits (a config section) and the whole-trajectory check before it runs.

A rejected trajectory changes nothing; the TrajectoryError says which waypoint segment,
which limit and which value (DESIGN §7).  The pose limits every sample is held to come
from the runtime's (cdpr.pose_limits), shrunk so that an accepted trajectory never trips
the runtime check (`sampled_pose_limits`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Annotated, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cdpr.description import PositiveFloat, StrictModel
from cdpr.pose import Pose
from cdpr.pose_limits import SCREEN_MARGIN, PoseLimits
from cdpr.reference import cable_segments
from cdpr.robot import Robot
from cdpr.trajectory.core import Reference, Samples, Trajectory, TrajectoryError, Waypoint
from cdpr.trajectory.jerk import jerk_violation

WrenchCheck = Callable[[Pose, NDArray[np.float64], NDArray[np.float64]], str | None]
# samples checked together, a step each: sampled (~0.15 ms), screened (~0.35 ms), by a
# BatchCheck (~0.35 ms); fewer cost more per sample (numpy's calls), more hold an event
# loop longer
CHUNK = 256
JERK_CHUNK = 128  # segments whose jerk is checked at once (~1 ms)


class Screened(NamedTuple):
    """A batch of samples screened (WrenchScreen): which certainly pass the wrench check,
    their cable lengths (N x n) and Jacobians (N x n x 6)."""

    clear: NDArray[np.bool_]
    lengths: NDArray[np.float64]
    jacobians: NDArray[np.float64]


@runtime_checkable
class WrenchScreen(Protocol):
    """A wrench check that also screens a batch (cdpr.wrench_check.ModelWrenchCheck)."""

    def screen(self, samples: Samples) -> Screened:
        """Which samples certainly pass the check (False: the check must decide), with
        the model's lengths and Jacobians at them."""
        ...


class BatchRefusal(NamedTuple):
    """The first pose of a batch a BatchCheck refuses: its index, the limit, one line."""

    index: int
    limit: str
    detail: str


class BatchCheck(Protocol):
    """A check of many poses at once (cdpr.workspace_check.WorkspaceCheck)."""

    def first_refusal(
        self,
        positions: NDArray[np.float64],
        rotations: NDArray[np.float64],
        jacobians: NDArray[np.float64] | None = None,
    ) -> BatchRefusal | None:
        """The first pose refused, else None (`jacobians`: Lambda at the poses, if known)."""
        ...


# The most waypoints a trajectory may have, and the highest max_waypoints a config may
# set: the daemon's event loop still does a few things whose cost grows with the count
# (the first validation step sorts the sample times: ~1.5 ms at 10,000; releasing a
# trajectory the controller is done with: 3-7 ms), and at 10,000 they stay far below the
# drives' 50 ms watchdog (bench/stall.py).  Longer motions: send them in pieces.
MAX_WAYPOINTS = 10_000


class TrajectoryLimits(StrictModel):
    """Limits every accepted trajectory respects; defaults suit a lab CDPR."""

    linear_speed: PositiveFloat = 1.0  # m/s, |v|
    angular_speed: PositiveFloat = 2.0  # rad/s, |ω|
    linear_accel: PositiveFloat = 5.0  # m/s², |p̈|
    angular_accel: PositiveFloat = 10.0  # rad/s², |ω̇|
    linear_jerk: PositiveFloat | None = None  # m/s³, |p⃛| (cdpr.trajectory.jerk); null: free
    angular_jerk: PositiveFloat | None = None  # rad/s³, |ω̈|; null: free
    sample_period: PositiveFloat = 0.01  # s, validation step along the path
    max_waypoints: int = Field(MAX_WAYPOINTS, ge=2, le=MAX_WAYPOINTS)  # see MAX_WAYPOINTS
    max_duration: PositiveFloat = 3600.0  # s, bounds the validation work too
    # s from now to a requested start; strict: a bool or a string is an error, not a number
    max_start_delay: Annotated[PositiveFloat, Field(strict=True)] = 60.0
    unit_tolerance: float = Field(1e-6, gt=0.0, le=1e-2)  # |‖q‖ - 1| normalised silently


# (limit name, unit, twist/accel slice) of the four rate limits, in checking order
_RATES = (
    ("linear_speed", "m/s", 0, slice(0, 3)),
    ("angular_speed", "rad/s", 0, slice(3, 6)),
    ("linear_accel", "m/s²", 1, slice(0, 3)),
    ("angular_accel", "rad/s²", 1, slice(3, 6)),
)


def rate_violation(ref: Reference, limits: TrajectoryLimits) -> tuple[str, float, str] | None:
    """The first rate limit `ref` exceeds, as (limit name, value, unit), else None."""
    for name, unit, which, part in _RATES:
        vec = ref[1 + which][part]
        size = math.sqrt(float(vec @ vec))
        if not size <= getattr(limits, name):  # NaN fails too
            return name, size, unit
    return None


def first_rate_violation(
    twists: NDArray[np.float64], accels: NDArray[np.float64], limits: TrajectoryLimits
) -> tuple[int, str, float, str] | None:
    """rate_violation over samples at once (rows of `twists` and `accels`, k x 6): the
    first sample exceeding a limit and the first limit it exceeds, as (row, limit name,
    value, unit), else None."""
    sizes = _rate_sizes(twists, accels)
    bad = ~(sizes <= _rate_limits(limits))  # NaN fails too
    rows = np.flatnonzero(bad.any(axis=1))
    if rows.size == 0:
        return None
    row = int(rows[0])
    col = int(bad[row].argmax())
    name, unit, _, _ = _RATES[col]
    return row, name, float(sizes[row, col]), unit


def _rate_sizes(twists: NDArray[np.float64], accels: NDArray[np.float64]) -> NDArray[np.float64]:
    """|v|, |ω|, |p̈|, |ω̇| of each sample (k x 4, _RATES' order)."""
    sources = (twists, accels)
    return np.stack(
        [np.linalg.norm(sources[which][:, part], axis=1) for _, _, which, part in _RATES], axis=1
    )


def _rate_limits(limits: TrajectoryLimits) -> list[float]:
    return [getattr(limits, name) for name, *_ in _RATES]


def sampled_pose_limits(path: PoseLimits, limits: TrajectoryLimits) -> PoseLimits:
    """The pose limits each validation sample must keep for the whole path, between the
    samples too, to stay inside `path`.

    Samples lie at most h = limits.sample_period apart.  Between two of them a position
    coordinate strays at most linear_accel·h²/8 beyond the larger of its two sampled
    values (|p̈| <= linear_accel).  For the tilt, c(t) = <q(t), q_home> has
    |c̈| <= |q̈| <= angular_accel/2 + angular_speed²/4, so c drops at most
    δ = (angular_accel/2 + angular_speed²/4)·h²/8 below the smaller sampled value:
    samples with tilt <= 2 acos(cos(tilt_max/2) + δ) keep the path's tilt <= tilt_max.
    A corner of the body at r from p has |d²(R r)/dt²| <= |r|·(angular_accel +
    angular_speed²), so it strays |r|·(angular_accel + angular_speed²)·h²/8 further.
    """
    h2 = limits.sample_period**2
    position = limits.linear_accel * h2 / 8.0
    delta = (limits.angular_accel / 2.0 + limits.angular_speed**2 / 4.0) * h2 / 8.0
    turn = (limits.angular_accel + limits.angular_speed**2) * h2 / 8.0
    orientation = 0.0
    if path.tilt_max > 0.0:  # else it is empty already
        sampled = 2.0 * math.acos(min(1.0, math.cos(path.tilt_max / 2.0) + delta))
        orientation = path.tilt_max - sampled
    return path.shrunk(position, orientation, turn)


@dataclass(frozen=True)
class LengthLimits:
    """Bounds on each cable's geometric length along a reference (m): inside them, the
    lengths the drives measure stay inside the robot's [length_min, length_max], which
    the runtime checks, while tracking keeps within its bounds (`tracked_length_limits`).
    `limits` names what they derive from, for the messages."""

    lower: tuple[float, ...]
    upper: tuple[float, ...]
    limits: str = "length_min/length_max"

    def violation(self, lengths: Sequence[float]) -> tuple[int, float, float, float] | None:
        """(cable, length, lower, upper) of the first cable outside, else None."""
        for k, (ell, lo, hi) in enumerate(zip(lengths, self.lower, self.upper, strict=True)):
            if not lo <= ell <= hi:
                return k, ell, lo, hi
        return None

    def clear(self, lengths: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which rows of `lengths` (N x n) certainly pass `violation`: every cable
        SCREEN_MARGIN m inside its bounds (batch arithmetic rounds differently)."""
        return np.all(
            (lengths >= np.add(self.lower, SCREEN_MARGIN))
            & (lengths <= np.subtract(self.upper, SCREEN_MARGIN)),
            axis=1,
        )

    def widened_to(self, lengths: Sequence[float]) -> LengthLimits:
        """The smallest bounds holding these and `lengths`: a transition may not go
        further out than where it starts, nor be refused for starting there."""
        return LengthLimits(
            tuple(min(lo, x) for lo, x in zip(self.lower, lengths, strict=True)),
            tuple(max(hi, x) for hi, x in zip(self.upper, lengths, strict=True)),
            self.limits,
        )


def cable_speed_bounds(robot: Robot, limits: TrajectoryLimits) -> list[float]:
    """Per cable, an upper bound of |l'| = |u . (v + w x r)| for any motion within
    `limits` (m/s): linear_speed + angular_speed |b_k|."""
    reach = np.linalg.norm(robot.geometry.attachments, axis=1)
    return (limits.linear_speed + limits.angular_speed * reach).tolist()


def tracked_length_limits(
    robot: Robot, position: float, orientation: float, limits: TrajectoryLimits
) -> LengthLimits:
    """The bounds a sampled reference's lengths must keep (DESIGN §7: an accepted
    trajectory never trips a runtime brake) when the measured pose may be `position` (m)
    and `orientation` (rad) from the reference:

    - the pose: |d l_k| <= |d p| + |b_k| |d theta| (triangle inequality; |(R' - R) b| <=
      |b| theta), i.e. position + |b_k| orientation;
    - between two samples h = sample_period apart the length strays at most
      |l''| h^2 / 8, |l''| <= linear_accel + |b_k| angular_accel + (linear_speed + |b_k|
      angular_speed)^2 / length_min;
    - stretch: a drive measures the length its drum paid out, l / (1 + t / EA), shorter
      under tension t <= force_max: the lower bound is raised by that factor.
    """
    b = np.linalg.norm(robot.geometry.attachments, axis=1).tolist()
    speeds = cable_speed_bounds(robot, limits)
    h2 = limits.sample_period**2
    lower, upper = [], []
    for k, r in enumerate(b):
        lo, hi = float(robot.length_min[k]), float(robot.length_max[k])
        accel = limits.linear_accel + r * limits.angular_accel
        accel += speeds[k] ** 2 / max(lo, 1e-3)
        margin = position + r * orientation + accel * h2 / 8.0
        stretch = 1.0 + float(robot.compliance[k]) * float(robot.force_max[k])
        lower.append((lo + margin) * stretch)
        upper.append(hi - margin)
    return LengthLimits(
        tuple(lower),
        tuple(upper),
        "length_min/length_max less the tracking, sampling and stretch margins",
    )


def check_start_delay(delay: float, limits: TrajectoryLimits) -> None:
    """TrajectoryError if a requested start lies more than max_start_delay seconds ahead
    (the start is when waypoint 0 is due)."""
    if not delay <= limits.max_start_delay:
        raise TrajectoryError(
            "max_start_delay",
            f"the start lies {delay:.6g} s ahead, beyond the limit {limits.max_start_delay:g} s",
            waypoint=0,
            value=delay,
        )


def validate(
    trajectory: Trajectory,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None = None,
    pose_limits: PoseLimits | None = None,
    length_limits: LengthLimits | None = None,
    workspace: BatchCheck | None = None,
) -> None:
    """Raise TrajectoryError on the first problem along the path, else return.

    If given, every waypoint's pose is checked against `pose_limits` first (naming that
    waypoint: a place the platform cannot be, whatever the timing), then the jerk of
    every segment, where limited (naming the segment's first waypoint).  Then samples
    every limits.sample_period from the start and at every waypoint time: rate limits,
    `pose_limits`, cable lengths within `length_limits` (default the robot's
    [length_min, length_max]), and, if given, ``wrench_check(pose, twist, accel)`` (None
    when the wrench is in W, else a reason), and `workspace`'s checks (validation_steps
    says how the samples are batched).  The waypoint index reported for a sample is that
    of the segment holding the failing instant.
    """
    steps = validation_steps(
        trajectory, robot, limits, wrench_check, pose_limits, length_limits, workspace=workspace
    )
    for _ in steps:
        pass


def validation_steps(
    trajectory: Trajectory,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None = None,
    pose_limits: PoseLimits | None = None,
    length_limits: LengthLimits | None = None,
    segments: int | None = None,
    workspace: BatchCheck | None = None,
) -> Iterator[float]:
    """`validate` one step at a time (each under a millisecond), so that a caller sharing
    an event loop with a control cycle can pause between: yields the time reached (a
    waypoint's, a sample's) after each step.

    The samples go CHUNK at a time: evaluated together (Trajectory.sample_many), screened
    together (each check's batch form, SCREEN_MARGIN inside its bounds, the wrench by a
    WrenchScreen: a few microseconds a sample), the few the screen cannot clear checked
    one by one as `validate` describes, then the `workspace` check on the chunk (before a
    problem found in it is raised, so the first problem along the path is named).
    `segments`: only the first that many segments (a transition into a trajectory already
    validated), whose end need not be at rest."""
    if segments is None:
        waypoints = trajectory.waypoints
    else:
        waypoints = tuple(trajectory.knot(k) for k in range(min(segments + 1, len(trajectory))))
    count = len(waypoints)
    if count > limits.max_waypoints:
        raise TrajectoryError(
            "max_waypoints",
            f"{count} waypoints exceed the limit of {limits.max_waypoints}",
            value=float(count),
        )
    duration = waypoints[-1].t - waypoints[0].t
    if not duration <= limits.max_duration:
        raise TrajectoryError(
            "max_duration",
            f"duration {duration:.6g} s exceeds the limit {limits.max_duration:g} s",
            value=duration,
        )
    bounds = length_limits or LengthLimits(
        tuple(robot.length_min.tolist()), tuple(robot.length_max.tolist())
    )
    if pose_limits is not None:
        yield from _waypoint_steps(pose_limits, waypoints)
    yield from _jerk_steps(trajectory, limits, len(waypoints) - 1)
    steps = math.floor(duration / limits.sample_period)
    grid = trajectory.start_time + limits.sample_period * np.arange(steps + 1)
    times = np.union1d(grid, [w.t for w in waypoints])  # ~1.5 ms at 10,000 waypoints
    yield float(times[0])
    for first in range(0, len(times), CHUNK):
        samples = trajectory.sample_many(times[first : first + CHUNK])
        yield float(samples.times[0])
        clear, jacobians = _screen(samples, robot, limits, wrench_check, pose_limits, bounds)
        for i in np.flatnonzero(~clear).tolist():  # the scalar checks decide, in order
            t = float(samples.times[i])
            try:
                _check_reference(
                    robot,
                    limits,
                    wrench_check,
                    pose_limits,
                    bounds,
                    trajectory.sample(t),
                    trajectory.waypoint_index(t),
                    f"at t={t:.6g} s",
                )
            except TrajectoryError:
                _check_batch(trajectory, workspace, samples, jacobians, i)  # earlier ones first
                raise
            yield t
        yield float(samples.times[-1])
        _check_batch(trajectory, workspace, samples, jacobians, len(samples.times))
        yield float(samples.times[-1])


def _screen(
    samples: Samples,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None,
    pose_limits: PoseLimits | None,
    bounds: LengthLimits,
) -> tuple[NDArray[np.bool_], NDArray[np.float64] | None]:
    """Which samples certainly pass _check_reference, each check's batch form at once
    (SCREEN_MARGIN inside every bound; the rest are checked one by one), and the
    Jacobians at them where the wrench screen computed them."""
    ceilings = np.multiply(_rate_limits(limits), 1.0 - SCREEN_MARGIN)
    clear = np.all(_rate_sizes(samples.twists, samples.accels) <= ceilings, axis=1)
    if pose_limits is not None:
        clear &= pose_limits.clear(samples.positions, samples.quaternions)
    if isinstance(wrench_check, WrenchScreen):
        screened = wrench_check.screen(samples)
        return clear & screened.clear & bounds.clear(screened.lengths), screened.jacobians
    clear &= bounds.clear(cable_segments(robot, samples.positions, samples.rotations)[0])
    return clear & (wrench_check is None), None


def _waypoint_steps(pose_limits: PoseLimits, waypoints: Sequence[Waypoint]) -> Iterator[float]:
    """TrajectoryError naming the first waypoint whose pose breaks `pose_limits`: CHUNK
    at a time, screened together (PoseLimits.clear), the rest checked one by one."""
    for first in range(0, len(waypoints), CHUNK):
        chunk = waypoints[first : first + CHUNK]
        positions = np.array([w.pose.position_tuple for w in chunk])
        quaternions = np.array([w.pose.quaternion_tuple for w in chunk])
        for i in np.flatnonzero(~pose_limits.clear(positions, quaternions)).tolist():
            w = chunk[i]
            _check_pose(pose_limits, w.pose, first + i, f"at t={w.t:.6g} s")
        yield chunk[-1].t


def _jerk_steps(trajectory: Trajectory, limits: TrajectoryLimits, segments: int) -> Iterator[float]:
    """TrajectoryError naming the first of the first `segments` segments whose jerk
    exceeds linear_jerk or angular_jerk (where set); checked JERK_CHUNK segments at a
    time, yielding the time checked up to between (10,000 segments at once held a
    shared event loop ~100 ms)."""
    if limits.linear_jerk is None and limits.angular_jerk is None:
        return
    starts, tables, durations = trajectory.curve.segments()
    for first in range(0, segments, JERK_CHUNK):
        last = min(first + JERK_CHUNK, segments)
        bad = jerk_violation(
            tables[first:last], durations[first:last], limits.linear_jerk, limits.angular_jerk
        )
        if bad is not None:
            k, name, value, unit = bad
            t0, t1 = starts[first + k], starts[first + k] + durations[first + k]
            raise TrajectoryError(
                name,
                f"{value:.6g} {unit} exceeds the limit {getattr(limits, name):g} {unit} "
                f"between t={t0:.6g} s and t={t1:.6g} s",
                waypoint=trajectory.waypoint_index(float(t0)),
                value=value,
            )
        yield float(starts[last - 1] + durations[last - 1])


def _check_batch(
    trajectory: Trajectory,
    workspace: BatchCheck | None,
    samples: Samples,
    jacobians: NDArray[np.float64] | None,
    count: int,
) -> None:
    """Raise TrajectoryError for the first of the first `count` samples `workspace`
    refuses."""
    if workspace is None or not count:
        return
    refused = workspace.first_refusal(
        samples.positions[:count],
        samples.rotations[:count],
        None if jacobians is None else jacobians[:count],
    )
    if refused is not None:
        t = float(samples.times[refused.index])
        raise TrajectoryError(
            refused.limit, f"{refused.detail} at t={t:.6g} s", waypoint=trajectory.waypoint_index(t)
        )


def check_target(
    target: Pose,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None,
    pose_limits: PoseLimits,
    length_limits: LengthLimits,
    workspace: BatchCheck | None,
) -> None:
    """Raise TrajectoryError (naming no waypoint, "at the target") if resting at `target`
    breaks a limit validation checks each sample against: a move to a pose that cannot
    be held is refused for that, not for the first point of its way that crosses
    something (the waypoints of a jerk-limited goto are its own, not the user's)."""
    rest = np.zeros(6)
    ref = Reference(target, rest, rest)
    _check_reference(
        robot, limits, wrench_check, pose_limits, length_limits, ref, None, "at the target"
    )
    refused = (
        None
        if workspace is None
        else workspace.first_refusal(np.array([ref.pose.position_tuple]), ref.pose.rotation[None])
    )
    if refused is not None:
        raise TrajectoryError(refused.limit, f"{refused.detail} at the target")


def _check_reference(
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None,
    pose_limits: PoseLimits | None,
    bounds: LengthLimits,
    ref: Reference,
    index: int | None,
    at: str,
) -> None:
    """Raise TrajectoryError naming waypoint `index` and `at` if `ref` breaks a limit."""
    bad = rate_violation(ref, limits)
    if bad is not None:
        name, size, unit = bad
        raise TrajectoryError(
            name,
            f"{size:.6g} {unit} exceeds the limit {getattr(limits, name):g} {unit} {at}",
            waypoint=index,
            value=size,
        )
    if pose_limits is not None:
        _check_pose(pose_limits, ref.pose, index, at)
    bad = bounds.violation(robot.cable_lengths(ref.pose).tolist())
    if bad is not None:
        k, ell, lo, hi = bad
        raise TrajectoryError(
            "cable_length",
            f"cable {k} length {ell:.6g} m outside [{lo:.6g}, {hi:.6g}] m ({bounds.limits}) {at}",
            waypoint=index,
            value=ell,
        )
    if wrench_check is not None:
        reason = wrench_check(ref.pose, ref.twist, ref.accel)
        if reason is not None:
            raise TrajectoryError("wrench_set", f"{reason} {at}", waypoint=index)


def _check_pose(pose_limits: PoseLimits, pose: Pose, index: int | None, at: str) -> None:
    bad = pose_limits.violation(pose)
    if bad is not None:
        raise TrajectoryError(bad.limit, f"{bad.detail} {at}", waypoint=index, value=bad.value)
