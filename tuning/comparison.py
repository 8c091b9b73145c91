"""Closed-loop figures of the standard trajectory set: the paper's controller, the
joint-space baseline with the same gains, the paper's controller under model mismatch
and without its command lead.  bench/controller.py prints them (its `tracking` figures)
and the paper-claim tests check them (claim 3: baseline_ratio < 1), from this one
function.
"""

from __future__ import annotations

from typing import Any

from cdpr import Robot
from cdpr.baseline import JointSpaceController
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from sim_bus.plant.config import PlantConfig, parse_plant_config
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking

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


def _rounded(figures: dict[str, Any]) -> dict[str, Any]:
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in figures.items()}
