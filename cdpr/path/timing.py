"""Time-optimal timing of a path within the cables' tensions: TOPP-RA (Pham and Pham
2018, the `toppra` package) on each motion of the path (rest to rest: the path is cut at
every dwell and every corner without a blend), with at every grid point along it:

- the wrench the controller's model needs (cdpr.wrench_check: the platform's
  and the winches' inertia, M(q) (q' s'' + q'' s'^2) + mu, the winches' m0 (Lambda
  accel + c)) inside what the cables can give, every tension kept `margin` N inside
  [t_min, f0 + f_b + force_max].  With u = s'' and x = s'^2 the wrench and the tension
  range are affine in (u, x), and so is each facet inequality of the zonotope of
  feasible wrenches (cdpr.wrench_margin's hyperplane shifting: the facet normals depend
  on Lambda alone, the offsets on the range): TOPP-RA's canonical linear form.  The
  winches' damping k0 l' is linear in s', not in (u, x): it is taken at the speed a
  first pass without it found, and the path timed again;
- the platform's linear and angular speed (trajectory limits, and each segment's speed
  cap), each cable's speed (cable_speed_bounds), the platform's linear and angular
  accelerations (each axis within the limit / sqrt(3): inside the limit's ball).

Where the trajectory limits bound the jerk, each motion's time law is then averaged over
a moving window (cdpr.path.time_law: a path jerk of at most the range of s'' over the
window divided by its width), slowed down uniformly by the least factor that brings
every grid point back inside the rows above (a slower time law lies between the average
and rest, which every row holds), and further by the cube root of what its jerk
(cdpr.trajectory.jerk) leaves above a limit: the path's curvature adds jerk that no
window removes (speed cubed times the curvature's rate).  The windows widen by WIDEN,
up to WIDTHS of them and until two in a row give a longer motion than the shortest so
far (the standard paths' durations against the width fall, then rise, with a dip on the
figure-eight's); the one giving the shortest motion is taken.  The jerk of each window
is estimated from its knots (_jerk_estimate), the one taken measured on its trajectory.

The result is a Trajectory through the grid's poses with their twists and accelerations,
which the daemon validates as it validates a client's (daemon.service.path_planning).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cdpr.path.geometry import BlendedPath, path_coordinates
from cdpr.path.jerk_estimate import jerk_peaks
from cdpr.path.model import Path, PathPoint
from cdpr.path.reachability import load_factor, parameterize
from cdpr.path.time_law import AveragedLaw, TimeLaw
from cdpr.reference import model_terms
from cdpr.robot import Robot
from cdpr.so3 import quat_from_matrix
from cdpr.trajectory.core import MIN_SEGMENT, Trajectory, TrajectoryError, knot_steps
from cdpr.trajectory.jerk import JERK_SAMPLES, jerk_excess, jerk_stretch
from cdpr.trajectory.limits import TrajectoryLimits, cable_speed_bounds
from cdpr.wrench_margin import facet_normals, rest_wrenches, wrench_length

Array = NDArray[np.float64]

GRID_STEP = 0.01  # m of (6-D) path between TOPP-RA's grid points on a blend
LINE_STEP = 0.05  # m between them on a line (_grid)
MIN_INTERVALS = 20  # grid intervals of the shortest motion
END_SPLIT = 8  # the first and last grid intervals cut in this many (_grid)
BLEND_INTERVALS = 8  # grid intervals on a blend at least (_grid)
# the share of each speed and acceleration limit the timing plans for: the trajectory's
# quintics between grid points pass above the grid's values (the standard paths at the
# full limits, sampled every 0.1 ms: speeds up to 0.3 % over, accelerations up to 4 %
# over with BLEND_INTERVALS, 15 % on 1 cm blends of two intervals), and the daemon's
# validation refuses what it finds over.  At this share the figure-eight's acceleration
# still reaches 1.021 x the limit between validation's samples (bench/planning.py paths)
LIMIT_SHARE = 0.98
# jerk limits (cdpr.path.time_law): averaging windows from the first (at least MIN_WIDTH
# s), WIDTHS of them each WIDEN times the last; the one that gives the shortest motion
MIN_WIDTH = 0.005
BENDING_SHARE = 0.8  # of a jerk limit: what the path's bending may take (_speed_bounds)
WIDEN = 1.3
WIDTHS = 6
_JERK_INSTANTS = np.linspace(0.0, 1.0, JERK_SAMPLES + 1)  # of a segment


@dataclass(frozen=True)
class Timing:
    """What the timing may ask: the tensions' `margin` (N) inside their range, and the
    grid steps (m of path) on blends and on lines (_grid)."""

    margin: float = 5.0
    step: float = GRID_STEP
    line_step: float = LINE_STEP


def time_path(
    path: Path, robot: Robot, limits: TrajectoryLimits, timing: Timing | None = None
) -> Trajectory:
    """The time-optimal Trajectory along `path` (module docstring); TrajectoryError
    "path_infeasible" naming the pose and the place where no timing holds the tensions."""
    timing = Timing() if timing is None else timing
    length = wrench_length(robot.geometry.attachments)
    parts: list[_Timed] = []
    t = 0.0
    for number, motion in enumerate(_motions(path, length)):
        timed = _time_motion(motion, robot, limits, timing, length, number, t)
        parts.append(timed if not parts else _Timed(*(a[1:] for a in timed)))  # the first
        t = float(timed.times[-1])  # is where the last motion rested
        dwell = motion[-1].dwell
        if dwell > 0.0:
            t += dwell
            rest = np.zeros((1, 6))
            parts.append(_Timed(np.array([t]), timed.positions[-1:], timed.quats[-1:], rest, rest))
    return Trajectory.through(*(np.concatenate(column) for column in zip(*parts, strict=True)))


class _Timed(NamedTuple):
    """Timed grid points: times (n,), positions (n, 3), quaternions (n, 4), twists and
    accelerations (n, 6), as Trajectory.through takes them."""

    times: Array
    positions: Array
    quats: Array
    twists: Array
    accels: Array


def _motions(path: Path, length: float) -> list[list[PathPoint]]:
    """The path cut where the platform must rest: at each dwell and each corner without
    a blend; a point where the path goes on straight is no corner; points where the
    platform already is are dropped."""
    origin = path.points[0].pose.rotation
    coordinates = path_coordinates([point.pose for point in path.points], origin, length)
    # a point within 1e-12 of the one before it is where the platform already is
    moves = np.abs(np.diff(coordinates, axis=0)).max(axis=1) > 1e-12
    kept = [path.points[0]]
    for point, moved in zip(path.points[1:], moves, strict=True):
        if moved:
            kept.append(point)
        else:
            last = kept[-1]
            kept[-1] = PathPoint(last.pose, last.speed, last.blend, last.dwell + point.dwell)
    if len(kept) < 2:
        raise TrajectoryError("path_infeasible", "the path goes nowhere: every pose is the first")
    nodes = coordinates[np.concatenate([[True], moves])]
    steps = np.diff(nodes, axis=0)
    units = steps / np.linalg.norm(steps, axis=1)[:, None]
    turns = np.linalg.norm(np.diff(units, axis=0), axis=1)  # at each interior point
    motions, current = [], [kept[0]]
    for i in range(1, len(kept)):
        current.append(kept[i])
        if i == len(kept) - 1:
            break
        if kept[i].dwell > 0.0 or (kept[i].blend <= 0.0 and turns[i - 1] > 1e-9):
            motions.append(current)
            current = [kept[i]]
    motions.append(current)
    return motions


def _time_motion(
    motion: list[PathPoint],
    robot: Robot,
    limits: TrajectoryLimits,
    timing: Timing,
    length: float,
    number: int,
    start: float,
) -> _Timed:
    """One motion, rest to rest, timed from `start` (s)."""
    geometry = BlendedPath([p.pose for p in motion], [p.blend for p in motion], length)
    grid = _grid(geometry, timing)
    caps = _speed_caps(geometry, motion, grid, limits)
    model = _GridModel.of(geometry, grid, robot)
    rows = _Rows(model, robot, limits, timing.margin, caps)
    damping = np.zeros(len(grid))  # s' at which the winches' damping is taken
    for _ in range(2 if np.any(robot.k0) or np.any(robot.friction) else 1):
        c = rows.constant(damping)
        sdd, speed, _, failed = parameterize(rows.a, rows.b, c, rows.xbound, grid)
        if failed >= 0:
            raise _infeasible(geometry, grid, failed, number)
        damping = speed
    # each knot between two intervals takes the mean of their accelerations: the quintic
    # between two knots given one interval's acceleration at one end and the next one's
    # at the other overshot the limits by 5 % (on blends, 1 cm grid)
    u = np.concatenate([[0.0], 0.5 * (sdd[:-1] + sdd[1:]), [0.0]])
    dt = 2.0 * np.diff(grid) / np.maximum(speed[:-1] + speed[1:], 1e-12)
    times = np.concatenate([[0.0], np.cumsum(dt)])
    if not _jerk_limits(limits):
        return _knots(model, start + times, speed, u)
    law = TimeLaw(grid, speed, sdd, times)
    width, fastest, end = _first_width(model, speed, u, limits), None, math.inf
    longer = 0  # windows in a row that gave a longer motion than the fastest
    for _ in range(WIDTHS):
        times, speed, u = _averaged(law, width, grid, (rows.a, rows.b, c, rows.xbound))
        # what the average leaves above a jerk limit, estimated: slowed down uniformly
        # (the jerk falls with the cube of the stretch; a slower time law stays feasible)
        k = jerk_stretch(_jerk_estimate(model, times, speed, u, limits))
        if times[-1] * k < end:
            fastest, end, longer = (times, speed, u, k), times[-1] * k, 0
        else:
            longer += 1
            if longer == 2:
                break
        width *= WIDEN
    times, speed, u, k = fastest
    knots = _knots(model, start + times * k, speed / k, u / (k * k))
    if not np.any(model.v[:, 3:]):  # the platform does not turn: the estimate is exact
        return knots
    # the fastest window's trajectory measured: stretched by what it really leaves
    exact = jerk_stretch(k**3 * _jerk_excess(knots, limits))
    if exact == k:
        return knots
    return _knots(model, start + times * exact, speed / exact, u / (exact * exact))


def _jerk_limits(limits: TrajectoryLimits) -> list[tuple[int, float, slice]]:
    """(0 linear / 1 angular, the limit, its twist components) of each jerk limit set."""
    pairs = ((limits.linear_jerk, slice(0, 3)), (limits.angular_jerk, slice(3, 6)))
    return [(k, limit, part) for k, (limit, part) in enumerate(pairs) if limit is not None]


def _jerk_excess(knots: _Timed, limits: TrajectoryLimits) -> float:
    """The largest ratio of the trajectory's jerk to its limit (those set)."""
    return jerk_excess(Trajectory.through(*knots), limits.linear_jerk, limits.angular_jerk)


