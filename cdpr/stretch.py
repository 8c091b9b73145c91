"""Cable stretch with an identified stiffness: one common scale of the robot file's
cable compliance 1/EA, estimated from the redundant cable lengths.

The drums measure the unstretched lengths l; forward kinematics needs the geometric
ones, L = l (1 + s t / EA) with EA the robot file's `cable_stiffness`, t the tensions and
s the compliance scale (the file's EA over the true one; 1 when the file is right).  A
wrong EA leaves a length error (s - 1) d, with the stretch vector d = l t / EA; forward
kinematics absorbs the part of it in range(Lambda) as a pose error and leaves the rest
as its residual, which rejects the first measurement for an EA 50 % off.

With n > 6 cables d is usually not in range(Lambda) (a tensed crossed robot stretches
every cable at once, like an internal force), so s is identifiable from the lengths:
after forward kinematics at s, the residual r = L(pose) - l - s d lies in the left null
space of Lambda, and the Gauss-Newton step of the joint problem in (pose, s) is

    ds = (d . r) / |P d|^2,   P d = d - Lambda (Lambda^T Lambda)^-1 Lambda^T d.

Where P d is small against d (the stretch looks like a pose change: s is not
identifiable there) s is left as it is.  `fit` alternates forward kinematics with this
step at rest (static tensions, at enable); `observe` and `update` take a small step
every cycle in flight (the planned tensions stand for the true ones there, so it averages over
ADAPTATION_TIME).  s stays within SCALE_BOUNDS: an EA outside them is a fault the
forward-kinematics residual reports.  What s cannot absorb remains a fault check: a
single cable off by e changes the residual by P e_k e, of which only the part along
P d could hide in s, and in flight s moves far too slowly to hide a sudden one.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import kernel_array, upper_solve
from cdpr.forward_kinematics import FKResult, solve_forward_kinematics
from cdpr.kinematics import AT_REST, pose_rows
from cdpr.pose import Pose
from cdpr.robot import Robot

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

SCALE_BOUNDS = (0.4, 2.5)  # the compliance scale s: an EA from 0.4x to 2.5x the file's
IDENTIFIABLE = 0.05  # |P d|^2 / |d|^2 below which s is not identifiable (left as it is)
ADAPTATION_TIME = 2.0  # s: time constant of the estimate in flight
FIT_ITERATIONS = 6  # forward kinematics alternated with the s step at rest


class ComplianceScale:
    """The estimated compliance scale `scale` of `robot`'s cables (module docstring);
    `stiffness_scale` = 1 / scale is the true EA as a multiple of the robot file's."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.scale = 1.0
        self._elastic = bool(np.any(robot.compliance > 0.0))
        self._compliance = np.array(robot.compliance, dtype=float)  # the kernel's own copy
        if self._elastic:  # numba loads the kernel at its first call: here, not in a cycle
            at_home = robot.cable_lengths(robot.home)
            self._step(at_home, np.ones(robot.n_cables), robot.forward_kinematics(at_home))
        self._observed: tuple[ArrayLike, ArrayLike, FKResult] | None = None

    @property
    def stiffness_scale(self) -> float:
        """The estimated EA over the robot file's."""
        return 1.0 / self.scale

    def stretched(self, lengths: ArrayLike, tensions: ArrayLike) -> Array:
        """Geometric lengths from the drums' `lengths` under `tensions`, at this scale."""
        return self.robot.stretched_lengths(lengths, np.asarray(tensions, dtype=float) * self.scale)

    def fit(
        self, lengths: ArrayLike, tensions_at: Callable[[Pose], Array], guess: Pose
    ) -> FKResult:
        """The pose and the scale from lengths measured at rest, the cables carrying
        `tensions_at(pose)`: forward kinematics alternated with the scale step, from
        `guess` and the current scale.  The last forward kinematics is at the final
        scale (its residual is the fault check)."""
        robot = self.robot
        lengths = np.asarray(lengths, dtype=float)
        unbounded = replace(robot.fk_settings, max_residual=math.inf)  # the fit's own FK
        pose = guess
        for _ in range(FIT_ITERATIONS):
            tensions = tensions_at(pose)
            stretched = self.stretched(lengths, tensions)
            fk = solve_forward_kinematics(robot.geometry, stretched, pose, unbounded)
            step = self._step(lengths, tensions, fk)
            if step is None:
                break
            pose = fk.pose
            self.scale = _bounded(self.scale + step)
        tensions = tensions_at(pose)
        return robot.forward_kinematics(self.stretched(lengths, tensions), pose)

    def observe(self, lengths: ArrayLike, tensions: ArrayLike, fk: FKResult) -> None:
        """A cycle's converged forward kinematics `fk` of `lengths` under `tensions` (at
        this scale), for the next `update`: kept, not used yet, so that a control cycle
        can leave the work to its measurement-free part."""
        self._observed = (lengths, tensions, fk)

    def update(self, period: float) -> None:
        """A small step (time constant ADAPTATION_TIME, for cycles `period` s apart)
        towards the scale the last observed cycle points to; nothing without one."""
        observed, self._observed = self._observed, None
        if observed is None:
            return
        step = self._step(*observed)
        if step is not None:
            self.scale = _bounded(self.scale + step * period / (ADAPTATION_TIME + period))

    def _step(self, lengths: ArrayLike, tensions: ArrayLike, fk: FKResult) -> float | None:
        """The Gauss-Newton step ds at forward kinematics `fk` (None: no step, the fit did
        not converge far enough to have a Jacobian or s is not identifiable)."""
        if not self._elastic or fk.jacobian is None or fk.normal_factor is None:
            return None
        n = self.robot.n_cables
        pose = fk.pose
        step = _scale_step(
            self.robot.geometry.rows, pose.position_tuple, pose.quaternion_tuple,
            kernel_array(lengths, (n,)), self._compliance, kernel_array(tensions, (n,)),
            kernel_array(fk.jacobian, (n, 6)), kernel_array(fk.normal_factor, (6, 6)),
            self.scale,
        )  # fmt: skip
        return None if math.isnan(step) else step


@njit(cache=True)
def _scale_step(
    cables: Array,
    p: tuple[float, float, float],
    q: tuple[float, float, float, float],
    lengths: Array,
    compliance: Array,
    tensions: Array,
    J: Array,
    U: Array,
    scale: float,
) -> float:
    """ds = (d . r) / |P d|^2 at the pose (p, q) (module docstring: d = l t / EA, P d
    its part out of range(Lambda) by the normal equations' factor U, r = L(pose) - l -
    s d); NaN where |P d|^2 <= IDENTIFIABLE |d|^2 (s not identifiable)."""
    n = lengths.shape[0]
    d, x = np.empty(n), np.zeros(6)
    for k in range(n):
        d[k] = lengths[k] * compliance[k] * tensions[k]
        for a in range(6):
            x[a] += d[k] * J[k, a]
    upper_solve(U, x)
    pd2 = dd = 0.0
    for k in range(n):
        projected = d[k]
        for a in range(6):
            projected -= J[k, a] * x[a]
        pd2 += projected * projected
        dd += d[k] * d[k]
    if not pd2 > IDENTIFIABLE * dd:
        return math.nan
    table, geometric = np.empty((n, 7)), np.empty(n)
    pose_rows(cables, p, q, AT_REST, table, geometric)
    along = 0.0
    for k in range(n):
        along += d[k] * (geometric[k] - (lengths[k] + scale * d[k]))
    return along / pd2


def _bounded(scale: float) -> float:
    low, high = SCALE_BOUNDS
    return min(max(scale, low), high)
