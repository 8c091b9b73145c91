"""Shared closed-loop test runs: the controller holding a pose on the simulated robot."""

from __future__ import annotations

import numpy as np

from cdpr import Pose, Robot, liediff
from cdpr.controller import ControlOutput, Hold, ParallelController
from sim_bus.plant import Plant, PlantConfig, equilibrium_tensions
from tuning.lockstep import Recording, run_lockstep

RATE = 500.0


def hold_run(
    robot: Robot,
    controller: ParallelController,
    target: Pose,
    duration: float,
    start: Pose | None = None,
    start_tensions: np.ndarray | None = None,
    plant_config: PlantConfig | None = None,
) -> tuple[Recording, list[ControlOutput]]:
    """Plant at rest at `start` (home) under `start_tensions` (the plant's equilibrium),
    controller reset there and asked to hold `target`; returns (recording, outputs).
    `plant_config` makes the plant (the TRUE robot: mismatch, actuator model)."""
    start = robot.home if start is None else start
    if start_tensions is None:
        start_tensions = equilibrium_tensions(robot, start)
    plant = Plant(robot, plant_config)
    plant.reset(start, start_tensions)
    controller.reset(start)
    controller.follow(Hold(target))
    outputs: list[ControlOutput] = []

    def control(t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        out = controller.step(t, lengths, rates)
        outputs.append(out)
        return out.commands if out.feasible else np.zeros(robot.n_cables)

    return run_lockstep(plant, control, duration, RATE), outputs


def pose_errors(rec: Recording, target: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and angle (rad) error of the true platform per cycle."""
    e = np.array([liediff(target, rec.pose(i)) for i in range(len(rec))])
    return np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)
