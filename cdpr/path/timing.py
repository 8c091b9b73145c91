"""Time-optimal timing of a path within the cables' tensions: TOPP-RA (Pham and Pham
2018, the `toppra` package) on each motion of the path (rest to rest: the path is cut at
every dwell and every corner without a blend), with at every grid point along it:

- the wrench the controller's model needs (cdpr.controller.wrench_check: the platform's
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
window removes (speed cubed times the curvature's rate).  Of WIDTHS windows the one
giving the shortest motion is taken.

The result is a Trajectory through the grid's poses with their twists and accelerations,
which the daemon validates as it validates a client's (daemon.service.path_planning).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import toppra
import toppra.algorithm
import toppra.constraint
from numpy.typing import NDArray

from cdpr.path.geometry import BlendedPath, path_coordinates
from cdpr.path.model import Path, PathPoint
from cdpr.path.time_law import AveragedLaw, TimeLaw
from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.trajectory.core import MIN_SEGMENT, Trajectory, TrajectoryError, Waypoint
from cdpr.trajectory.jerk import segment_jerks
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
BENDING_SHARE = 0.8  # of a jerk limit: what the path's bending may take (_rows)
WIDEN = 1.3
WIDTHS = 6


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
    waypoints: list[Waypoint] = []
    t = 0.0
    for number, motion in enumerate(_motions(path, length)):
        timed = _time_motion(motion, robot, limits, timing, length, number)
        if waypoints:
            timed = timed[1:]  # the first is where the last motion rested
        for w in timed:
            waypoints.append(Waypoint(t + w.t, w.pose, w.twist, w.accel))
        t = waypoints[-1].t
        dwell = motion[-1].dwell
        if dwell > 0.0:
            t += dwell
            waypoints.append(Waypoint(t, waypoints[-1].pose, np.zeros(6), np.zeros(6)))
    return Trajectory(waypoints)


def _motions(path: Path, length: float) -> list[list[PathPoint]]:
    """The path cut where the platform must rest: at each dwell and each corner without
    a blend; a point where the path goes on straight is no corner; points where the
    platform already is are dropped."""
    origin = path.points[0].pose.rotation
    nodes, kept = [], []
    for point in path.points:
        theta_q = path_coordinates(point.pose, origin, length)
        if nodes and np.allclose(theta_q, nodes[-1], atol=1e-12, rtol=0.0):
            last = kept[-1]
            kept[-1] = PathPoint(last.pose, last.speed, last.blend, last.dwell + point.dwell)
            continue
        nodes.append(theta_q)
        kept.append(point)
    if len(kept) < 2:
        raise TrajectoryError("path_infeasible", "the path goes nowhere: every pose is the first")
    motions, current = [], [kept[0]]
    for i in range(1, len(kept)):
        current.append(kept[i])
        if i == len(kept) - 1:
            break
        u_in = nodes[i] - nodes[i - 1]
        u_out = nodes[i + 1] - nodes[i]
        turns = np.linalg.norm(u_out / np.linalg.norm(u_out) - u_in / np.linalg.norm(u_in))
        if kept[i].dwell > 0.0 or (kept[i].blend <= 0.0 and turns > 1e-9):
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
) -> list[Waypoint]:
    """One motion, rest to rest, timed (its own clock from 0)."""
    geometry = BlendedPath([p.pose for p in motion], [p.blend for p in motion], length)
    grid = _grid(geometry, timing)
    caps = _speed_caps(geometry, motion, grid, limits)
    model = _GridModel.of(geometry, grid, robot)
    damping = np.zeros(len(grid))  # s' at which the winches' damping is taken
    for _ in range(2 if np.any(robot.k0) else 1):
        rows = _rows(model, robot, limits, timing.margin, caps, damping)
        constraint = _TensionConstraint(rows)
        problem = toppra.algorithm.TOPPRA([constraint], geometry, gridpoints=grid)
        sdd, speed, _, controllable = problem.compute_parameterization(0.0, 0.0, True)
        if speed is None or np.isnan(speed).any():
            raise _infeasible(geometry, grid, controllable, number)
        damping = speed
    # each knot between two intervals takes the mean of their accelerations: the quintic
    # between two knots given one interval's acceleration at one end and the next one's
    # at the other overshot the limits by 5 % (on blends, 1 cm grid)
    u = np.concatenate([[0.0], 0.5 * (sdd[:-1] + sdd[1:]), [0.0]])
    dt = 2.0 * np.diff(grid) / np.maximum(speed[:-1] + speed[1:], 1e-12)
    times = np.concatenate([[0.0], np.cumsum(dt)])
    if not _jerk_limits(limits):
        return _waypoints(model, times, speed, u)
    law = TimeLaw(grid, speed, sdd, times)
    width, fastest = _first_width(model, speed, u, limits), None
    for _ in range(WIDTHS):
        times, speed, u = _averaged(law, width, grid, rows)
        # what the average leaves above a jerk limit: slowed down uniformly (the jerk
        # falls with the cube of the stretch; a slower time law stays feasible)
        excess = _jerk_excess(_waypoints(model, times, speed, u), limits)
        k = max(1.0, excess ** (1.0 / 3.0) * (1.0 + 1e-9))
        out = _waypoints(model, times * k, speed / k, u / (k * k))
        if fastest is None or out[-1].t < fastest[-1].t:
            fastest = out
        width *= WIDEN
    return fastest


def _jerk_limits(limits: TrajectoryLimits) -> list[tuple[int, float, slice]]:
    """(0 linear / 1 angular, the limit, its twist components) of each jerk limit set."""
    pairs = ((limits.linear_jerk, slice(0, 3)), (limits.angular_jerk, slice(3, 6)))
    return [(k, limit, part) for k, (limit, part) in enumerate(pairs) if limit is not None]


def _jerk_excess(waypoints: list[Waypoint], limits: TrajectoryLimits) -> float:
    """The largest ratio of the trajectory's jerk to its limit (those set)."""
    jerks = segment_jerks(*Trajectory(waypoints).curve.segments()[1:])
    return max(float(jerks[k].max()) / limit for k, limit, _ in _jerk_limits(limits))