def _knots(model: _GridModel, times: Array, speed: Array, u: Array) -> _Timed:
    """The motion's knots: the grid points reached at `times` with path speeds `speed`
    and accelerations `u`, at rest at both ends (_spaced: the points kept)."""
    kept = _spaced(times)
    v, a, s = model.v[kept], model.acc[kept], speed[kept, None]
    twists = v * s
    accels = v * u[kept, None] + a * s * s
    twists[[0, -1]] = accels[[0, -1]] = 0.0
    return _Timed(times[kept], model.positions[kept], model.quats[kept], twists, accels)


def _jerk_estimate(
    model: _GridModel, times: Array, speed: Array, u: Array, limits: TrajectoryLimits
) -> float:
    """The largest ratio of jerk to its limit (those set) of the quintics _knots would
    put through the grid points at `times`, without building them (cdpr.path.
    jerk_estimate: the linear part exact, the angular part exact about one fixed axis).
    Where the platform turns, the window chosen by it is measured on its trajectory
    (_time_motion)."""
    knots = _knots(model, times, speed, u)
    steps = knot_steps(knots.positions, knots.quats)
    peaks = jerk_peaks(knots.times, steps, knots.twists, knots.accels, _JERK_INSTANTS)
    return max(peaks[k] / limit for k, limit, _ in _jerk_limits(limits))


