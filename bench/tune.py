"""Benchmark of `cdprd tune` on the simulator: a winch whose true m0, k0 and
force lag are 30 % off the robot file (m0 x1.3, k0 x0.7, lag 2.6 ms for 2 ms), free drum,
odrive reference8 config, 20 s PRBS through the drive's CAN frames in simulated time.

Prints m0_error_rel, k0_error_rel, lag_error_rel (noise-free), noisy_error_rel_max (10 um
encoder noise, 5 % force noise: the largest of the three), experiment_seconds, and
tracking_ratio: the largest over the standard trajectory set of RMS position error with
the identified actuator and the proposed gains over that with the hand-tuned defaults
(both on the true plant, the identified robot file, no gain scheduling).

    python bench/tune.py [--json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cdpr.control_spec import DEFAULT_PID, ControllerSpec
from cdpr.controller import ParallelController
from daemon.config import load_config
from sim_bus.plant.config import parse_plant_config
from tuning.gain_design import design, identified_robot
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking
from tuning.winch_tune import Request, identify_simulated
from tuning.workspace_analysis import analyse

CONFIG = Path(__file__).resolve().parent.parent / "config" / "reference8-odrive.yaml"
TRUE = {"m0": 1.9 * 1.3, "k0": 20.0 * 0.7, "lag": 2.6e-3}
PLANT = {"actuator": {"c": [TRUE["lag"]]}, "mismatch": {"m0_scale": 1.3, "k0_scale": 0.7}}


def errors(model: object) -> dict[str, float]:
    return {k: abs(getattr(model, k) / v - 1.0) for k, v in TRUE.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    config = load_config(CONFIG)
    robot, rate = config.robot, config.controller.rate_hz
    run = identify_simulated(robot, config.drives, parse_plant_config(PLANT), Request(), rate)
    noisy_plant = parse_plant_config(
        {**PLANT, "encoder": {"counts_per_metre": 1e5, "noise_std": 1e-5}, "force_noise": 0.05}
    )
    noisy = identify_simulated(robot, config.drives, noisy_plant, Request(seed=1), rate)
    model = run.model
    modal = analyse(robot, config.controller, points_per_axis=3).grid.mass_range
    gains = design(robot, model, modal, 0.0, rate)
    tuned = identified_robot(robot, model)
    true_plant = parse_plant_config(PLANT)
    ratios = {}
    for name, make in STANDARD_SET.items():
        trajectory = make(tuned)
        rms = [
            run_tracking(
                tuned, trajectory, ParallelController(tuned, ControllerSpec(pid=pid)), true_plant
            ).rms_mm
            for pid in (gains.gains, DEFAULT_PID)
        ]
        ratios[name] = rms[0] / rms[1]
    e = errors(model)
    out = {
        "m0_error_rel": round(e["m0"], 5),
        "k0_error_rel": round(e["k0"], 5),
        "lag_error_rel": round(e["lag"], 5),
        "noisy_error_rel_max": round(max(errors(noisy.model).values()), 5),
        "experiment_seconds": round(run.experiment_seconds, 3),
        "tracking_ratio": round(max(ratios.values()), 4),
        "tracking_ratios": {k: round(v, 4) for k, v in ratios.items()},
        "gains": gains.gains.model_dump(),
    }
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k}: {v}")


if __name__ == "__main__":
    main()