def _waypoints(model: _GridModel, times: Array, speed: Array, u: Array) -> list[Waypoint]:
    """The motion's waypoints: the grid points reached at `times` with path speeds
    `speed` and accelerations `u`, at rest at both ends (_spaced: the points kept)."""
    positions, rotations, v, a = model.positions, model.rotations, model.v, model.acc
    out = []
    last = len(times) - 1
    for i in _spaced(times):
        pose = Pose.from_matrix(positions[i], rotations[i])
        if i in (0, last):
            out.append(Waypoint(times[i], pose, np.zeros(6), np.zeros(6)))
        else:
            out.append(
                Waypoint(times[i], pose, v[i] * speed[i], v[i] * u[i] + a[i] * speed[i] ** 2)
            )
    return out


def _first_width(model: _GridModel, speed: Array, u: Array, limits: TrajectoryLimits) -> float:
    """The averaging window (s) a first try takes: each acceleration's largest swing
    (twice its peak) over its jerk limit."""
    accel = model.v * u[:, None] + model.acc * (speed**2)[:, None]
    width = MIN_WIDTH
    for _, limit, part in _jerk_limits(limits):
        width = max(width, 2.0 * float(np.linalg.norm(accel[:, part], axis=1).max()) / limit)
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
    need = a * u[:, None] + b * x[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(c < 0.0, need / -c, 0.0)
        over = np.where(xbound[:, 1] > 0.0, x / xbound[:, 1], 0.0)
    k = math.sqrt(max(1.0, float(ratios.max()), float(over.max())))
    return times * k, speed / k, u / (k * k)


def _spaced(times: Array) -> list[int]:
    """The grid points kept as waypoints: the first, the last, and each one at least
    MIN_SEGMENT after the one kept before it (a trajectory's shortest segment).  Near
    rest, where the path's grid is fine (END_SPLIT) or its poses close together, grid
    points come less than that apart in time; the quintic between the kept ones passes
    within micrometres of the others."""
    kept = [0]
    for i in range(1, len(times) - 1):
        if times[i] - times[kept[-1]] >= MIN_SEGMENT:
            kept.append(i)
    last = len(times) - 1
    if len(kept) > 1 and times[last] - times[kept[-1]] < MIN_SEGMENT:
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
    pieces = [np.zeros(1)]
    for s0, s1, blend in path.parts():
        step = min(timing.step, (s1 - s0) / BLEND_INTERVALS) if blend else timing.line_step
        pieces.append(np.linspace(s0, s1, max(1, math.ceil((s1 - s0) / step)) + 1)[1:])
    grid = np.concatenate(pieces)
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
    segments = geometry.segments(grid)
    return np.array([min(caps[i] for i in pair) for pair in segments])


def _infeasible(
    geometry: BlendedPath, grid: Array, controllable: Array, number: int
) -> TrajectoryError:
    """Where the path cannot be timed: the first grid point whose controllable set is
    empty (the path's tensions cannot be held there at any speed)."""
    empty = [i for i, k in enumerate(controllable) if not np.all(np.isfinite(k)) or k[1] < k[0]]
    i = empty[-1] if empty else 0
    position = geometry(grid[i])[:3]
    where = ", ".join(f"{c:.3f}" for c in position)
    return TrajectoryError(
        "path_infeasible",
        f"motion {number}: no speed holds every cable within its tensions at "
        f"{grid[i]:.3f} m along it (position {where} m): the wrench it needs lies outside "
        "what the cables can give there",
    )


class _TensionConstraint(toppra.constraint.LinearConstraint):
    """TOPP-RA's canonical linear constraint a u + b x + c <= 0 (F = I, g = 0, the same
    at every grid point) for the tensions and accelerations, with the speed bounds on x
    (module docstring): the rows `_rows` computed for the motion's grid."""

    def __init__(self, rows: tuple[Array, Array, Array, Array]) -> None:
        super().__init__()
        self.rows = rows
        self.identical = True

    def compute_constraint_params(self, path, gridpoints, *args, **kwargs):
        """The rows at each grid point i for its interval's (u, x), and the rows of point
        i + 1 for the same u with x + 2 ds u there (TOPP-RA's interpolation scheme): a
        knot's two one-sided accelerations are then both feasible at it, and so is their
        mean, which the trajectory takes (_time_motion)."""
        a, b, c, xbound = self.rows
        twice = 2.0 * np.diff(gridpoints)[:, None]
        a = np.hstack([a, np.vstack([a[1:] + twice * b[1:], a[-1:]])])
        b = np.hstack([b, np.vstack([b[1:], b[-1:]])])
        c = np.hstack([c, np.vstack([c[1:], c[-1:]])])
        width = a.shape[1]
        return a, b, c, np.eye(width), np.zeros(width), None, xbound


@dataclass(frozen=True)
class _GridModel:
    """What the constraints need at each grid point (N of them), the same for every
    pass: the poses, the path's rates per unit s (v = (p', w_s), acc = (p'', w_ss),
    `third` their rate along the grid),
    the controller's model at twist v (Lambda, c, M, mu) and mu at rest, and the facet
    normals of the wrench zonotope (cdpr.wrench_margin.facet_normals: one per facet
    pair, zero where the subset spans no facet)."""

    positions: Array
    rotations: Array
    v: Array
    acc: Array
    Lam: Array
    c: Array
    M: Array
    mu: Array
    mu_rest: Array
    normals: Array
    third: Array

    @classmethod
    def of(cls, path: BlendedPath, grid: Array, robot: Robot) -> _GridModel:
        positions, rotations, p1, w1, p2, w2 = path.poses(grid)
        v, acc = np.hstack([p1, w1]), np.hstack([p2, w2])
        flat = rotations.reshape(len(grid), 9)
        terms = [robot.model_terms_at(*at) for at in zip(positions, flat, v, strict=True)]
        Lam, c, M, mu = (np.array(x) for x in zip(*terms, strict=True))
        mu_rest = -rest_wrenches(robot.platform, rotations)  # mu at zero twist
        third = np.gradient(acc, grid, axis=0)  # the path's third derivative per unit s
        return cls(positions, rotations, v, acc, Lam, c, M, mu, mu_rest, facet_normals(Lam), third)


def _rows(
    model: _GridModel,
    robot: Robot,
    limits: TrajectoryLimits,
    margin: float,
    caps: Array,
    damping: Array,
) -> tuple[Array, Array, Array, Array]:
    """(a, b, c, xbound) of the tension, acceleration and speed limits at every grid
    point: rows a u + b x + c <= 0, x in xbound (module docstring)."""
    m0, k0, t_min, f_max = robot.m0, robot.k0, robot.t_min, robot.force_max
    Lam, v, acc, normals = model.Lam, model.v, model.acc, model.normals
    lv = np.einsum("nkj,nj->nk", Lam, v)
    la = np.einsum("nkj,nj->nk", Lam, acc)
    # w = Lambda^T f0 - tau and the tension range, each as (u, x, 1) coefficients
    g = (m0 * lv, m0 * (la + model.c), k0 * lv * damping[:, None])
    tau_x = np.einsum("nij,nj->ni", model.M, acc) + model.mu - model.mu_rest
    w = (
        np.einsum("nkj,nk->nj", Lam, g[0]) - np.einsum("nij,nj->ni", model.M, v),
        np.einsum("nkj,nk->nj", Lam, g[1]) - tau_x,
        -model.mu_rest,
    )
    lo = t_min + margin
    hi_c = g[2] + f_max - margin
    mid = (0.5 * g[0], 0.5 * g[1], 0.5 * (lo + hi_c))
    rad = (0.5 * g[0], 0.5 * g[1], 0.5 * (hi_c - lo))
    e = np.einsum("nsj,nkj->nsk", normals, Lam)  # c . a_j for each facet and cable
    ae = np.abs(e)
    rows = []
    for w_k, mid_k, rad_k, g_k in zip(w, mid, rad, g, strict=True):
        cw = np.einsum("nsj,nj->ns", normals, w_k)
        em = np.einsum("nsk,nk->ns", e, mid_k)
        ar = np.einsum("nsk,nk->ns", ae, rad_k)
        rows.append([cw - em - ar, em - cw - ar, -rad_k, g_k])  # facets, range open, g
    rows[2][3] = rows[2][3] - f_max - t_min  # g - force_max <= t_min: the lower bound t_min
    # accelerations, each axis within the limit / sqrt(3)
    p1, w1, p2, w2 = v[:, :3], v[:, 3:], acc[:, :3], acc[:, 3:]
    lin = LIMIT_SHARE * limits.linear_accel / math.sqrt(3.0)
    ang = LIMIT_SHARE * limits.angular_accel / math.sqrt(3.0)
    rows[0].append(np.hstack([p1, -p1, w1, -w1]))
    rows[1].append(np.hstack([p2, -p2, w2, -w2]))
    n = len(v)
    rows[2].append(-np.hstack([np.full((n, 6), lin), np.full((n, 6), ang)]))
    a, b, c = (np.hstack(r) for r in rows)
    # speeds: the platform's (its cap), its turning, each cable's
    with np.errstate(divide="ignore"):
        columns = [
            (LIMIT_SHARE * caps / np.linalg.norm(p1, axis=1)) ** 2,
            (LIMIT_SHARE * limits.angular_speed / np.linalg.norm(w1, axis=1)) ** 2,
            (LIMIT_SHARE * np.array(cable_speed_bounds(robot, limits)) / np.abs(lv)) ** 2,
        ]
        # the jerk the path's bending adds at speed s' (its third derivative x s'^3): a
        # share of each jerk limit
        for _, limit, part in _jerk_limits(limits):
            bending = np.linalg.norm(model.third[:, part], axis=1)
            columns.append((BENDING_SHARE * limit / bending) ** (2.0 / 3.0))
        bounds = np.column_stack(columns)
    xbound = np.column_stack([np.zeros(n), bounds.min(axis=1)])
    return a, b, c, xbound
