"""The jerk of a reference: how fast its linear and angular accelerations change.

Every segment is a quintic Hermite (cdpr.trajectory.core), so the acceleration is
continuous and the jerk finite; a jerk limit bounds how fast it changes, which a drive
feels as the slope of its torque.  Per segment the jerk is taken at JERK_SAMPLES + 1
evenly spaced instants, ends included, as the change of the accelerations across a
millionth of the segment around each (the linear one is the quintic's third derivative,
a quadratic in time whose peak between two instants exceeds theirs by at most 1/8 of its
change across them; the angular one is the rate of ω̇ = J_l θ̈ + J̇_l θ̇).  All segments
of a trajectory at once, in numpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from cdpr.trajectory.rotation import angular_rates

if TYPE_CHECKING:
    from cdpr.trajectory.core import Trajectory

Array = NDArray[np.float64]

JERK_SAMPLES = 8  # intervals per segment; the jerk is taken at their ends
_FRACTIONS = np.linspace(0.0, 1.0, JERK_SAMPLES + 1)
_STEP = 1e-6  # of a segment: the interval over which an acceleration's rate is taken
_POWERS = np.arange(6.0)
UNITS = {"linear_jerk": "m/s³", "angular_jerk": "rad/s³"}  # of the two limits


def segment_jerks(tables: Array, durations: Array) -> tuple[Array, Array]:
    """The largest linear (m/s³) and angular (rad/s³) jerk of each of m segments (tables
    (m, 6, 18) as segment_tables gives them, durations (m,) s): two arrays of m."""
    tables = np.asarray(tables, dtype=float).reshape(-1, 6, 18)
    h = np.asarray(durations, dtype=float).reshape(-1)
    dt = h * _STEP
    middle, half = h[:, None] * _FRACTIONS, 0.5 * dt[:, None]
    taus = np.stack([middle - half, middle + half])
    y = (taus[..., None] ** _POWERS) @ tables  # (2, m, k, 18)
    flat = np.ascontiguousarray(y.reshape(-1, 18).T)
    _, omega_dot = angular_rates(flat[3:6], flat[9:12], flat[15:18])
    linear = y[..., 12:15]
    angular = np.stack(omega_dot, axis=1).reshape(linear.shape)
    rate = dt[:, None]
    return (
        (np.linalg.norm(linear[1] - linear[0], axis=2) / rate).max(axis=1),
        (np.linalg.norm(angular[1] - angular[0], axis=2) / rate).max(axis=1),
    )


def jerk_excess(
    trajectory: Trajectory, linear_jerk: float | None, angular_jerk: float | None
) -> float:
    """The largest ratio of `trajectory`'s jerk to its limit (those set; 0 with none)."""
    linear, angular = segment_jerks(*trajectory.curve.segments()[1:])
    return max(
        (
            float(jerks.max()) / limit
            for jerks, limit in ((linear, linear_jerk), (angular, angular_jerk))
            if limit is not None
        ),
        default=0.0,
    )


def jerk_stretch(excess: float) -> float:
    """The uniform stretch of time (>= 1) that brings a jerk `excess` times its limit
    within it, and 1e-6 below (the jerk falls with the cube of the stretch; estimates
    and segment_jerks' differences agree to 1e-9)."""
    return max(1.0, excess ** (1.0 / 3.0) * (1.0 + 1e-6))


def jerk_violation(
    tables: Array, durations: Array, linear_jerk: float | None, angular_jerk: float | None
) -> tuple[int, str, float, str] | None:
    """The first segment whose jerk exceeds a limit (None: not limited), as (segment,
    limit name, value, unit), else None."""
    if linear_jerk is None and angular_jerk is None:
        return None
    linear, angular = segment_jerks(tables, durations)
    bad = np.zeros(len(linear), dtype=bool)
    if linear_jerk is not None:
        bad |= ~(linear <= linear_jerk)  # NaN fails too
    if angular_jerk is not None:
        bad |= ~(angular <= angular_jerk)
    rows = np.flatnonzero(bad)
    if rows.size == 0:
        return None
    k = int(rows[0])
    if linear_jerk is not None and not linear[k] <= linear_jerk:
        return k, "linear_jerk", float(linear[k]), UNITS["linear_jerk"]
    return k, "angular_jerk", float(angular[k]), UNITS["angular_jerk"]