def _first_width(model: _GridModel, speed: Array, u: Array, limits: TrajectoryLimits) -> float:
    """The averaging window (s) a first try takes: each acceleration's peak over its jerk
    limit, the window that turns a step from rest to the peak into a ramp at the limit
    (a swing from one peak to the other needs twice that: the wider windows tried next,
    and the slowdown for what a window leaves, cover it; starting at twice, the standard
    paths took 2-14 % longer)."""
    accel = model.v * u[:, None] + model.acc * (speed**2)[:, None]
    width = MIN_WIDTH
    for _, limit, part in _jerk_limits(limits):
        width = max(width, float(np.linalg.norm(accel[:, part], axis=1).max()) / limit)
    return width


def _averaged(
    law: TimeLaw, width: float, grid: Array, rows: tuple[Array, Array, Array, Array]
) -> tuple[Array, Array, Array]:
    """(times, speeds, accelerations) at the grid points of `law` averaged over `width`
    s (cdpr.path.time_law), slowed down uniformly by the least factor k that brings
    every grid point's (u, x) back inside the timing's constraint rows: (u, x) / k^2 lies
    between the average's and rest, which every row holds with room (c < 0)."""
    averaged = AveragedLaw(law, width)
    times = averaged.timed_at(grid)
    _, speed, u = averaged.at(times)
    a, b, c, xbound = rows
    x = speed**2
    with np.errstate(divide="ignore", invalid="ignore"):
        over = np.where(xbound[:, 1] > 0.0, x / xbound[:, 1], 0.0)
    k = math.sqrt(max(1.0, load_factor(a, b, c, u, x), float(over.max())))
    return times * k, speed / k, u / (k * k)


