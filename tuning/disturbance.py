"""Disturbance rejection: the holding robot pushed by an external wrench step (a person
leaning on the platform, a tool touching something), in simulated time (issue 19).

The plant (sim_bus.plant, elastic cables, drive lag, encoder quantisation as in the
standard set) holds the home pose under the paper's controller; at `start` a constant
wrench begins to act on the platform and stays.  Reported: the largest position error
of the TRUE platform from home, the 2 % settling time (from the step until the error
stays within 2 % of that peak, or 0.1 mm, whichever is larger: the integral action
brings it back), the error left at the end, and whether the controller faulted.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from sim_bus.plant import Plant, equilibrium_tensions
from sim_bus.plant.config import DisturbanceConfig, PlantConfig
from tuning.lockstep import run_lockstep

SETTLE_BAND = 0.02  # of the peak error
SETTLE_FLOOR = 1e-4  # m: a band never narrower than this (encoder quantisation)


class DisturbanceFigures(NamedTuple):
    peak_mm: float
    peak_offset_mm: tuple[float, float, float]  # where the platform was then, from home
    settle_s: float  # inf when it never settles within the run
    final_mm: float
    fault: str  # the controller's first fault, "" if none


def step_response(
    robot: Robot,
    spec: ControllerSpec,
    wrench: tuple[float, ...] = (50.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    start: float = 0.5,
    duration: float = 4.0,
    rate_hz: float = 500.0,
    config: PlantConfig | None = None,
) -> DisturbanceFigures:
    """The holding robot's response to `wrench` (N, N·m; world frame) from `start` on."""
    config = (config or PlantConfig()).model_copy(
        update={"disturbance": DisturbanceConfig(wrench=wrench, start=start)}
    )
    plant = Plant(robot, config)
    home = robot.home
    plant.reset(home, equilibrium_tensions(plant.robot, home))
    controller = ParallelController(robot, spec)
    controller.reset(home)
    faults: list[str] = []

    def control(t: float, lengths: Any, rates: Any) -> np.ndarray:
        out = controller.step(t, lengths, rates)
        if not np.all(np.isfinite(out.commands)):
            faults.append(f"t={t:.3f} s: {out.reason or 'non-finite commands'}")
        return out.commands if not faults else np.zeros(robot.n_cables)

    rec = run_lockstep(plant, control, duration, rate_hz)
    times = rec.t
    offsets = rec.series["position"] - home.position
    errors = np.linalg.norm(offsets, axis=1)
    after = times >= start
    worst = int(np.argmax(np.where(after, errors, -1.0)))
    peak = float(errors[worst])
    band = max(SETTLE_BAND * peak, SETTLE_FLOOR)
    outside = np.flatnonzero(after & (errors > band))
    if len(outside) == 0:
        settle = 0.0
    elif outside[-1] == len(times) - 1:
        settle = float("inf")
    else:
        settle = float(times[outside[-1] + 1] - start)
    fault = faults[0] if faults else ""
    offset = tuple(float(v) * 1e3 for v in offsets[worst])
    return DisturbanceFigures(peak * 1e3, offset, settle, float(errors[-1]) * 1e3, fault)
