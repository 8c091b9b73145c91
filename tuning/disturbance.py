"""Disturbance rejection: the holding robot pushed by an external wrench step (a person
leaning on the platform, a tool touching something), in simulated time.

The plant (sim_bus.plant, elastic cables, drive lag, encoder quantisation as in the
standard set) holds the home pose under the paper's controller; at `start` a constant
wrench begins to act on the platform and stays.  Reported: the largest position error
of the TRUE platform from home, the 2 % settling time (from the step until the error
stays within 2 % of that peak, or 0.1 mm, whichever is larger: the integral action
brings it back), the error left at the end, and whether the controller faulted.

A push that ends (`release_response`: a person letting go): the push's peak, the
rebound (how far the platform then goes the other way, along the direction of the
push's peak: the external wrench observer's estimate outliving the push moves it
there, cdpr.wrench_observer), and the settling time from the release.
"""

from __future__ import annotations

import math
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


class ReleaseFigures(NamedTuple):
    peak_mm: float  # while the push acts
    rebound_mm: float  # after it ends, against the direction of the peak (0: none)
    settle_s: float  # from the release, as DisturbanceFigures.settle_s; inf: never
    fault: str


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
    times, offsets, fault = _run(robot, spec, wrench, start, math.inf, duration, rate_hz, config)
    errors = np.linalg.norm(offsets, axis=1)
    after = times >= start
    worst = int(np.argmax(np.where(after, errors, -1.0)))
    peak = float(errors[worst])
    settle = _settle(times, errors, start, max(SETTLE_BAND * peak, SETTLE_FLOOR))
    offset = tuple(float(v) * 1e3 for v in offsets[worst])
    return DisturbanceFigures(peak * 1e3, offset, settle, float(errors[-1]) * 1e3, fault)


def release_response(
    robot: Robot,
    spec: ControllerSpec,
    wrench: tuple[float, ...] = (50.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    start: float = 0.5,
    end: float = 1.0,
    duration: float = 6.0,
    rate_hz: float = 500.0,
    config: PlantConfig | None = None,
) -> ReleaseFigures:
    """The holding robot pushed by `wrench` from `start` to `end` (s), then let go."""
    times, offsets, fault = _run(robot, spec, wrench, start, end, duration, rate_hz, config)
    errors = np.linalg.norm(offsets, axis=1)
    pushed = (times >= start) & (times < end)
    worst = int(np.argmax(np.where(pushed, errors, -1.0)))
    peak = float(errors[worst])
    direction = offsets[worst] / peak if peak > 0.0 else np.zeros(3)
    back = -offsets[times >= end].dot(direction)
    rebound = max(0.0, float(back.max()))
    settle = _settle(times, errors, end, max(SETTLE_BAND * peak, SETTLE_FLOOR))
    return ReleaseFigures(peak * 1e3, rebound * 1e3, settle, fault)


def _settle(times: np.ndarray, errors: np.ndarray, since: float, band: float) -> float:
    """Seconds from `since` until the error stays within `band` (inf: not within the run)."""
    outside = np.flatnonzero((times >= since) & (errors > band))
    if len(outside) == 0:
        return 0.0
    if outside[-1] == len(times) - 1:
        return math.inf
    return float(times[outside[-1] + 1] - since)


def _run(
    robot: Robot,
    spec: ControllerSpec,
    wrench: tuple[float, ...],
    start: float,
    end: float,
    duration: float,
    rate_hz: float,
    config: PlantConfig | None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Hold home under `wrench` acting for start <= t < end, lock-step: the sample times,
    the TRUE platform's offsets from home (m, one row each), the controller's first fault."""
    config = (config or PlantConfig()).model_copy(
        update={"disturbance": DisturbanceConfig(wrench=wrench, start=start, end=end)}
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
    offsets = rec.series["position"] - home.position
    return rec.t, offsets, faults[0] if faults else ""
