"""Waypoints -> a C² pose reference with analytic twist and acceleration (DESIGN §7).

Between two knots, every segment is a quintic Hermite curve fixed by the knot states
(pose, twist, accel) at both ends, so sharing one state per knot makes the reference C²
by construction, whatever the knot rates are:

- position: p(t) is the quintic in R³ through (p, v, a) at both knots;
- orientation: R(t) = exp(θ(t)) R_k with θ a quintic in R³ in the world frame, θ = 0 at
  the start and θ = log(R_k+1 R_kᵀ) at the end of the segment; ω = J_l(θ) θ̇ and
  ω̇ = J_l(θ) θ̈ + (d/dt J_l(θ)) θ̇, in closed form (J_l the left Jacobian of SO(3)).

Knot rates that the waypoints leave free are chosen to minimise the integrated squared
jerk of the positions and of the cumulative world-frame rotation vectors (a banded linear
system).  With no interior twists that is exactly the C⁴ quintic interpolating spline.

scipy's RotationSpline is not used: its angular rate and acceleration are in the BODY
frame (ω_world = R ω_body) and its end conditions are not at rest; a robot starts and
stops at rest, and the controller wants the world-frame ω of DESIGN §3.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solveh_banded

from cdpr.compiled_linalg import kernel_array
from cdpr.pose import QUATERNION_NORM_TOLERANCE, Pose, liediff
from cdpr.so3 import (
    quat_mul4,
    quats_to_matrices,
    quats_to_rotvecs,
)
from cdpr.trajectory.compiled_curve import evaluate_segments, segment_sample
from cdpr.trajectory.rotation import angular_rates, left_jacobians

Array = NDArray[np.float64]

SCHEMA_VERSION = 1  # of the interface form (as_dict / parse_trajectory)
MIN_SEGMENT = 1e-4  # s: shortest time between waypoints (keeps h⁵ well away from zero)
MAX_TIME = 1e9  # s: |t| bound, so that time differences stay exact enough and finite
MAX_MAGNITUDE = 1e6  # bound on position, twist and accel components (m, m/s, rad/s, ...)
_REST_TOLERANCE = 1e-9  # a final twist/accel must be zero to within this

_ZERO6 = np.zeros(6)
_ZERO6.setflags(write=False)

# Quintic Hermite on [0, 1]: (y0, v0, a0, y1, v1, a1) -> coefficients c0..c5 of τ^j.
_HERMITE = np.array(
    [
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.5, 0.0, 0.0, 0.0],
        [-10.0, -6.0, -1.5, 10.0, -4.0, 0.5],
        [15.0, 8.0, 1.5, -15.0, 7.0, -1.0],
        [-6.0, -3.0, -0.5, 6.0, -3.0, 0.5],
    ]
)
# d/dτ on coefficient columns: (D c)_j = (j + 1) c_(j+1)
_DERIVATIVE = np.diag(np.arange(1.0, 6.0), 1)
_POWERS = np.arange(6.0)  # of τ, the rows of a segment table
# ∫₀¹ jerk² dτ as a quadratic form in (c3, c4, c5), then in the Hermite knot data
_JERK_GRAM = np.array([[36.0, 72.0, 120.0], [72.0, 192.0, 360.0], [120.0, 360.0, 720.0]])
_JERK_COST = _HERMITE[3:].T @ _JERK_GRAM @ _HERMITE[3:]


class TrajectoryError(ValueError):
    """A trajectory was rejected: which waypoint (or None), which limit, which value.

    `limit` is a short name such as "times_increasing", "linear_speed", "cable_length",
    "wrench_set", "unit_quaternion", "finite", "schema"; `field` names the offending
    input key (e.g. "waypoints[3].quaternion") where there is one.
    """

    def __init__(
        self,
        limit: str,
        detail: str,
        *,
        waypoint: int | None = None,
        value: float | None = None,
        field: str | None = None,
    ) -> None:
        self.limit = limit
        self.waypoint = waypoint
        self.value = value
        self.field = field
        prefix = "" if waypoint is None else f"waypoint {waypoint}: "
        super().__init__(f"{prefix}{limit}: {detail}")


@dataclass(frozen=True, eq=False, slots=True)
class Waypoint:
    """A pose to be at at time t (s); optionally the twist (v, ω) and accel there.

    A twist or accel left None is chosen by the trajectory (minimum jerk); at the first
    waypoint None means at rest, and the last waypoint is always at rest.
    """

    t: float
    pose: Pose
    twist: Array | None = None
    accel: Array | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", float(self.t))
        for name in ("twist", "accel"):
            raw = getattr(self, name)
            if raw is not None and not _frozen_vector(raw):
                arr = np.array(raw, dtype=float)
                if arr.shape != (6,):
                    raise TrajectoryError("schema", f"{name} must have 6 components (v, ω)")
                arr.setflags(write=False)
                object.__setattr__(self, name, arr)


def _frozen_vector(value: object) -> bool:
    """A float 6-vector that nothing can change: read-only, and so is every array it
    views, down to the one that owns the memory.  A waypoint keeps it as given (a path's
    timing hands over thousands, rows of one read-only array), where any other value is
    copied and frozen."""
    if not (isinstance(value, np.ndarray) and value.shape == (6,) and value.dtype == np.float64):
        return False
    while value is not None:
        if not isinstance(value, np.ndarray) or value.flags.writeable:
            return False
        value = value.base
    return True


class Reference(NamedTuple):
    """The requested state at one instant: pose η_r, twist φ_r (6,), accel α_r (6,)."""

    pose: Pose
    twist: Array
    accel: Array

    def same_as(self, other: Reference) -> bool:
        """The same pose, twist and accel: a transition from one continues the other."""
        return (
            self.pose == other.pose
            and np.array_equal(self.twist, other.twist)
            and np.array_equal(self.accel, other.accel)
        )


class Samples(NamedTuple):
    """The references at many times as arrays (Curve.sample_many): what a check of a
    batch of samples reads."""

    times: Array  # (N,)
    positions: Array  # (N, 3)
    quaternions: Array  # (N, 4), w first
    rotations: Array  # (N, 3, 3)
    twists: Array  # (N, 6)
    accels: Array  # (N, 6)


class _Blend(NamedTuple):
    """Segments joined before a trajectory's own first waypoint (Trajectory.after_blend):
    segment k from leads[k] to the next lead, the last into the trajectory's start."""

    leads: tuple[Waypoint, ...]  # each with its time, pose, twist and accel given
    tables: tuple[Array, ...]
    quats: tuple[tuple[float, ...], ...]

    def shifted(self, dt: float) -> _Blend:
        """The same segments, every lead's time moved by dt."""
        leads = tuple(Waypoint(w.t + dt, w.pose, w.twist, w.accel) for w in self.leads)
        return self._replace(leads=leads)

    def segment(self, t: float) -> int:
        """The lead whose segment holds t (the first for times before it)."""
        k = len(self.leads) - 1
        while k > 0 and self.leads[k].t > t:
            k -= 1
        return k