def _spaced(times: Array) -> list[int]:
    """The grid points kept as waypoints: the first, the last, and each one at least
    MIN_SEGMENT after the one kept before it (a trajectory's shortest segment).  Near
    rest, where the path's grid is fine (END_SPLIT) or its poses close together, grid
    points come less than that apart in time; the quintic between the kept ones passes
    within micrometres of the others."""
    at = times.tolist()
    kept, last_kept = [0], at[0]
    for i in range(1, len(at) - 1):
        if at[i] - last_kept >= MIN_SEGMENT:
            kept.append(i)
            last_kept = at[i]
    last = len(at) - 1
    if len(kept) > 1 and at[last] - last_kept < MIN_SEGMENT:
        kept.pop()
    return [*kept, last]


def _grid(path: BlendedPath, timing: Timing) -> Array:
    """Grid points along a motion: `timing.step` apart on its blends (BLEND_INTERVALS at
    least on each), where the path bends and the constraints change fastest,
    `timing.line_step` on its lines, where
    they change only as the cables' directions do (MIN_INTERVALS at least over the
    motion), the first and last intervals cut in END_SPLIT: the motion starts and ends at
    rest with no acceleration, which the trajectory's quintic between two grid points
    reaches by braking harder than TOPP-RA's last interval did (a speed 2 % over its cap
    there on a 1 cm grid)."""
    starts, ends, blends = (np.array(column) for column in zip(*path.parts(), strict=True))
    spans = ends - starts
    steps = np.where(blends, np.minimum(timing.step, spans / BLEND_INTERVALS), timing.line_step)
    counts = np.maximum(1, np.ceil(spans / steps).astype(int))  # intervals on each part
    part = np.repeat(np.arange(len(spans)), counts)
    k = np.arange(len(part)) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    points = starts[part] + spans[part] * (k / counts[part])
    points[np.cumsum(counts) - 1] = ends  # each part's end exactly
    grid = np.concatenate([[0.0], points])
    if len(grid) <= MIN_INTERVALS:
        grid = np.linspace(0.0, path.s_end, MIN_INTERVALS + 1)
    first = np.linspace(grid[0], grid[1], END_SPLIT + 1)
    last = np.linspace(grid[-2], grid[-1], END_SPLIT + 1)
    return np.concatenate([first, grid[2:-2], last])


def _speed_caps(
    geometry: BlendedPath, motion: list[PathPoint], grid: Array, limits: TrajectoryLimits
) -> Array:
    """The linear speed cap (m/s) at each grid point: the segment's own (the point it
    ends at), the smaller of the two on a blend, never above limits.linear_speed."""
    caps = [
        limits.linear_speed if p.speed is None else min(p.speed, limits.linear_speed)
        for p in motion
    ]
    per_part = np.array([min(caps[i] for i in pair) for pair in geometry.part_segments])
    return per_part[geometry.part_at(grid)]


