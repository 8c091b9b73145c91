"""Flying with a cable stiffness the robot file has wrong.

`EnabledAtRest` wraps the controller so that a lock-step run enables as the daemon does
(Service.measured_pose): the first cycle's lengths, measured at rest, give the pose and
the cables' stiffness estimate (cdpr.stretch) before the controller flies.
`stiffness_sweep` runs the standard trajectories on plants whose true EA is a multiple
of the robot file's `cable_stiffness`, and reports per run whether it flew (the fault
that would brake the daemon, if any), the RMS / max position error of the true platform,
the estimate after the fit at rest and at the end, and the largest FK residual
(bench/stiffness.py prints them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from cdpr import Pose, Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ControlOutput, ParallelController, static_tensions
from cdpr.trajectory import Trajectory
from sim_bus.plant import PlantConfig
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking

FACTORS = (0.5, 0.6, 1.0, 1.5, 2.0)  # true EA / the robot file's


class EnabledAtRest:
    """A ParallelController whose first step first fits pose and stiffness at rest, as
    the daemon's enable does; records each cycle's FK residual and the estimate."""

    def __init__(self, controller: ParallelController) -> None:
        self.controller = controller
        self.fitted: float | None = None  # the stiffness estimate after the fit at rest
        self.residuals: list[float] = []
        self.estimates: list[float] = []

    def reset(self, pose: Pose) -> None:
        self.controller.reset(pose)
        self.fitted = None

    def follow(self, source: Trajectory) -> None:
        self.controller.follow(source)

    def step(self, t: float, lengths: ArrayLike, length_rates: ArrayLike) -> ControlOutput:
        c = self.controller
        if self.fitted is None:
            robot, solver = c.robot, c.tension
            c.stretch.fit(lengths, lambda pose: static_tensions(robot, solver, pose), c.pose)
            self.fitted = c.stretch.stiffness_scale
        out = c.step(t, lengths, length_rates)
        self.residuals.append(out.fk_residual)
        self.estimates.append(c.stretch.stiffness_scale)
        return out


def true_stiffness(robot: Robot, factor: float) -> PlantConfig:
    """A plant whose cables' EA is `factor` times the robot file's (its first cable's)."""
    stiffness = robot.actuators[0].cable_stiffness
    if stiffness is None:
        raise ValueError(f"robot {robot.name} declares no cable_stiffness")
    return PlantConfig.model_validate({"cable": {"stiffness": stiffness * factor}})


def fly(robot: Robot, spec: ControllerSpec, factor: float, name: str) -> dict[str, Any]:
    """One standard trajectory `name`, enabled at rest, true EA = factor x the file's."""
    controller = EnabledAtRest(ParallelController(robot, spec))
    result = run_tracking(
        robot, STANDARD_SET[name](robot), controller, true_stiffness(robot, factor), spec.rate_hz
    )
    residuals = np.array(controller.residuals)
    return {
        "ea_factor": factor,
        "trajectory": name,
        "flew": not result.fault,
        "fault": result.fault,
        "rms_mm": result.rms_mm,
        "max_mm": result.max_mm,
        "estimate_at_rest": controller.fitted,
        "estimate_end": controller.estimates[-1],
        "max_fk_residual_mm": float(np.nanmax(residuals) * 1e3),
    }


def stiffness_sweep(
    robot: Robot,
    spec: ControllerSpec,
    factors: Sequence[float] = FACTORS,
    names: Sequence[str] = tuple(STANDARD_SET),
) -> list[dict[str, Any]]:
    """`fly` for every factor and trajectory."""
    return [fly(robot, spec, factor, name) for factor in factors for name in names]
