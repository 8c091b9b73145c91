"""The paper's single-actuator procedure on one winch: settings, lock-step run, results.

`cdprd tune` (daemon.cli.tune_cmd) runs the experiment on a bus in real time; tests and
bench/tune.py run the same experiment against the simulator's rig with frames exchanged
in simulated time (tuning.can_lockstep).  Both fit the model (tuning.identify) and
design gains from it (tuning.gain_design); this module holds what they share.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import can
import numpy as np

from cdpr import Robot
from drivers.config import DrivesConfig
from drivers.factory import protocol_driver
from sim_bus.config import RigConfig
from sim_bus.plant.config import PlantConfig
from sim_bus.virtual_robot import VirtualRobot
from tuning.can_lockstep import LockstepLink, run_experiment
from tuning.experiment import Abort, Load, Plan, Record, WinchExperiment
from tuning.identify import Identified, Setup, fit

LATENCY_PERCENTILE = 95.0


class Request(NamedTuple):
    """What the user asks for: the cable (`drive`), the load (a hanging mass in kg, or
    clamped with a pretension in N), the amplitude limit and the excitation level (N),
    the excitation time and the travel allowed (m)."""

    drive: int = 0
    load_mass: float = 0.0
    clamped: bool = False
    preload: float = 100.0
    amplitude: float = 20.0
    excitation: float | None = None  # default: 0.75 amplitude
    duration: float = 20.0
    travel: float = 0.1
    seed: int = 0


def load_of(robot: Robot, request: Request) -> Load:
    """The passive load of `request` for `robot` (its gravity)."""
    if request.clamped:
        return Load.clamped(request.preload)
    return Load.hanging(request.load_mass, float(np.linalg.norm(robot.platform.gravity)))


def plan_for(robot: Robot, request: Request, rate_hz: float) -> Plan:
    """The experiment plan: the request's amplitudes and the robot file's actuator
    (range, force limit, starting guess) for cable `request.drive`."""
    if not 0 <= request.drive < robot.n_cables:
        raise ValueError(f"--drive {request.drive}: the robot has cables 0..{robot.n_cables - 1}")
    act = robot.actuators[request.drive]
    excitation = 0.75 * request.amplitude if request.excitation is None else request.excitation
    return Plan(
        amplitude=request.amplitude,
        excitation=excitation,
        duration=request.duration,
        travel=request.travel,
        length_min=act.length_min,
        length_max=act.length_max,
        force_max=act.force_max,
        m0_guess=act.m0,
        k0_guess=act.k0,
        period=1.0 / rate_hz,
        seed=request.seed,
    )


def setup_for(robot: Robot, request: Request, record: Record) -> Setup:
    """What the fit knows: the robot file's actuator, the load, the cable length (the
    length at the start of the record) and EA (the robot file's, else the plant default)."""
    act = robot.actuators[request.drive]
    stiffness = act.cable_stiffness or PlantConfig().cable.stiffness
    return Setup(act, load_of(robot, request), float(record.length[0]), stiffness)


class Run(NamedTuple):
    """One experiment: its record, its abort (None: it ran to the end), the fitted model
    (None after an abort), frames exchanged, the excitation time (s) and the loop's
    latency (s: from a sample to its answer taking effect: the LATENCY_PERCENTILE of the
    host's, receipt to command, plus the bus's delay both ways)."""

    record: Record
    abort: Abort | None
    model: Identified | None
    frames: int
    experiment_seconds: float
    latency: float


def identify_simulated(
    robot: Robot,
    drives: DrivesConfig,
    plant: PlantConfig,
    request: Request,
    rate_hz: float,
    faults: list[tuple[float, str]] | None = None,
    true_load: float | None = None,
    true: Robot | None = None,
) -> Run:
    """The identification experiment against the simulator's rig (run_simulated)."""
    experiment = WinchExperiment(plan_for(robot, request, rate_hz), load_of(robot, request))
    abort, frames = run_simulated(
        robot, drives, plant, request, experiment, faults, true_load, true
    )
    return finish(robot, request, experiment, abort, frames)


def run_simulated(
    robot: Robot,
    drives: DrivesConfig,
    plant: PlantConfig,
    request: Request,
    experiment: WinchExperiment,
    faults: list[tuple[float, str]] | None = None,
    true_load: float | None = None,
    true: Robot | None = None,
) -> tuple[Abort | None, int]:
    """`experiment` against the simulator's rig (sim.rig for `request`), the drive's
    frames exchanged in simulated time; `faults` (simulated time, kind: drive, snap or
    silent) are injected on the way; `true_load` (kg) hangs instead of the mass the
    request names (a user who got the load wrong); `true` is the robot the simulator
    builds its winch on (sim.robot: sim_bus.config.true_base; default `robot`, the
    host's).  Its abort, and the frames."""
    mass = request.load_mass if true_load is None else true_load
    rig = RigConfig(
        drive=request.drive,
        load_mass=0.0 if request.clamped else mass,
        clamped=request.clamped,
        preload=request.preload,
    )
    sim = VirtualRobot(robot if true is None else true, drives, plant, rig)
    one = drives.single(request.drive)
    driver = protocol_driver(one, [drives.scalings_for(robot)[request.drive]])
    link = LockstepLink(sim, driver)
    for at, kind in faults or []:
        link.schedule(at, _fault(sim, kind))
    abort = run_experiment(link, experiment, one.brake)
    return abort, link.frames_sent + link.frames_received


def finish(
    robot: Robot, request: Request, experiment: WinchExperiment, abort: Abort | None, frames: int
) -> Run:
    """Fit the record unless the experiment aborted."""
    record = experiment.record
    start = record.excitation_start
    seconds = 0.0 if math.isnan(start) else record.command_t[-1] - start
    model = None
    if abort is None:
        model = fit(setup_for(robot, request, record), record.arrays())
    latencies = record.latencies()
    host = float(np.percentile(latencies, LATENCY_PERCENTILE)) if len(latencies) else 0.0
    latency = host + 2.0 * record.transit  # the sample's way in, the command's way out
    return Run(record, abort, model, frames, seconds, latency)


def _fault(sim: VirtualRobot, kind: str) -> Callable[[], list[can.Message]]:
    """A device fault of the rig's one drive (sim_bus's names)."""
    if kind not in ("drive", "snap", "silent"):
        raise ValueError(f"unknown fault {kind!r} (drive, snap, silent)")

    def inject() -> list[can.Message]:
        if kind == "drive":
            return sim.drive_fault(0)
        if kind == "snap":
            sim.snap_cable(0)
        else:
            sim.silence(0)
        return []

    return inject
