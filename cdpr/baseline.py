"""The usual CDPR controller, as the baseline the paper's controller is compared with.

Joint space: each cable's PID tracks its inverse-kinematics length l_r = L(eta_r) with
the SAME single-actuator controller (gains per unit mass), scaled by one constant
mass per cable, plus the static tension feed-forward of the reference pose:

    f_c = -t_static(eta_r) + m_k (l_r'' + a_k) + k0 l_r',  a_k = PID(l_k - l_r,k)

m_k is the mass one cable moves when it pulls alone at the home pose,
1 / (Lambda M^-1 Lambda^T)_kk: fixed, no gain scheduling, as such builds are tuned.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.control_spec import ControllerSpec
from cdpr.controller import Hold, ReferenceSource, tension_solver
from cdpr.pose import Pose
from cdpr.robot import Robot

Array = NDArray[np.float64]


class JointSpaceController:
    """Per-cable PID on inverse-kinematics lengths with static tension feed-forward."""

    def __init__(self, robot: Robot, spec: ControllerSpec | None = None) -> None:
        self.robot = robot
        spec = spec or ControllerSpec()
        n = robot.n_cables
        self.loop = spec.linear_controller().discretise(spec.period, n, spec.discretisation)
        self.tension = tension_solver(robot, spec)
        Lam = robot.jacobian(robot.home)
        apparent = Lam @ np.linalg.solve(robot.mass_matrix(robot.home), Lam.T)
        self.cable_mass = 1.0 / np.diag(apparent)
        self._error = np.zeros((self.loop.Dd.shape[1], n))
        self._zero = np.zeros(n)
        self.reset(robot.home)

    def reset(self, pose: Pose) -> None:
        """Hold `pose` with a fresh controller state."""
        self.source: ReferenceSource = Hold(pose)
        self.loop.reset()

    def follow(self, source: ReferenceSource) -> None:
        self.source = source

    def step(self, t: float, lengths: ArrayLike, length_rates: ArrayLike) -> Array:
        """The force commands for this cycle (NaN when the static tensions are infeasible)."""
        robot = self.robot
        ref = self.source.sample(t)
        L_r, Lam_r = robot.lengths_and_jacobian(ref.pose)
        static = self.tension.solve(
            Lam_r, robot.bias_wrench(ref.pose, np.zeros(6)), self._zero, self._zero
        )
        if not static.feasible:
            return np.full(robot.n_cables, np.nan)
        rate_r = Lam_r @ ref.twist
        accel_r = Lam_r @ ref.accel + robot.bias_accel(ref.pose, ref.twist)
        # the drums pay out the unstretched length of the reference cable lengths
        self._error[0] = np.asarray(lengths, dtype=float) - robot.drum_lengths(L_r, static.tensions)
        if self._error.shape[0] > 1:
            self._error[1] = np.asarray(length_rates, dtype=float) - rate_r
        a = self.loop.step(self._error)
        return -static.tensions + self.cable_mass * (accel_r + a) + robot.drag(rate_r)