def _infeasible(geometry: BlendedPath, grid: Array, stage: int, number: int) -> TrajectoryError:
    """Where the path cannot be timed: the grid point whose speeds cannot be controlled
    (the path's tensions cannot be held there at any speed)."""
    position = geometry(grid[stage])[:3]
    where = ", ".join(f"{c:.3f}" for c in position)
    return TrajectoryError(
        "path_infeasible",
        f"motion {number}: no speed holds every cable within its tensions at "
        f"{grid[stage]:.3f} m along it (position {where} m): the wrench it needs lies "
        "outside what the cables can give there",
    )


@dataclass(frozen=True)
class _GridModel:
    """What the constraints need at each grid point (N of them), the same for every
    pass: the poses (rotations as matrices and quaternions), the path's rates per unit
    s (v = (p', w_s), acc = (p'', w_ss), `third` their rate along the grid),
    the controller's model at twist v (Lambda, c, M, mu) and mu at rest, the facet
    normals of the wrench zonotope (cdpr.wrench_margin.facet_normals: one per facet
    pair, zero where the subset spans no facet) and each normal's product with each
    cable's column of Lambda^T (`facet_cables`)."""

    positions: Array
    rotations: Array
    quats: Array
    v: Array
    acc: Array
    Lam: Array
    c: Array
    M: Array
    mu: Array
    mu_rest: Array
    normals: Array
    facet_cables: Array
    third: Array

    @classmethod
    def of(cls, path: BlendedPath, grid: Array, robot: Robot) -> _GridModel:
        positions, rotations, p1, w1, p2, w2 = path.poses(grid)
        v, acc = np.hstack([p1, w1]), np.hstack([p2, w2])
        Lam, c, M, mu = model_terms(robot, positions, rotations, v)
        mu_rest = -rest_wrenches(robot.platform, rotations)  # mu at zero twist
        third = np.gradient(acc, grid, axis=0)  # the path's third derivative per unit s
        normals = facet_normals(Lam)
        facet_cables = np.matmul(normals, np.swapaxes(Lam, 1, 2))  # c . a_j, facet by cable
        quats = quat_from_matrix(rotations)
        return cls(
            positions, rotations, quats, v, acc, Lam, c, M, mu, mu_rest, normals, facet_cables,
            third,
        )  # fmt: skip


def _times(matrices: Array, vectors: Array) -> Array:
    """Each matrix times its vector (N x r x k by N x k: N x r), as batched matmul."""
    return np.matmul(matrices, vectors[:, :, None])[:, :, 0]


def _transposed_times(matrices: Array, vectors: Array) -> Array:
    """Each matrix's transpose times its vector (N x r x k by N x r: N x k)."""
    return np.matmul(vectors[:, None, :], matrices)[:, 0, :]