class Curve:
    """What a trajectory samples: segment tables between knot times, each segment's
    start rotation, a time shift, and optionally one blend segment in front.

    Built by `Trajectory`; `packed` / `unpacked` carry it between processes as one
    float64 array and a small header, so that a process that only samples (the
    real-time core) gets it without rebuilding anything: the unpacked curve reads the
    array in place, whatever the number of segments.
    """

    def __init__(
        self,
        times: Sequence[float],
        tables: Sequence[Array],
        quats: Sequence[tuple[float, ...]],
        first: Pose,
        last: Pose,
        shift: float = 0.0,
        blend: _Blend | None = None,
        *,
        arrays: tuple[Array, Array, Array],
    ) -> None:
        self._times, self._tables, self._quats = times, tables, quats
        # the same as arrays (times (m + 1,), tables (m, 6, 18), quats (m, 4)): sample_many's
        self._arrays = arrays
        self._first, self._last = first, last
        self.shift = shift
        self.blend = blend
        self.body_start = times[0] + shift
        self.start_time = self.body_start if blend is None else blend.leads[0].t
        self.end_time = times[-1] + shift
        self._before = Reference(first if blend is None else blend.leads[0].pose, _ZERO6, _ZERO6)
        self._after = Reference(last, _ZERO6, _ZERO6)

    def placed(self, shift: float, blend: _Blend | None) -> Curve:
        """The same segments with another time shift and blend."""
        return Curve(
            self._times, self._tables, self._quats, self._first, self._last, shift, blend,
            arrays=self._arrays,
        )  # fmt: skip

    def segment(self, t: float) -> int:
        """The last knot of the segments at or before t (-1 before the first), as a
        bisection of the shifted times would find it: shifting t back by the shift
        rounds differently from shifting the times, by at most one knot here."""
        times, shift = self._times, self.shift
        k = bisect_right(times, t - shift) - 1
        if k + 1 < len(times) and times[k + 1] + shift <= t:
            return k + 1
        if k >= 0 and times[k] + shift > t:
            return k - 1
        return k

    def sample(self, t: float) -> Reference:
        """(η_r, φ_r, α_r) at time t: evaluates only the segment holding t."""
        if type(t) is not float:  # e.g. a numpy scalar: it would slow the scalar code below
            t = float(t)
        if t >= self.end_time:
            return self._after
        if t >= self.body_start:
            k = self.segment(t)
            return evaluate_segment(
                self._tables[k], self._quats[k], t - (self._times[k] + self.shift)
            )
        if t >= self.start_time:  # in the blend
            blend = self.blend
            assert blend is not None
            k = blend.segment(t)
            return evaluate_segment(blend.tables[k], blend.quats[k], t - blend.leads[k].t)
        if t < self.start_time:
            return self._before
        raise ValueError(f"sample time must be a number, got {t!r}")

    def sample_many(self, times: Array) -> Samples:
        """sample() at many times (ascending or not) at once: the samples inside the
        segments evaluated by a compiled loop (cdpr.trajectory.compiled_curve, imported
        the same kernel as sample's), those before, after or in the blend one by one."""
        t = np.asarray(times, dtype=float)
        count = len(t)
        positions, quaternions = np.empty((count, 3)), np.empty((count, 4))
        twists, accels = np.empty((count, 6)), np.empty((count, 6))
        inside = (t >= self.body_start) & (t < self.end_time)
        if inside.all():
            knots, tables, quats = self._arrays
            k = self._segments_of(t, knots)
            tau = t - (knots[k] + self.shift)
            evaluate_segments(tables, quats, k, tau, positions, quaternions, twists, accels)
        else:
            for i in np.flatnonzero(~inside).tolist():
                ref = self.sample(float(t[i]))
                positions[i], quaternions[i] = ref.pose.position_tuple, ref.pose.quaternion_tuple
                twists[i], accels[i] = ref.twist, ref.accel
            rows = np.flatnonzero(inside)
            if rows.size:
                part = self.sample_many(t[rows])
                positions[rows], quaternions[rows] = part.positions, part.quaternions
                twists[rows], accels[rows] = part.twists, part.accels
        return Samples(t, positions, quaternions, quats_to_matrices(quaternions), twists, accels)

    def _segments_of(self, t: Array, knots: Array) -> NDArray[np.intp]:
        """segment(t) for an array of times inside the segments."""
        shift, last = self.shift, len(knots) - 1
        k = np.searchsorted(knots, t - shift, side="right") - 1
        k = np.where((k < last) & (knots[np.minimum(k + 1, last)] + shift <= t), k + 1, k)
        return np.where((k >= 0) & (knots[np.maximum(k, 0)] + shift > t), k - 1, k)

    def segments(self) -> tuple[Array, Array, Array]:
        """(start times (m,), tables (m, 6, 18), durations (m,)) of every segment in time
        order, the blend's first: for a check over the whole curve at once (its jerk)."""
        times = np.asarray(self._times, dtype=float) + self.shift
        tables = np.asarray(self._tables, dtype=float).reshape(-1, 6, 18)
        if self.blend is not None:
            times = np.concatenate([[w.t for w in self.blend.leads], times])
            tables = np.concatenate([np.stack(self.blend.tables), tables])
        return times[:-1], tables, np.diff(times)

    def packed(self) -> tuple[dict, Array]:
        """(header, data): the knot times, the segment tables and the start rotations
        in one float64 array; the rest (poses, shift, blend) in a small header."""
        n = len(self._times)
        data = np.empty(n + (n - 1) * (_TABLE_SIZE + 4))
        data[:n] = [self._times[k] for k in range(n)]
        tables_end = n + (n - 1) * _TABLE_SIZE
        data[n:tables_end] = np.asarray([self._tables[k] for k in range(n - 1)]).ravel()
        data[tables_end:] = np.asarray([self._quats[k] for k in range(n - 1)]).ravel()
        header = {
            "knots": n,
            "shift": self.shift,
            "first": self._first,
            "last": self._last,
            "blend": self.blend,
        }
        return header, data

    @classmethod
    def unpacked(cls, header: dict, data: Array) -> Curve:
        """The curve of `packed`, reading `data` in place (it must outlive the curve)."""
        n = int(header["knots"])
        if n < 2 or data.shape != (n + (n - 1) * (_TABLE_SIZE + 4),):
            raise ValueError(f"a packed curve of {n} knots cannot hold {data.shape} values")
        tables_end = n + (n - 1) * _TABLE_SIZE
        tables = data[n:tables_end].reshape(n - 1, 6, 18)
        quats = data[tables_end:].reshape(n - 1, 4)
        return cls(
            _Floats(data[:n]),
            tables,
            _Rows(quats),
            header["first"],
            header["last"],
            float(header["shift"]),
            header["blend"],
            arrays=(data[:n], tables, quats),
        )


