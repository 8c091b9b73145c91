"""Closed-loop tracking runs: a controller following a trajectory on the simulated robot.

The plant starts at rest in equilibrium at the trajectory's start pose, the controller
is reset there and follows the trajectory; the run lasts the trajectory plus a settling
time, in lock-step (deterministic).  The figures are those the controller issue asks
for: position / orientation error of the TRUE platform against the reference, tension
range and slack events.  A cycle whose controller reports no feasible command ends the
run (the daemon would brake there).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr import Pose, Robot, liediff
from cdpr.trajectory import Trajectory
from sim_bus.plant import Plant, equilibrium_tensions
from sim_bus.plant.config import PlantConfig
from tuning.lockstep import Recording, run_lockstep
from tuning.scenarios import start_pose

Array = NDArray[np.float64]
SLACK_TENSION = 1.0  # N: a cable below this is counted as slack


class TrackingController(Protocol):
    """ParallelController or the joint-space baseline."""

    def reset(self, pose: Pose) -> None: ...

    def follow(self, source: Trajectory) -> None: ...

    def step(self, t: float, lengths: ArrayLike, length_rates: ArrayLike) -> object: ...


class TrackingFigures(NamedTuple):
    """Error of the true poses against their references, and the cable tensions."""

    rms_mm: float
    max_mm: float
    rms_deg: float
    max_deg: float
    min_tension: float
    max_tension: float
    slack_events: int  # samples where some cable went below SLACK_TENSION (after a taut one)


def pose_errors(references: Sequence[Pose], poses: Sequence[Pose]) -> tuple[Array, Array]:
    """Per sample, the position error (mm) and the orientation error (deg) of the pose
    against its reference."""
    pos_err, ang_err = [], []
    for ref, pose in zip(references, poses, strict=True):
        error = liediff(ref, pose)
        pos_err.append(math.hypot(*error[:3].tolist()))
        ang_err.append(math.degrees(math.hypot(*error[3:].tolist())))
    return np.array(pos_err) * 1e3, np.array(ang_err)


def tracking_figures(
    references: Sequence[Pose], poses: Sequence[Pose], tensions: ArrayLike
) -> TrackingFigures:
    """Figures of one run: the pose at sample i against reference i, tensions (N) one
    row per sample."""
    pos, ang = pose_errors(references, poses)
    tensions = np.asarray(tensions, dtype=float)
    slack = np.any(tensions < SLACK_TENSION, axis=1)
    onsets = int(np.count_nonzero(slack[1:] & ~slack[:-1]) + slack[0])
    return TrackingFigures(
        float(np.sqrt(np.mean(pos**2))),
        float(pos.max()),
        float(np.sqrt(np.mean(ang**2))),
        float(ang.max()),
        float(tensions.min()),
        float(tensions.max()),
        onsets,
    )


class TrackingResult(NamedTuple):
    rms_mm: float
    max_mm: float
    rms_deg: float
    max_deg: float
    min_tension: float
    max_tension: float
    slack_events: int  # cycles where some cable went below SLACK_TENSION (after a taut one)
    fault: str  # "" or why the controller gave up
    recording: Recording

    def figures(self) -> dict[str, float | int | str]:
        """The numbers without the recording (for reports and JSON)."""
        return {k: v for k, v in self._asdict().items() if k != "recording"}


def run_tracking(
    robot: Robot,
    trajectory: Trajectory,
    controller: TrackingController,
    config: PlantConfig | None = None,
    rate_hz: float = 500.0,
    settle: float = 0.5,
    warm_up: float = 0.0,
    latency: float = 0.0,
) -> TrackingResult:
    """Track `trajectory` with `controller` on a plant of `robot` (see module docstring),
    the controller holding the start pose for `warm_up` s before the trajectory (shifted
    by that much) begins, its commands applied `latency` s late (tuning.lockstep)."""
    plant = Plant(robot, config)
    start = start_pose(trajectory)
    plant.reset(start, equilibrium_tensions(plant.robot, start))
    controller.reset(start)
    if warm_up:
        trajectory = trajectory.shifted(warm_up)
    controller.follow(trajectory)
    faults: list[str] = []

    def control(t: float, lengths: Array, rates: Array) -> Array:
        if faults:  # hold the last command's place with zero force: the run is over
            return np.zeros(robot.n_cables)
        out = controller.step(t, lengths, rates)
        commands = np.asarray(getattr(out, "commands", out), dtype=float)
        if not np.all(np.isfinite(commands)):
            faults.append(f"t={t:.3f} s: {getattr(out, 'reason', '') or 'non-finite commands'}")
            return np.zeros(robot.n_cables)
        return commands

    duration = trajectory.end_time - trajectory.start_time + warm_up + settle
    recording = run_lockstep(plant, control, duration, rate_hz, latency)
    return _figures(trajectory, recording, faults[0] if faults else "")


def _figures(trajectory: Trajectory, rec: Recording, fault: str) -> TrackingResult:
    times = rec.t.tolist()
    references = [trajectory.sample(t).pose for t in times]
    poses = [rec.pose(i) for i in range(len(times))]
    return TrackingResult(*tracking_figures(references, poses, rec.tensions), fault, rec)
