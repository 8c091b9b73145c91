"""Pretension in lock-step (simulated time): the daemon's bring-up from slack cables on a
docking fixture, without the CAN bus (bench/calibration.py's pretension keys).

The plant starts on its fixture (sim_bus.plant.fixture) with slack cables; each cycle
runs cdpr.pretension as the daemon's core does, then, at its end, homes at the fixture
pose (cdpr.homing) and closes the position loop like the daemon's enable (the pose and
stiffness fitted at rest, ParallelController.reset) and holds for `hold` seconds.
Measured on the plant's truth: how far the platform moved from where it rested, the
largest cable tension, and the step in force when the loop closed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from cdpr.homing import homed_offsets
from cdpr.pretension import Pretension, PretensionSpec, ramp_target
from sim_bus.plant import Plant, PlantConfig
from tuning.lockstep import run_lockstep

Array = NDArray[np.float64]


@dataclass
class PretensionRun:
    taut_seconds: float  # s from the start until the last cable was taut
    motion_mm: float  # largest true platform displacement from its resting position
    watched_mm: float  # the largest the pretension's own watch saw (cdpr.pretension)
    peak_force_n: float  # largest true cable tension
    loop_close_step_n: float  # largest change of a force command when the loop closed
    closed_at: float  # s, when the position loop closed (nan: never)
    fault: str  # why it aborted ("" if not)


class _Bringup:
    """run_lockstep's callback: pretension, then homing and the position loop."""

    def __init__(
        self, robot: Robot, controller: ControllerSpec, spec: PretensionSpec, pose_name: str
    ) -> None:
        self.robot = robot
        self.controller = ParallelController(robot, controller)
        self.pose = robot.poses[pose_name]
        self.spec = spec
        self.pretension: Pretension | None = None
        self.offsets = np.zeros(robot.n_cables)
        self.closed_at = math.nan
        self.step_at_close = math.nan
        self.fault = ""

    def __call__(self, t: float, lengths: Array, rates: Array) -> Array:
        c, robot, p = self.controller, self.robot, self.pretension
        if p is None:
            target = ramp_target(robot, c.tension, self.pose, self.spec.carry)
            p = self.pretension = Pretension(
                robot, self.spec, self.pose, target, c.stretch.scale, lengths
            )
        if p.active:
            return p.step(t, lengths, rates)
        if p.fault:
            self.fault = self.fault or p.fault
            return p.forces
        if p.phase == "done":
            assert p.settled_lengths is not None
            self.offsets = homed_offsets(robot, self.pose, p.planned, c.stretch.scale,
                                         p.settled_lengths, self.offsets)  # fmt: skip
            fk = c.stretch.fit(lengths + self.offsets, lambda pose: p.planned, self.pose)
            p.close(c, fk.pose, t)
            self.closed_at = t
        p.unload(c, t)
        out = c.step(t, lengths + self.offsets, rates)
        if not out.feasible:
            self.fault = self.fault or f"t={t:.3f} s: {out.reason}"
            return p.forces
        if math.isnan(self.step_at_close):
            self.step_at_close = float(np.abs(out.commands - p.forces).max())
        return out.commands


def run_pretension(
    robot: Robot,
    plant: PlantConfig,
    controller: ControllerSpec | None = None,
    spec: PretensionSpec | None = None,
    hold: float = 1.0,
    latency: float = 2e-3,
) -> PretensionRun:
    """Bring up `plant` (its `fixture` set: the platform resting there, cables slack)
    with the file's `robot`, then hold for `hold` s with the loop closed."""
    if plant.fixture is None:
        raise ValueError("run_pretension needs sim.plant.fixture (the platform on a fixture)")
    controller = controller or ControllerSpec()
    spec = spec or PretensionSpec()
    simulated = Plant(robot, plant)
    bringup = _Bringup(robot, controller, spec, plant.fixture.pose)
    rest = simulated.pose.position.copy()
    slack = max(plant.fixture.slack_for(robot.n_cables))
    ramp = float(robot.force_max.max()) / spec.ramp_rate
    duration = slack / spec.wind_speed + 2.0 * spec.taut_time + ramp + spec.settle_time
    duration += spec.unload_time + hold
    recording = run_lockstep(simulated, bringup, duration, controller.rate_hz, latency)
    pretension = bringup.pretension
    assert pretension is not None
    t = recording.t
    end = bringup.closed_at + spec.unload_time + hold
    until = t <= (t[-1] if math.isnan(end) else end)
    moved = np.linalg.norm(recording.position[until] - rest, axis=1).max()
    return PretensionRun(
        taut_seconds=float(np.nanmax(pretension.taut_at)),
        motion_mm=float(moved * 1e3),
        watched_mm=pretension.motion * 1e3,
        peak_force_n=float(recording.tensions[until].max()),
        loop_close_step_n=bringup.step_at_close,
        closed_at=bringup.closed_at,
        fault=bringup.fault or (pretension.fault or ""),
    )