_TABLE_SIZE = 6 * 18  # values in one segment table


class _Floats(Sequence[float]):
    """A float64 vector read as Python floats (numpy scalars slow the scalar code)."""

    def __init__(self, values: Array) -> None:
        self._values = values

    def __len__(self) -> int:
        return len(self._values)

    def __getitem__(self, k):  # type: ignore[override]
        return float(self._values[k])


class _Rows(Sequence[tuple[float, ...]]):
    """The rows of a 2-d float64 array, each read as a tuple of Python floats."""

    def __init__(self, values: Array) -> None:
        self._values = values

    def __len__(self) -> int:
        return len(self._values)

    def __getitem__(self, k):  # type: ignore[override]
        return tuple(self._values[k].tolist())


class Trajectory:
    """A C² reference through >= 2 waypoints; `sample(t)` once per control cycle.

    Before the first waypoint the reference is the first pose at rest, after the last
    one the last pose at rest (the last waypoint must be at rest, so this is no jump).
    Interior waypoint twists (and accels) are honoured exactly; the rates left free
    minimise the integrated squared jerk.  Consecutive orientations are joined along
    the shorter rotation (< π): add waypoints for larger turns.

    `shifted` and `after_blend` cost the same whatever the number of waypoints (a
    service plans them between control cycles): the result shares the segments built
    here, and keeps the time shift and the blend segment beside them.
    """

    def __init__(self, waypoints: Sequence[Waypoint]) -> None:
        self._build(_Knots.of(tuple(waypoints)))

    @classmethod
    def through(
        cls,
        times: Array,
        positions: Array,
        quaternions: Array,
        twists: Array | None = None,
        accels: Array | None = None,
    ) -> Trajectory:
        """The trajectory through n knots given as arrays (times (n,), positions (n, 3),
        unit quaternions (n, 4), twists and accels (n, 6) at every knot, or None: the
        trajectory chooses them as for a Waypoint without them): what a planner or a
        parser of thousands of knots hands over, with no Waypoint made per knot until
        `waypoints` asks.  Checked as waypoints are."""
        out = cls.__new__(cls)
        out._build(_Knots.of_arrays(times, positions, quaternions, twists, accels))
        return out

    def _build(self, knots: _Knots) -> None:
        """The curve through `knots` (the constructors' common part)."""
        times, positions, quats = knots.times, knots.positions, knots.quats
        with np.errstate(all="ignore"):
            steps = knot_steps(positions, quats)
            values = np.zeros((len(times), 6))
            values[:, :3] = positions
            values[1:, 3:] = np.cumsum(steps[:, 3:], axis=0)
            twists, accels = _knot_rates(times, values, knots)
            h = np.diff(times)
            tables = segment_tables(
                positions[:-1], twists[:-1], accels[:-1], twists[1:], accels[1:], steps, h
            )
        if not (np.all(np.isfinite(tables)) and np.all(np.isfinite(twists))):
            raise TrajectoryError(
                "finite", "the curve through these waypoints is not finite (values too large?)"
            )
        # the knots and the curve as built: never changed, shared by shifted and
        # blended copies
        self._knots = knots
        self._rates = (twists, accels)
        self._curve = Curve(
            times.tolist(),
            list(tables),  # per segment; a list indexes faster than a 3-d array
            list(map(tuple, quats.tolist())),
            knots.pose(0),
            knots.pose(len(times) - 1),
            # the start rotations as the kernels take them whichever way the knots came
            # (of_arrays leaves them read-only, another type to numba, which would
            # compile at a client's first trajectory, in the companion's event loop)
            arrays=(times, tables, kernel_array(quats[:-1], (len(times) - 1, 4))),
        )
        self._listed: tuple[Waypoint, ...] | None = None  # `waypoints`, made when asked

    def _moved(self, shift: float, blend: _Blend | None) -> Trajectory:
        """This trajectory with another time shift and blend (the segments are shared)."""
        out = Trajectory.__new__(Trajectory)
        out._knots, out._rates = self._knots, self._rates
        out._curve = self._curve.placed(shift, blend)
        out._listed = None
        return out

    @property
    def lead_segments(self) -> int:
        """The segments after_blend joined before the trajectory's own first waypoint
        (0 if none)."""
        blend = self._curve.blend
        return 0 if blend is None else len(blend.leads)

    @property
    def curve(self) -> Curve:
        """What `sample` evaluates: the segments, the time shift and the blend."""
        return self._curve

    def __len__(self) -> int:
        """The number of waypoints (a blend's first one included)."""
        blend = self._curve.blend
        return len(self._knots.times) + (0 if blend is None else len(blend.leads))

    @property
    def waypoints(self) -> tuple[Waypoint, ...]:
        """The waypoints as given (times shifted, a blend's first one first).  Made on
        first use for a shifted or blended trajectory: a cost that grows with their
        number, unlike `knot`, `len` and `sample`."""
        if self._listed is None:
            shift, blend = self._curve.shift, self._curve.blend
            listed = self._knots.waypoints
            if shift != 0.0:
                listed = tuple(Waypoint(w.t + shift, w.pose, w.twist, w.accel) for w in listed)
            self._listed = listed if blend is None else (*blend.leads, *listed)
        return self._listed

    def knot(self, index: int) -> Waypoint:
        """Waypoint `index` (0 <= index < len) with the twist and accel the trajectory
        has there."""
        if not 0 <= index < len(self):
            raise IndexError(f"knot {index} of a trajectory of {len(self)} waypoints")
        blend = self._curve.blend
        if blend is not None:
            if index < len(blend.leads):
                return blend.leads[index]
            index -= len(blend.leads)
        knots, (twists, accels) = self._knots, self._rates
        t = float(knots.times[index]) + self._curve.shift
        return Waypoint(t, knots.pose(index), twists[index], accels[index])

    @property
    def knots(self) -> tuple[Waypoint, ...]:
        """Every `knot`: the waypoints with the trajectory's twist and accel (all set)."""
        return tuple(self.knot(k) for k in range(len(self)))

    @property
    def start_time(self) -> float:
        """Time of the first waypoint (s)."""
        return self._curve.start_time

    @property
    def end_time(self) -> float:
        """Time of the last waypoint (s); the last pose is held from then on."""
        return self._curve.end_time

    @property
    def duration(self) -> float:
        """end_time - start_time (s)."""
        return self._curve.end_time - self._curve.start_time

    def waypoint_index(self, t: float) -> int:
        """Index of the waypoint that starts the segment holding t (clipped to the ends)."""
        curve = self._curve
        k = curve.segment(t)
        if curve.blend is not None:
            leads = len(curve.blend.leads)
            k = k + leads if t >= curve.body_start else curve.blend.segment(t)
        return min(max(k, 0), len(self) - 1)

    def sample(self, t: float) -> Reference:
        """(η_r, φ_r, α_r) at time t: evaluates only the segment holding t."""
        return self._curve.sample(t)

    def sample_many(self, times: Array) -> Samples:
        """sample() at many times at once, as arrays (Curve.sample_many)."""
        return self._curve.sample_many(times)

    def shifted(self, dt: float) -> Trajectory:
        """The same trajectory with every time moved by dt (e.g. to start "now")."""
        dt = float(dt)
        if not math.isfinite(dt):
            raise ValueError(f"time shift must be finite, got {dt!r}")
        blend = self._curve.blend
        return self._moved(self._curve.shift + dt, None if blend is None else blend.shifted(dt))

    def after_blend(self, leads: Sequence[Waypoint], shift: float) -> Trajectory:
        """This trajectory shifted by `shift`, preceded by a segment from each of `leads`
        (their poses, twists and accels all given) to the next, the last into its start
        state.  The segments already built are reused: the cost is that of the leads'
        segments whatever the length."""
        if any(w.twist is None or w.accel is None for w in leads) or not leads:
            raise ValueError("a blend needs its leads, each with its twist and accel")
        if self._curve.blend is not None:
            raise ValueError("this trajectory begins with a blend already")
        out = self.shifted(shift)
        twists, accels = self._rates
        ends = [(w.t, w.pose, w.twist, w.accel) for w in leads[1:]]
        ends.append((out._curve.body_start, self._knots.pose(0), twists[0], accels[0]))
        tables = []
        for w, (t, pose, twist, accel) in zip(leads, ends, strict=True):
            h = t - w.t
            if not h >= MIN_SEGMENT:
                raise TrajectoryError(
                    "times_increasing", f"the blend would last {h:.6g} s (< {MIN_SEGMENT:g} s)"
                )
            step = liediff(w.pose, pose)
            tables.append(segment_table(w.pose, w.twist, w.accel, twist, accel, step, h))
        if not np.all(np.isfinite(tables)):
            raise TrajectoryError("finite", "the blend into this trajectory is not finite")
        quats = tuple(w.pose.quaternion_tuple for w in leads)
        return self._moved(out._curve.shift, _Blend(tuple(leads), tuple(tables), quats))

    def as_dict(self) -> dict:
        """Interface form (JSON / YAML ready), the inverse of parse_trajectory."""
        out = []
        for w in self.waypoints:
            item = {"t": w.t, **w.pose.as_dict()}
            for name in ("twist", "accel"):
                vec = getattr(w, name)
                if vec is not None:
                    item[name] = {"linear": vec[:3].tolist(), "angular": vec[3:].tolist()}
            out.append(item)
        return {"version": SCHEMA_VERSION, "waypoints": out}

    def __repr__(self) -> str:
        return (
            f"Trajectory({len(self)} waypoints, t = {self.start_time:.6g} .. {self.end_time:.6g} s)"
        )


