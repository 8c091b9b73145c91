"""The time-optimal duration of one rest-to-rest motion along a path, computed
independently of cdpr.path.timing's TOPP-RA and its facets: the convex formulation of
Verscheure, Demeulenaere, Swevers, De Schutter and Diehl (2009, "Time-optimal path
tracking for robots: a convex optimization approach") with the tensions themselves as
variables at every grid point.  b = s'^2 at grid points, a = s'' between them, the
controller's model (cdpr.wrench_check's quantities: tau = M accel + mu,
f0 = m0 (Lambda accel + c)) Lambda^T t = Lambda^T f0 - tau with t within [max(t_min,
f0 - force_max), f0 + force_max] less `margin`, the same speed and acceleration limits,
and the time sum 2 ds / (sqrt(b_i) + sqrt(b_i+1)) minimised as a second-order cone
program (cvxpy with Clarabel; a test extra).  The winches' damping is left out (it is
linear in s', not convex in (a, b)): give a robot with k0 = 0.

The tests and bench/planning.py hold TOPP-RA's durations to it.
"""

from __future__ import annotations

import numpy as np

from cdpr.path.geometry import BlendedPath
from cdpr.pose import Pose
from cdpr.robot import Robot
from cdpr.trajectory import TrajectoryLimits, cable_speed_bounds
from cdpr.wrench_margin import wrench_length


def convex_duration(
    poses: list[Pose],
    blends: list[float],
    robot: Robot,
    limits: TrajectoryLimits,
    margin: float,
    step: float,
) -> float:
    """The least duration (s) of the motion through `poses` (rest to rest, corners
    rounded by `blends`) on a `step` (m) grid (module docstring)."""
    import cvxpy as cp

    if np.any(robot.k0):
        raise ValueError("convex_duration: the winches' damping k0 must be 0")
    path = BlendedPath(poses, blends, wrench_length(robot.geometry.attachments))
    grid = np.linspace(0.0, path.s_end, int(np.ceil(path.s_end / step)) + 1)
    ds = np.diff(grid)
    positions, rotations, p1, w1, p2, w2 = path.poses(grid)
    n, N = robot.n_cables, len(grid)
    b = cp.Variable(N, nonneg=True)
    a = cp.Variable(N - 1)
    # tensions in hundreds of N and the time in ms: unscaled, Clarabel reported OPTIMAL
    # 1.6 % above a feasible point it had not found
    t = 100.0 * cp.Variable((N, n))
    constraints = [b[0] == 0, b[-1] == 0, b[1:] - b[:-1] == 2 * cp.multiply(ds, a)]
    speeds = np.array(cable_speed_bounds(robot, limits))
    root3 = np.sqrt(3.0)
    zero = np.zeros(6)
    for i in range(N):
        u = a[min(i, N - 2)]
        pose = Pose.from_matrix(positions[i], rotations[i])
        v, acc = np.concatenate([p1[i], w1[i]]), np.concatenate([p2[i], w2[i]])
        Lam, c_v, M, mu_v = robot.model_terms(pose, v)
        mu_g = robot.model_terms(pose, zero)[3]
        tau = M @ v * u + (M @ acc + mu_v - mu_g) * b[i] + mu_g
        f0 = cp.multiply(robot.m0 * (Lam @ v), u) + cp.multiply(robot.m0 * (Lam @ acc + c_v), b[i])
        constraints += [
            Lam.T @ t[i] == Lam.T @ f0 - tau,
            t[i] >= robot.t_min + margin,
            t[i] >= f0 - robot.force_max + margin,
            t[i] <= f0 + robot.force_max - margin,
            cp.abs(p1[i] * u + p2[i] * b[i]) <= limits.linear_accel / root3,
            cp.abs(w1[i] * u + w2[i] * b[i]) <= limits.angular_accel / root3,
        ]
        caps = [limits.linear_speed / np.linalg.norm(p1[i])] if np.any(p1[i]) else []
        caps += [limits.angular_speed / np.linalg.norm(w1[i])] if np.any(w1[i]) else []
        rates = np.abs(Lam @ v)
        caps += [s / r for s, r in zip(speeds, rates, strict=True) if r > 0]
        constraints.append(b[i] <= min(caps) ** 2)
    root = cp.sqrt(b)
    time = cp.sum(cp.multiply(2 * ds, cp.inv_pos(root[:-1] + root[1:])))
    problem = cp.Problem(cp.Minimize(1000.0 * time), constraints)
    problem.solve(solver=cp.CLARABEL)
    if problem.status != cp.OPTIMAL:
        raise RuntimeError(f"convex_duration: the solver ended {problem.status}")
    return float(problem.value) / 1000.0
