"""Trajectory limits (a config section) and the whole-trajectory check before it runs.

A rejected trajectory changes nothing; the TrajectoryError says which waypoint segment,
which limit and which value (DESIGN §7).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from cdpr.description import PositiveFloat, StrictModel
from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.trajectory.core import Reference, Trajectory, TrajectoryError

WrenchCheck = Callable[[Pose, NDArray[np.float64], NDArray[np.float64]], str | None]
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
    sample_period: PositiveFloat = 0.01  # s, validation step along the path
    max_waypoints: int = Field(MAX_WAYPOINTS, ge=2, le=MAX_WAYPOINTS)  # see MAX_WAYPOINTS
    max_duration: PositiveFloat = 3600.0  # s, bounds the validation work too
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
    sources = (twists, accels)
    sizes = np.stack(
        [np.linalg.norm(sources[which][:, part], axis=1) for _, _, which, part in _RATES], axis=1
    )
    bad = ~(sizes <= [getattr(limits, name) for name, *_ in _RATES])  # NaN fails too
    rows = np.flatnonzero(bad.any(axis=1))
    if rows.size == 0:
        return None
    row = int(rows[0])
    col = int(bad[row].argmax())
    name, unit, _, _ = _RATES[col]
    return row, name, float(sizes[row, col]), unit


def validate(
    trajectory: Trajectory,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None = None,
) -> None:
    """Raise TrajectoryError on the first problem along the path, else return.

    Samples every limits.sample_period from the start and at every waypoint time:
    rate limits, cable lengths within [length_min, length_max], and, if given,
    ``wrench_check(pose, twist, accel)`` (None when the wrench is in W, else a reason).
    The waypoint index reported is that of the segment holding the failing instant.
    """
    for _ in validation_steps(trajectory, robot, limits, wrench_check):
        pass


def validation_steps(
    trajectory: Trajectory,
    robot: Robot,
    limits: TrajectoryLimits,
    wrench_check: WrenchCheck | None = None,
) -> Iterator[float]:
    """`validate` one sample at a time: yields each sampled time once it passed, so a
    caller sharing an event loop with a control cycle can pause between samples."""
    count = len(trajectory.waypoints)
    if count > limits.max_waypoints:
        raise TrajectoryError(
            "max_waypoints",
            f"{count} waypoints exceed the limit of {limits.max_waypoints}",
            value=float(count),
        )
    if not trajectory.duration <= limits.max_duration:
        raise TrajectoryError(
            "max_duration",
            f"duration {trajectory.duration:.6g} s exceeds the limit {limits.max_duration:g} s",
            value=trajectory.duration,
        )
    steps = math.floor(trajectory.duration / limits.sample_period)
    grid = trajectory.start_time + limits.sample_period * np.arange(steps + 1)
    knots = [w.t for w in trajectory.waypoints]
    for t in np.union1d(grid, knots).tolist():
        ref = trajectory.sample(t)
        index = trajectory.waypoint_index(t)
        at = f"at t={t:.6g} s"
        bad = rate_violation(ref, limits)
        if bad is not None:
            name, size, unit = bad
            raise TrajectoryError(
                name,
                f"{size:.6g} {unit} exceeds the limit {getattr(limits, name):g} {unit} {at}",
                waypoint=index,
                value=size,
            )
        lengths = robot.cable_lengths(ref.pose)
        for k, (ell, lo, hi) in enumerate(
            zip(lengths.tolist(), robot.length_min, robot.length_max, strict=True)
        ):
            if not lo <= ell <= hi:
                raise TrajectoryError(
                    "cable_length",
                    f"cable {k} length {ell:.6g} m outside [{lo:g}, {hi:g}] m {at}",
                    waypoint=index,
                    value=ell,
                )
        if wrench_check is not None:
            reason = wrench_check(ref.pose, ref.twist, ref.accel)
            if reason is not None:
                raise TrajectoryError("wrench_set", f"{reason} {at}", waypoint=index)
        yield t