class _Knots:
    """The waypoints as arrays, checked: count, types, finite and increasing times, sane
    magnitudes, rest at the end.

    The bounds on |t| and on the magnitudes keep every spline coefficient and every
    sample of an accepted trajectory finite.  The checks run on whole arrays; a waypoint
    they flag is checked alone (_check_waypoint), which names its problem.  Built from
    Waypoints (`of`) or from arrays (`of_arrays`: the Waypoints made when asked).
    """

    def __init__(
        self,
        times: Array,
        positions: Array,
        quats: Array,
        given: tuple[Array, Array, Array, Array],
        listed: tuple[Waypoint, ...] | None,
    ) -> None:
        self.times, self.positions, self.quats = times, positions, quats
        # the given twists and accels (zero where not given), and where they are given
        self.twists, self.accels, self.twist_given, self.accel_given = given
        self._listed = listed
        n = len(times)
        t = self.times
        with np.errstate(invalid="ignore"):
            good = np.abs(t) <= MAX_TIME
            good[1:] &= t[1:] >= t[:-1] + MIN_SEGMENT
            for vec in (self.positions, self.twists, self.accels):
                good &= np.all(np.abs(vec) <= MAX_MAGNITUDE, axis=1)
        for i in np.flatnonzero(~good).tolist():
            _check_waypoint(self.waypoint(i), i, float(t[i - 1]) if i > 0 else -math.inf)
        _check_at_rest(self.waypoint(n - 1), n - 1)

    @classmethod
    def of(cls, wps: tuple[Waypoint, ...]) -> _Knots:
        """The knots of these waypoints."""
        _check_count(len(wps))
        for i, w in enumerate(wps):
            if not isinstance(w, Waypoint):
                raise TrajectoryError(
                    "schema", f"expected a Waypoint, got {type(w).__name__}", waypoint=i
                )
        n = len(wps)
        twists, accels = np.zeros((n, 6)), np.zeros((n, 6))
        twist_given = np.array([w.twist is not None for w in wps])
        accel_given = np.array([w.accel is not None for w in wps])
        if twist_given.any():
            twists[twist_given] = [w.twist for w in wps if w.twist is not None]
        if accel_given.any():
            accels[accel_given] = [w.accel for w in wps if w.accel is not None]
        return cls(
            np.array([w.t for w in wps]),
            np.array([w.pose.position_tuple for w in wps]),
            np.array([w.pose.quaternion_tuple for w in wps]),
            (twists, accels, twist_given, accel_given),
            wps,
        )

    @classmethod
    def of_arrays(
        cls,
        times: Array,
        positions: Array,
        quats: Array,
        twists: Array | None,
        accels: Array | None,
    ) -> _Knots:
        """The knots of these arrays (Trajectory.through), copied read-only; each
        quaternion must be unit (it is stored normalised); rates None: not given."""
        n = len(times)
        given = [np.full(n, rates is not None) for rates in (twists, accels)]
        twists, accels = (np.zeros((n, 6)) if r is None else r for r in (twists, accels))
        arrays = [np.array(a, dtype=float) for a in (times, positions, quats, twists, accels)]
        times, positions, quats, twists, accels = arrays
        _check_count(n)
        for name, a, width in (
            ("positions", positions, 3), ("quaternions", quats, 4),
            ("twists", twists, 6), ("accels", accels, 6),
        ):  # fmt: skip
            if a.shape != (n, width):
                raise TrajectoryError("schema", f"{name} must be {n} x {width}, not {a.shape}")
        with np.errstate(invalid="ignore"):
            norms = np.linalg.norm(quats, axis=1)
            wrong = np.flatnonzero(~(np.abs(norms - 1.0) <= QUATERNION_NORM_TOLERANCE))
        if len(wrong):
            i = int(wrong[0])
            raise TrajectoryError(
                "unit_quaternion",
                f"quaternion {quats[i].tolist()} has norm {norms[i]:.9g}",
                waypoint=i,
                field=f"waypoints[{i}].quaternion",
            )
        quats /= norms[:, None]
        for a in arrays:
            a.setflags(write=False)
        return cls(times, positions, quats, (twists, accels, *given), None)

    @property
    def waypoints(self) -> tuple[Waypoint, ...]:
        """The knots as Waypoints (made on first use when built from arrays)."""
        if self._listed is None:
            self._listed = tuple(self.waypoint(i) for i in range(len(self.times)))
        return self._listed

    def waypoint(self, i: int) -> Waypoint:
        """Knot i as a Waypoint, its twist and accel where given."""
        if self._listed is not None:
            return self._listed[i]
        twist = self.twists[i] if self.twist_given[i] else None
        accel = self.accels[i] if self.accel_given[i] else None
        return Waypoint(float(self.times[i]), self.pose(i), twist, accel)

    def pose(self, i: int) -> Pose:
        """Knot i's pose."""
        if self._listed is not None:
            return self._listed[i].pose
        return Pose._from_unit(self.positions[i].tolist(), self.quats[i].tolist())


