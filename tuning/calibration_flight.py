"""Homing and calibration flown in lock-step on a simulated robot that is not the robot
file (bench/calibration.py).

`Encoders` reads the simulated drums as the drives would: each drive's zero lies where
sim.plant.mismatch.encoder_offsets puts it, scaled by the true drum radius, and the
offsets in force turn positions into lengths.  `home` finds the offsets with the
platform resting at a known pose (cdpr.homing, as the daemon's `home`); `fly_poses` flies
the controller (the robot file's model, enabled at rest as the daemon does) through
rest-to-rest moves to each pose, and records the lengths and commanded forces at rest
there (tuning.calibration.Sample), the payload estimate frozen and the external wrench
observer held as `cdprd calibrate` has them.  `track` runs a standard trajectory with a given
model and offsets and measures the true platform in that model's world frame.
Simulated time only: deterministic, as fast as the plant steps.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdpr import Pose, Robot, liediff
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController, static_tensions
from cdpr.homing import homed_offsets
from cdpr.trajectory import Trajectory, Waypoint
from sim_bus.plant import Plant, equilibrium_tensions
from sim_bus.plant.config import PlantConfig
from tuning.calibration import Sample
from tuning.lockstep import run_lockstep
from tuning.scenarios import start_pose

Array = NDArray[np.float64]
SPEED = 0.25  # m/s of a calibration move (and SPEED rad/s)
DWELL = 1.5  # s at rest at each pose
AVERAGE = 0.3  # s at the end of the dwell averaged into the sample


@dataclass(frozen=True)
class Frame:
    """A rigid change of world frame x -> R x + t (and of the platform frame by `U`:
    the model's platform frame in the true one), for comparing a model's poses with the
    simulated truth."""

    R: Array
    t: Array
    U: Pose

    def to_model(self, pose: Pose) -> Pose:
        """A true (world) pose in the model's frames."""
        world = Pose.from_matrix(self.R @ pose.position + self.t, self.R @ pose.rotation)
        p = world.position + world.rotation @ self.U.position
        return Pose.from_matrix(p, world.rotation @ self.U.rotation)

    def to_world(self, pose: Pose) -> Pose:
        """A pose in the model's frames, in the true world."""
        R = self.R.T @ pose.rotation @ self.U.rotation.T
        p = self.R.T @ (pose.position - self.t) - R @ self.U.position
        return Pose.from_matrix(p, R)


IDENTITY = Frame(np.eye(3), np.zeros(3), Pose((0.0, 0.0, 0.0)))


def best_fit(points: Array, onto: Array) -> tuple[Array, Array]:
    """R, t of the rigid motion minimising |R points + t - onto| (Kabsch)."""
    mp, mo = points.mean(axis=0), onto.mean(axis=0)
    u, _, vt = np.linalg.svd((onto - mo).T @ (points - mp))
    d = np.diag([1.0, 1.0, float(np.linalg.det(u @ vt))])
    R = u @ d @ vt
    return R, mo - R @ mp


def model_frame(true: Robot, model: Robot) -> Frame:
    """How `model`'s frames sit on the truth's: world by the anchors' best rigid fit,
    platform by the attachments' (tuning.calibration's gauge)."""
    R, t = best_fit(np.asarray(true.geometry.anchors), np.asarray(model.geometry.anchors))
    Rb, tb = best_fit(np.asarray(model.geometry.attachments), np.asarray(true.geometry.attachments))
    return Frame(R, t, Pose.from_matrix(tb, Rb))


class Encoders:
    """The drives' view of the simulated drums, as a daemon with `model`'s drum radii
    and `offsets` reads them: offset + (drum - zero) x model radius / true radius (m)."""

    def __init__(self, plant: Plant, model: Robot, offsets: Sequence[float]) -> None:
        mismatch = plant.config.mismatch
        self.zero = -np.array(mismatch.encoder_offsets_for(plant.n))  # true drum length at 0
        self.scale = np.array(
            [m.drum_radius / t.drum_radius for m, t in zip(
                model.actuators, plant.robot.actuators, strict=True)]
        )  # fmt: skip
        self.offsets = np.asarray(offsets, dtype=float)

    def read(self, drums: Array, rates: Array) -> tuple[Array, Array]:
        return self.offsets + (drums - self.zero) * self.scale, rates * self.scale


def _plant(model: Robot, config: PlantConfig, pose: Pose) -> Plant:
    plant = Plant(model, config)
    plant.reset(pose, equilibrium_tensions(plant.robot, pose))
    return plant


def home(model: Robot, config: PlantConfig, pose: Pose, offsets: Sequence[float]) -> Array:
    """The offsets homing finds with the platform resting at `pose` (true world)."""
    plant = _plant(model, config, pose)
    encoders = Encoders(plant, model, offsets)
    lengths, _ = encoders.read(*plant.measure())
    solver = ParallelController(model, ControllerSpec()).tension
    tensions = static_tensions(model, solver, pose)
    return homed_offsets(model, pose, tensions, 1.0, lengths, offsets)


class _Flight:
    """A controller enabled at rest (pose and stiffness fitted as the daemon's enable
    does) in a lock-step loop; `control` is run_lockstep's callback."""

    def __init__(self, model: Robot, spec: ControllerSpec, encoders: Encoders) -> None:
        self.controller = ParallelController(model, spec)
        self.encoders = encoders
        self.fault = ""
        self.enabled = False
        self.switches: list[tuple[float, Trajectory]] = []
        self.log: list[tuple[float, Array, Array]] = []

    def control(self, t: float, drums: Array, rates: Array) -> Array:
        c = self.controller
        lengths, rates = self.encoders.read(drums, rates)
        if not self.enabled:
            robot, solver = c.robot, c.tension
            fk = c.stretch.fit(lengths, lambda pose: static_tensions(robot, solver, pose), c.pose)
            if not fk.converged:
                self.fault = f"enable: forward kinematics failed: {fk.reason}"
            c.reset(fk.pose)
            self.enabled = True
        while self.switches and self.switches[0][0] <= t:
            c.follow(self.switches.pop(0)[1])
        if self.fault:
            return np.zeros(len(drums))
        out = c.step(t, lengths, rates)
        if not np.all(np.isfinite(out.commands)):
            self.fault = f"t={t:.3f} s: {out.reason or 'non-finite commands'}"
            return np.zeros(len(drums))
        self.log.append((t, lengths, out.commands))
        return out.commands


def fly_poses(
    robot: Robot,
    model: Robot,
    spec: ControllerSpec,
    config: PlantConfig,
    offsets: Sequence[float],
    poses: Sequence[Pose],
    start: Pose,
    progress: Callable[[str], None] | None = None,
) -> tuple[list[Sample], str]:
    """Fly the simulated robot (`robot`, the file, with `config`'s mismatch) with `model`
    and `offsets` from rest at `start` (true world) to each of `poses` (the model's
    frame), and record a Sample at rest at each; (samples, fault: "" or why the flight
    stopped)."""
    plant = _plant(robot, config, start)
    flight = _Flight(model, spec, Encoders(plant, model, offsets))
    # as `cdprd calibrate`: the file's platform, the external wrench observer held
    if flight.controller.payload is not None:
        flight.controller.payload.frozen = True
    flight.controller.hold_observer(True)
    # the moves start from the pose measured at enable (the first cycle)
    run_lockstep(plant, flight.control, 0.1, spec.rate_hz)
    t, here = 0.1, flight.controller.pose
    stamps = []
    for target in poses:
        error = liediff(here, target)
        distance = max(float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:])))
        move = max(1.0, distance / SPEED)
        flight.switches.append((t, Trajectory([Waypoint(t, here), Waypoint(t + move, target)])))
        t += move + DWELL
        stamps.append(t)
        here = target
    samples = []
    elapsed = 0.1
    for k, stamp in enumerate(stamps):
        run_lockstep(plant, flight.control, stamp - elapsed, spec.rate_hz)
        elapsed = stamp
        if flight.fault:
            return samples, flight.fault
        recent = [(x, f) for s, x, f in flight.log if s >= stamp - AVERAGE - 1e-9]
        flight.log.clear()
        samples.append(
            Sample(np.mean([x for x, _ in recent], axis=0), np.mean([f for _, f in recent], axis=0))
        )
        if progress is not None:
            progress(f"flying: pose {k + 1} of {len(stamps)} recorded")
    return samples, ""


def track(
    robot: Robot,
    model: Robot,
    spec: ControllerSpec,
    config: PlantConfig,
    offsets: Sequence[float],
    trajectory: Trajectory,
    frame: Frame = IDENTITY,
    settle: float = 0.5,
) -> tuple[float, float, str]:
    """Fly `trajectory` (the model's frame) with `model` and `offsets` on the simulated
    robot (`robot`, the file, with `config`'s mismatch), from rest at its start; (RMS,
    max position error in mm of the true platform in the model's frame against the
    reference, fault or "")."""
    begin = start_pose(trajectory)
    plant = _plant(robot, config, frame.to_world(begin))
    flight = _Flight(model, spec, Encoders(plant, model, offsets))
    flight.switches.append((0.0, trajectory))
    duration = trajectory.end_time - trajectory.start_time + settle
    recording = run_lockstep(plant, flight.control, duration, spec.rate_hz)
    errors = []
    for i, t in enumerate(recording.t.tolist()):
        true = frame.to_model(recording.pose(i))
        errors.append(float(np.linalg.norm(liediff(trajectory.sample(t).pose, true)[:3])))
    e = np.array(errors) * 1e3
    return float(math.sqrt(np.mean(e**2))), float(e.max()), flight.fault