class _Rows:
    """The rows a u + b x + c <= 0 and x in xbound of the tension, acceleration and speed
    limits at every grid point (module docstring).  a, b and xbound depend on the path
    alone; c also on the path speeds the winches' damping is taken at (`constant`).

    A facet's two rows, with w = (w_u, w_x, w_1) the wrench's coefficients, e_j = c . a_j
    its normal's product with each cable, and the tension range [lo, hi] (hi = g + f_max
    - margin, g = (g_u, g_x, g_1) the winches' forces): c . w <= sum_j max(e_j lo_j, e_j
    hi_j) and the same below, i.e. c . w - e+ . hi - e- . lo <= 0 and e+ . lo + e- . hi -
    c . w <= 0, e+ and e- the positive and negative parts of e; in u and x, where lo = 0
    and hi = g, these are c . w - e+ . g and e- . g - c . w."""

    def __init__(
        self,
        model: _GridModel,
        robot: Robot,
        limits: TrajectoryLimits,
        margin: float,
        caps: Array,
    ) -> None:
        self.robot = robot
        m0 = robot.m0
        Lam, v, acc = model.Lam, model.v, model.acc
        self.lv = lv = _times(Lam, v)
        la = _times(Lam, acc)
        g = np.stack([m0 * lv, m0 * (la + model.c)], axis=-1)  # (N, n, u/x)
        tau_x = _times(model.M, acc) + model.mu - model.mu_rest
        w = np.stack(
            [
                _transposed_times(Lam, g[:, :, 0]) - _times(model.M, v),
                _transposed_times(Lam, g[:, :, 1]) - tau_x,
            ],
            axis=-1,
        )
        cw = np.matmul(model.normals, w)
        self.positive = np.maximum(model.facet_cables, 0.0)
        self.negative = np.minimum(model.facet_cables, 0.0)
        above, below = np.matmul(self.positive, g), np.matmul(self.negative, g)
        # c . w_1 and the tension range without damping, the same for both passes
        self.facets_1 = _times(model.normals, -model.mu_rest)
        self.lo, self.top = robot.t_min + margin, robot.force_max - margin
        self.above_1 = self.positive @ self.top + self.negative @ self.lo
        self.below_1 = self.positive @ self.lo + self.negative @ self.top
        # accelerations, each axis within the limit / sqrt(3)
        p1, w1, p2, w2 = v[:, :3], v[:, 3:], acc[:, :3], acc[:, 3:]
        self.accel_1 = np.concatenate(
            [np.full(6, limits.linear_accel), np.full(6, limits.angular_accel)]
        ) * (-LIMIT_SHARE / math.sqrt(3.0))
        # facets (both sides), the range open (hi - lo > 0), g >= t_min, accelerations
        self.a = np.hstack(
            [cw[:, :, 0] - above[:, :, 0], below[:, :, 0] - cw[:, :, 0], -0.5 * g[:, :, 0],
             g[:, :, 0], p1, -p1, w1, -w1]
        )  # fmt: skip
        self.b = np.hstack(
            [cw[:, :, 1] - above[:, :, 1], below[:, :, 1] - cw[:, :, 1], -0.5 * g[:, :, 1],
             g[:, :, 1], p2, -p2, w2, -w2]
        )  # fmt: skip
        self.xbound = _speed_bounds(model, robot, limits, caps, lv)

    def constant(self, damping: Array) -> Array:
        """c with the winches' damping taken at path speeds `damping` (one per point):
        the tension range [lo, hi] is [t_min + margin, g_1 + f_max - margin], g_1 the
        damping force (back-EMF and friction: Robot.drag)."""
        robot, lo, top = self.robot, self.lo, self.top
        g_1 = robot.drag(self.lv * damping[:, None])
        above, below = self.above_1, self.below_1
        if np.any(g_1):
            above = above + _times(self.positive, g_1)
            below = below + _times(self.negative, g_1)
        n = len(damping)
        return np.hstack(
            [self.facets_1 - above, below - self.facets_1, -0.5 * (g_1 + top - lo),
             g_1 - robot.force_max - robot.t_min, np.broadcast_to(self.accel_1, (n, 12))]
        )  # fmt: skip


def _speed_bounds(
    model: _GridModel, robot: Robot, limits: TrajectoryLimits, caps: Array, lv: Array
) -> Array:
    """xbound: [0, the least of the speed bounds on x = s'^2] at each grid point: the
    platform's speed (its cap), its turning, each cable's speed, and the jerk the path's
    bending adds at speed s' (its third derivative x s'^3), a share of each jerk limit."""
    p1, w1 = model.v[:, :3], model.v[:, 3:]
    with np.errstate(divide="ignore"):
        columns = [
            (LIMIT_SHARE * caps / np.linalg.norm(p1, axis=1)) ** 2,
            (LIMIT_SHARE * limits.angular_speed / np.linalg.norm(w1, axis=1)) ** 2,
            (LIMIT_SHARE * np.array(cable_speed_bounds(robot, limits)) / np.abs(lv)) ** 2,
        ]
        for _, limit, part in _jerk_limits(limits):
            bending = np.linalg.norm(model.third[:, part], axis=1)
            columns.append((BENDING_SHARE * limit / bending) ** (2.0 / 3.0))
        bounds = np.column_stack(columns)
    return np.column_stack([np.zeros(len(caps)), bounds.min(axis=1)])