def _check_count(n: int) -> None:
    """A trajectory has two waypoints at least."""
    if n < 2:
        raise TrajectoryError("min_waypoints", f"a trajectory needs at least 2 waypoints, got {n}")


def _check_waypoint(w: Waypoint, i: int, previous: float) -> None:
    """Waypoint i's time (finite, bounded, after `previous`) and magnitudes."""
    if not abs(w.t) <= MAX_TIME:
        raise TrajectoryError(
            "finite",
            f"t = {w.t!r} s is not a finite time within ±{MAX_TIME:g} s",
            waypoint=i,
            value=w.t,
            field=f"waypoints[{i}].t",
        )
    if not w.t >= previous + MIN_SEGMENT:
        raise TrajectoryError(
            "times_increasing",
            f"t = {w.t:.9g} s must exceed the previous waypoint's {previous:.9g} s "
            f"by at least {MIN_SEGMENT:g} s",
            waypoint=i,
            value=w.t,
            field=f"waypoints[{i}].t",
        )
    for name, vec in (("position", w.pose.position), ("twist", w.twist), ("accel", w.accel)):
        if vec is not None and not np.all(np.abs(vec) <= MAX_MAGNITUDE):
            raise TrajectoryError(
                "finite",
                f"{name} {vec.tolist()} is not finite within ±{MAX_MAGNITUDE:g}",
                waypoint=i,
                value=float(np.max(np.abs(vec))),
                field=f"waypoints[{i}].{name}",
            )


