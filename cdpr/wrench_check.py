"""The controller's wrench check for trajectories (DESIGN §7), one sample at a time and
screened in batches: the daemon's validation asks it of every sampled reference.

Its own module, apart from cdpr.controller: its batch screen is compiled
(cdpr.compiled_model), and the real-time core, which runs the controller, does not load
numba.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cdpr.compiled_model import wrench_screen
from cdpr.pose import Pose
from cdpr.pose_limits import SCREEN_MARGIN
from cdpr.robot import Robot
from cdpr.tension import TensionSolver
from cdpr.trajectory import Samples, Screened

Array = NDArray[np.float64]


class ModelWrenchCheck:
    """A trajectory check (DESIGN §7): is the wrench the controller would need to follow
    (pose, twist, accel) exactly — steps 7–10 with α_c = α_r — in W?  Called: None if
    it is, else the reason.  `screen`: the same question for a batch of samples, as far
    as a batch can answer it (compiled: load it with daemon.service.planner.load_checks
    before a validation shares a control cycle's event loop)."""

    def __init__(self, robot: Robot, tension: TensionSolver) -> None:
        self.robot, self.tension = robot, tension
        limits = tension.limits
        self._cables = robot.geometry.rows
        self._actuators = np.array(
            [robot.m0, robot.k0, robot.friction, limits.t_min, limits.force_max, limits.t_ref]
        )
        self._margin = SCREEN_MARGIN * float(limits.force_max.max())  # N

    def __call__(self, pose: Pose, twist: Array, accel: Array) -> str | None:
        robot = self.robot
        Lam, c, M, mu = robot.model_terms(pose, twist)
        result = self.tension.solve(
            Lam, M @ accel + mu, robot.drag(Lam @ twist), robot.m0 * (Lam @ accel + c)
        )
        return None if result.feasible else f"wrench not in W: {result.reason}"

    def screen(self, samples: Samples) -> Screened:
        """The samples' cable lengths and Jacobians, and which samples' wrenches certainly
        lie in W: the least-norm tensions about t_ref (cdpr.tension's closed form before
        it fixes a cable) carry the wrench and lie inside their bounds at t_min by
        SCREEN_MARGIN x the largest force_max, a tension vector in W whichever solver the
        call would use (cdpr.compiled_model.wrench_screen).  Not clear means only that the
        call must decide (a bound active, a singular pose)."""
        robot = self.robot
        count, n = len(samples.times), robot.n_cables
        clear = np.empty(count, np.bool_)
        lengths, jacobians = np.empty((count, n)), np.empty((count, n, 6))
        wrench_screen(
            samples.positions, samples.rotations, samples.twists, samples.accels,
            self._cables, robot.platform.rows, self._actuators, self._margin,
            clear, lengths, jacobians,
        )  # fmt: skip
        return Screened(clear, lengths, jacobians)


def wrench_check(robot: Robot, tension: TensionSolver) -> ModelWrenchCheck:
    """The controller's wrench check for trajectories (ModelWrenchCheck)."""
    return ModelWrenchCheck(robot, tension)
