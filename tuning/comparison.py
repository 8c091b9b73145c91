"""Closed-loop figures of the standard trajectory set: the paper's controller, the
joint-space baseline with the same gains, the paper's controller under model mismatch
and without its command lead.  bench/controller.py prints them (its `tracking` figures)
and the paper-claim tests check them (claim 3: baseline_ratio < 1), from this one
function.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cdpr import Robot
from cdpr.baseline import JointSpaceController
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from cdpr.trajectory import Trajectory
from sim_bus.plant.config import PlantConfig, parse_plant_config
from tuning.scenarios import STANDARD_SET, rotation_wobble
from tuning.tracking import pose_errors, run_tracking

MISMATCH = {
    "mismatch": {"mass_scale": 1.1, "m0_scale": 0.9},
    "encoder": {"counts_per_metre": 1e5, "noise_std": 5e-6},
    "seed": 7,
}


def standard_set_figures(robot: Robot, spec: ControllerSpec) -> dict[str, dict[str, Any]]:
    """Per trajectory of STANDARD_SET: the paper's controller's TrackingResult figures
    (rounded), "baseline" (the joint-space controller's), "baseline_ratio" (RMS position
    error, paper / baseline), "mismatch" (plant mass +10 %, m0 -10 %, 5 um noise),
    "no_lead" (commands evaluated for their measurement's instant: command_lead 0) and
    "lead_ratio" (RMS position error, spec's lead / none)."""
    out: dict[str, dict[str, Any]] = {}
    mismatch = parse_plant_config(MISMATCH)
    unled = spec.model_copy(update={"command_lead": 0.0})
    for name, make in STANDARD_SET.items():
        trajectory = make(robot)
        paper = run_tracking(robot, trajectory, ParallelController(robot, spec), PlantConfig())
        base = run_tracking(robot, trajectory, JointSpaceController(robot, spec), PlantConfig())
        off = run_tracking(robot, trajectory, ParallelController(robot, spec), mismatch)
        figures = _rounded(paper.figures())
        figures["baseline"] = _rounded(base.figures())
        figures["baseline_ratio"] = round(paper.rms_mm / base.rms_mm, 3)
        figures["mismatch"] = _rounded(off.figures())
        late = run_tracking(robot, trajectory, ParallelController(robot, unled), PlantConfig())
        figures["no_lead"] = _rounded(late.figures())
        figures["lead_ratio"] = round(paper.rms_mm / late.rms_mm, 3)
        out[name] = figures
    return out


# a payload of +10 % of the platform's mass, and +30 % with the centre of mass
# moved 5 cm (3 cm sideways, 4 cm down: the vertical part only tilts and sideways
# accelerations reveal)
PAYLOADS = {
    "payload10": {"mismatch": {"mass_scale": 1.1}},
    "payload30": {"mismatch": {"mass_scale": 1.3, "center_of_mass_offset": [0.03, 0.0, -0.04]}},
}
WARM_UP = 2.0  # s the robot holds the start pose with the payload before the flight
HOLD = 1.0  # s it holds the last pose after the flight


def payload_figures(robot: Robot, spec: ControllerSpec) -> dict[str, dict[str, Any]]:
    """Per trajectory of STANDARD_SET and payload of PAYLOADS: the paper's controller with
    the payload estimate on (spec's adaptation) holding the start pose for WARM_UP s, then
    flying the trajectory: the RMS position error over the flight (`rms_mm`) and over the
    HOLD s of holding after it (`hold_mm`), and the same with the estimate off
    (`adaptation_off`)."""
    spec_on = spec.model_copy(
        update={"adaptation": spec.adaptation.model_copy(update={"enabled": True})}
    )
    spec_off = spec.model_copy(
        update={"adaptation": spec.adaptation.model_copy(update={"enabled": False})}
    )
    out: dict[str, dict[str, Any]] = {}
    for name, make in STANDARD_SET.items():
        trajectory = make(robot)
        figures: dict[str, Any] = {}
        for label, plant in PAYLOADS.items():
            config = parse_plant_config(plant)
            on, off = (
                _payload_run(robot, trajectory, ParallelController(robot, s), config)
                for s in (spec_on, spec_off)
            )
            figures[label] = {**on, "adaptation_off": off}
        out[name] = figures
    return out


def _payload_run(
    robot: Robot,
    trajectory: Trajectory,
    controller: ParallelController,
    config: PlantConfig,
    latency: float = 0.0,
) -> dict[str, float | str]:
    result = run_tracking(
        robot, trajectory, controller, config, settle=HOLD, warm_up=WARM_UP, latency=latency
    )
    rec = result.recording
    flown = trajectory.shifted(WARM_UP)
    times = rec.t
    errors, _ = pose_errors(
        [flown.sample(t).pose for t in times.tolist()], [rec.pose(i) for i in range(len(times))]
    )
    flight = (times >= flown.start_time) & (times <= flown.end_time)
    hold = times > flown.end_time
    return {
        "rms_mm": round(float(np.sqrt(np.mean(errors[flight] ** 2))), 4),
        "hold_mm": round(float(np.sqrt(np.mean(errors[hold] ** 2))), 4),
        "fault": result.fault,
    }


def _rounded(figures: dict[str, Any]) -> dict[str, Any]:
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in figures.items()}


# the inertia estimate on reference8's elastic cables, the platform's inertia
# 1.5x the file's and 2 kg hung 5 cm aside and 10 cm down (the centre of mass 15 mm off)
INERTIA_PAYLOAD = {"mass": 2.0, "position": [0.05, 0.0, -0.1]}
INERTIA_PLANT = {"mismatch": {"inertia_scale": 1.5, "payload": INERTIA_PAYLOAD}}
LATENCY_STEP = 2.5e-4  # s: the plant step of a run with latency (a whole number of steps)


def inertia_figures(robot: Robot, spec: ControllerSpec, latency: float = 0.0) -> dict[str, Any]:
    """The payload estimate with the inertia (spec's adaptation, inertia on) on
    INERTIA_PLANT, holding the start pose for WARM_UP s and then turning about all three
    axes (tuning.scenarios.rotation_wobble): the error of the inertia's diagonal
    (`diagonal_error_pct`, per axis, % of the truth's), of its products (`products_error`,
    the largest, kg m^2) and of the mass (`mass_error_pct`), the RMS position error over
    the flight and the HOLD s after it (`rms_mm`, `hold_mm`), and those with the inertia
    left at the file's (`inertia_off`).  With a `latency` (s) the commands take effect
    that late on a plant stepping LATENCY_STEP s (its drives' rates still over a control
    period, as at the default 1 ms step), and the controller is told."""
    plant: dict[str, Any] = INERTIA_PLANT
    if latency:
        window = round(1.0 / (spec.rate_hz * LATENCY_STEP))
        plant = {**plant, "step": LATENCY_STEP, "encoder": {"velocity_window_steps": window}}
    config = parse_plant_config(plant)
    truth = config.mismatch.apply(robot, np.random.default_rng()).platform
    out: dict[str, Any] = {}
    for inertia in (True, False):
        adaptation = spec.adaptation.model_copy(update={"enabled": True, "inertia": inertia})
        controller = ParallelController(robot, spec.model_copy(update={"adaptation": adaptation}))
        controller.set_latency(latency)
        flight = _payload_run(robot, rotation_wobble(robot), controller, config, latency)
        if not inertia:
            out["inertia_off"] = flight
            continue
        estimate = controller.payload
        assert estimate is not None
        error = estimate.platform.inertia - truth.inertia
        out = {
            "diagonal_error_pct": np.round(
                100.0 * np.diag(error) / np.diag(truth.inertia), 2
            ).tolist(),
            "products_error": round(float(np.abs(error[np.triu_indices(3, 1)]).max()), 4),
            "mass_error_pct": round(100.0 * (estimate.mass / truth.mass - 1.0), 3),
            **flight,
        }
    return out