def _check_at_rest(last: Waypoint, i: int) -> None:
    """The last waypoint's twist and accel, where given, are zero."""
    for name in ("twist", "accel"):
        vec = getattr(last, name)
        if vec is not None and not np.all(np.abs(vec) <= _REST_TOLERANCE):
            size = float(np.linalg.norm(vec))
            raise TrajectoryError(
                "end_at_rest",
                f"the last waypoint's {name} has norm {size:.6g}; a trajectory must end at "
                "rest (it then holds the last pose)",
                waypoint=i,
                value=size,
                field=f"waypoints[{i}].{name}",
            )


def knot_steps(positions: Array, quats: Array) -> Array:
    """liediff from each pose to the next, (n - 1, 6), of n positions and quaternions."""
    (w1, x1, y1, z1), (w2, x2, y2, z2) = quats[:-1].T, quats[1:].T
    rotations = np.stack(quat_mul4(w2, x2, y2, z2, w1, -x1, -y1, -z1), axis=1)
    return np.concatenate([positions[1:] - positions[:-1], quats_to_rotvecs(rotations)], axis=1)


def _knot_rates(times: Array, values: Array, knots: _Knots) -> tuple[Array, Array]:
    """Knot rates (n, 6) and accelerations (n, 6) of minimum integrated squared jerk.

    `values` holds positions and cumulative rotation vectors at the knots.  Given rates
    are kept; the first knot defaults to rest, the last is at rest.  Unknowns are
    (v_k, a_k) per knot; each segment adds its quintic Hermite jerk cost, so the normal
    equations are banded and symmetric positive definite in the free unknowns.
    """
    n = len(times)
    known = np.zeros((2 * n, 6))
    known[0::2], known[1::2] = knots.twists, knots.accels
    free = np.zeros(2 * n, dtype=bool)
    free[2:-2:2], free[3:-2:2] = ~knots.twist_given[1:-1], ~knots.accel_given[1:-1]
    if free.any():
        h = np.diff(times)
        one = np.ones(n - 1)
        scale = np.stack([one, h, h * h, one, h, h * h], axis=1)
        cost = _JERK_COST * scale[:, :, None] * scale[:, None, :] / (h**5)[:, None, None]
        # per segment k: its unknowns (v_k, a_k, v_k+1, a_k+1) and its two knots' values
        u_idx = 2 * np.arange(n - 1)[:, None] + np.arange(4)
        block = cost[:, 1:][:, [0, 1, 3, 4]][:, :, [1, 2, 4, 5]]  # unknown x unknown
        by_values = cost[:, [1, 2, 4, 5]][:, :, [0, 3]]  # unknown x (y_k, y_k+1)
        # the right-hand side: the values' and the given rates' part, moved over
        ends = np.stack([values[:-1], values[1:]], axis=1)
        rhs = np.zeros((2 * n, 6))
        np.add.at(rhs, u_idx, -(by_values @ ends) - block @ known[u_idx])
        # the free unknowns' matrix, symmetric and banded (3 above the diagonal): each
        # segment's entries between free unknowns, at the free unknowns' own indices
        col = np.cumsum(free) - 1
        rows = np.broadcast_to(u_idx[:, :, None], block.shape)
        cols = np.broadcast_to(u_idx[:, None, :], block.shape)
        upper = free[rows] & free[cols] & (rows <= cols)
        r, c = col[rows[upper]], col[cols[upper]]
        banded = np.zeros((4, int(free.sum())))
        np.add.at(banded, (3 + r - c, c), block[upper])
        d = 1.0 / np.sqrt(banded[3])  # Jacobi scaling: segment lengths may differ a lot
        for shift in range(1, 4):
            banded[3 - shift, shift:] *= d[:-shift] * d[shift:]
        banded[3] *= d * d
        try:
            solved = solveh_banded(banded, d[:, None] * rhs[free], check_finite=False)
        except np.linalg.LinAlgError:  # not positive definite in floating point
            solved = np.full((len(d), 6), np.nan)
        known[free] = d[:, None] * solved
    return known[0::2], known[1::2]


def segment_table(
    pose0: Pose,
    twist0: Array,
    accel0: Array,
    twist1: Array,
    accel1: Array,
    step: Array,
    h: float,
) -> Array:
    """Coefficients of one segment between two knot states: 6 powers of τ (rows) x
    [p, θ | their rates | their accels] (18 columns), see evaluate_segment.

    `step` = liediff(pose0, pose1); segment_tables for one segment.
    """
    rows = (pose0.position, twist0, accel0, twist1, accel1, step)
    return segment_tables(*(np.asarray(r, dtype=float)[None] for r in rows), np.array([h]))[0]


def segment_tables(
    p0: Array, twist0: Array, accel0: Array, twist1: Array, accel1: Array, step: Array, h: Array
) -> Array:
    """segment_table of m segments at once (m, 6, 18): start positions p0 (m, 3), knot
    rates (m, 6) at both ends, steps (m, 6) and durations h (m,).

    θ̇ and θ̈ at the end follow from ω = J_l(θ) θ̇ and ω̇ = J_l θ̈ + J̇_l θ̇ at θ = step;
    at the start θ = 0, so θ̇ = ω and θ̈ = ω̇ there.
    """
    delta = step[:, 3:]
    J = left_jacobians(delta)
    theta_dot1 = np.linalg.solve(J, twist1[:, 3:, None])[..., 0]
    _, jdot_thetadot = angular_rates(delta.T, theta_dot1.T, np.zeros((3, len(h))))
    theta_ddot1 = np.linalg.solve(J, (accel1[:, 3:] - np.stack(jdot_thetadot, 1))[..., None])
    y0 = np.concatenate([p0, np.zeros_like(p0)], axis=1)
    y1 = np.concatenate([p0 + step[:, :3], delta], axis=1)
    v1 = np.concatenate([twist1[:, :3], theta_dot1], axis=1)
    a1 = np.concatenate([accel1[:, :3], theta_ddot1[..., 0]], axis=1)
    return _hermite_coefficients(y0, twist0, accel0, y1, v1, a1, h)


def _hermite_coefficients(
    y0: Array, v0: Array, a0: Array, y1: Array, v1: Array, a1: Array, h: Array
) -> Array:
    """Per segment (m of them), the coefficients of τ^j (rows) of the quintic with value,
    rate, accel at τ = 0, h, followed by those of its first and second derivatives
    (6 + 6 + 6 columns): (m, 6, 18)."""
    hh = (h * h)[:, None]
    data = np.stack([y0, v0 * h[:, None], a0 * hh, y1, v1 * h[:, None], a1 * hh], axis=1)
    c = (_HERMITE @ data) / (h[:, None] ** np.arange(6.0))[:, :, None]
    rate = _DERIVATIVE @ c
    return np.concatenate([c, rate, _DERIVATIVE @ rate], axis=2)


def segment_rates(table: Array, taus: Array) -> tuple[Array, Array]:
    """Twists and accels (k x 6 each) at the k times `taus` into a segment: the rates of
    evaluate_segment for many samples at once (a transition's limit check)."""
    y = (taus[:, None] ** _POWERS).dot(table).T  # 18 rows: values, rates, accels of [p, θ]
    omega, omega_dot = angular_rates(y[3:6], y[9:12], y[15:18])
    twists = np.column_stack([*y[6:9], *omega])
    accels = np.column_stack([*y[12:15], *omega_dot])
    return twists, accels


def evaluate_segment(table: Array, q0: Sequence[float], tau: float) -> Reference:
    """The reference at τ seconds into a segment (`table` from segment_table, start
    rotation q0), by the compiled kernel (cdpr.trajectory.compiled_curve): one product
    of the powers of τ with the table gives the values, rates and accels of [p, θ]
    together."""
    y = segment_sample(kernel_array(table, (6, 18)), q0[0], q0[1], q0[2], q0[3], tau)
    return Reference(Pose._from_unit(y[:3].tolist(), y[3:7].tolist()), y[7:13], y[13:])
