"""Homing and geometric self-calibration of reference8 on a simulated robot that is not
the robot file, in lock-step (simulated time: the same
controller, homing and solver as the daemon, without the CAN bus and zenoh).

Truth: every anchor moved 20 mm in a random direction from the file, every drive's
encoder zero random within one drum turn, the cables' EA 0.6 x the file's.  Home at the
home pose, pick poses (greedy D-optimal from candidates in the workspace), fly them with
the file's model, identify (tuning.calibration), then fly the standard trajectories with
the corrected robot file and offsets and with the true ones.  Errors are in the
calibration's gauge (the world frame as the file's anchor frame, least squares):

    anchor_error_max_mm     corrected anchors against the true ones in that frame
    before_anchor_error_max_mm  the file's anchors against the true ones
    offset_error_max_mm     offsets (length at motor zero) against the truth
    stiffness_error_rel     |EA found / true EA - 1|
    tracking_ratio          the largest over the standard set of RMS error with the
                            corrected file / RMS with the true file (true platform in
                            each file's frame); tracking_extra_mm the largest difference;
                            runs: each trajectory's RMS with the true file, the corrected
                            one, and before calibration (the file, homed), and any fault
    calibrate_seconds       wall time of the lock-step flight plus the solve

Pretension (item 3), the same truth with the platform resting on a docking fixture at
home and every cable 2-10 cm slack (random), brought up in lock-step (tuning.pretension:
cdpr.pretension, homing, the loop closed and held for 1 s):

    pretension_motion_mm    the platform's largest true displacement from where it rested
    pretension_peak_force_n the largest true cable tension (force_max is 600 N)
    pretension_taut_seconds simulated time until the last cable was taut
    pretension_loop_close_step_n  the largest change of a force command at the loop close

    python bench/calibration.py [--json] [--poses N] [--seed S] [--pretension-only]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
from timing import REFERENCE8

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from sim_bus.plant.config import PlantConfig
from sim_bus.plant.fixture import FixtureConfig
from tuning.calibration import candidate_poses, corrected_robot, identify, select_poses
from tuning.calibration_flight import best_fit, fly_poses, home, model_frame, track
from tuning.pretension import run_pretension
from tuning.scenarios import STANDARD_SET

ANCHOR_MOVE = 0.02  # m
EA_FACTOR = 0.6
SLACK = (0.02, 0.10)  # m, the range each cable's slack is drawn from


def truth(robot: Robot, rng: np.random.Generator) -> PlantConfig:
    n = robot.n_cables
    directions = rng.normal(size=(n, 3))
    moves = ANCHOR_MOVE * directions / np.linalg.norm(directions, axis=1)[:, None]
    turn = 2.0 * math.pi * robot.actuators[0].drum_radius
    stiffness = robot.actuators[0].cable_stiffness * EA_FACTOR
    return PlantConfig.model_validate(
        {
            "cable": {"stiffness": stiffness},
            "encoder": {"counts_per_metre": 1.0e5, "noise_std": 0.0},
            "mismatch": {
                "anchor_offsets": moves.tolist(),
                "encoder_offsets": rng.uniform(-turn / 2, turn / 2, n).tolist(),
            },
        }
    )


def pretension(robot: Robot, config: PlantConfig, seed: int) -> dict[str, float]:
    """The pretension keys: `config`'s truth on a fixture at home, cables slack."""
    slack = np.random.default_rng([seed, 3]).uniform(*SLACK, robot.n_cables)
    on_fixture = config.model_copy(update={"fixture": FixtureConfig(slack_m=slack.tolist())})
    run = run_pretension(robot, on_fixture, ControllerSpec())
    if run.fault:
        raise SystemExit(f"error: pretension aborted: {run.fault}")
    return {
        "pretension_motion_mm": run.motion_mm,
        "pretension_peak_force_n": run.peak_force_n,
        "pretension_taut_seconds": run.taut_seconds,
        "pretension_loop_close_step_n": run.loop_close_step_n,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="one JSON object")
    parser.add_argument("--poses", type=int, default=60, help="calibration poses (default 60)")
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument(
        "--pretension-only", action="store_true", help="only the pretension keys (seconds)"
    )
    args = parser.parse_args(argv)
    say = (lambda text: print(text, file=sys.stderr)) if args.json else print
    robot = Robot.from_yaml(REFERENCE8)
    spec = ControllerSpec()
    rng = np.random.default_rng(args.seed)
    config = truth(robot, rng)
    if args.pretension_only:
        return report(pretension(robot, config, args.seed), args.json)
    from sim_bus.plant import Plant

    true_robot = Plant(robot, config).robot
    n = robot.n_cables
    true_offsets = -np.array(config.mismatch.encoder_offsets_for(n))

    started = time.perf_counter()
    homed = home(robot, config, robot.home, np.zeros(n))
    say(f"homed: offsets off the truth by up to {np.abs(homed - true_offsets).max() * 1e3:.2f} mm")
    # two rounds: the file's model is 20 mm off, so the first flies half as far out
    # (forward kinematics stays within max_residual), the second flies the corrected model
    model, offsets = robot, homed
    for round_, (reach, count) in enumerate(((0.5, args.poses // 2), (1.0, args.poses))):
        candidates = candidate_poses(
            model, 400, rng, reach=(0.6 * reach, 0.6 * reach, 0.45 * reach)
        )
        poses = select_poses(model, count, candidates)
        say(f"round {round_ + 1}: {len(poses)} poses")
        samples, fault = fly_poses(robot, model, spec, config, offsets, poses, robot.home, say)
        if fault:
            print(f"error: the calibration flight stopped: {fault}", file=sys.stderr)
            return 1
        calibration = identify(model, offsets, samples, progress=say)
        model = Robot.from_dict(corrected_robot(model, calibration), source="calibrated")
        offsets = calibration.offsets
    seconds = time.perf_counter() - started
    corrected = model

    file_ea = robot.actuators[0].cable_stiffness
    found_ea = corrected.actuators[0].cable_stiffness
    R, t = best_fit(np.asarray(true_robot.geometry.anchors), np.asarray(robot.geometry.anchors))
    true_in_gauge = np.asarray(true_robot.geometry.anchors) @ R.T + t
    anchor_error = np.linalg.norm(calibration.anchors - true_in_gauge, axis=1).max()
    before = np.linalg.norm(
        np.asarray(robot.geometry.anchors) - np.asarray(true_robot.geometry.anchors), axis=1
    ).max()
    runs = {}
    for name, make in STANDARD_SET.items():
        trajectory = make(robot)
        reference = track(robot, true_robot, spec, config, true_offsets, trajectory)
        calibrated = track(
            robot, corrected, spec, config, calibration.offsets, trajectory,
            model_frame(true_robot, corrected),
        )  # fmt: skip
        before_run = track(robot, robot, spec, config, homed, trajectory)
        runs[name] = {"true_rms_mm": reference[0], "calibrated_rms_mm": calibrated[0],
                      "before_rms_mm": before_run[0], "true_fault": reference[2],
                      "calibrated_fault": calibrated[2], "before_fault": before_run[2]}  # fmt: skip
        say(f"{name}: RMS {calibrated[0]:.4f} mm calibrated, {reference[0]:.4f} mm true file")
    ratio = max(r["calibrated_rms_mm"] / r["true_rms_mm"] for r in runs.values())
    extra = max(r["calibrated_rms_mm"] - r["true_rms_mm"] for r in runs.values())
    result = {
        "anchor_error_max_mm": float(anchor_error * 1e3),
        "offset_error_max_mm": float(np.abs(calibration.offsets - true_offsets).max() * 1e3),
        "stiffness_error_rel": abs(found_ea / (file_ea * EA_FACTOR) - 1.0),
        "tracking_ratio": ratio,
        "tracking_extra_mm": extra,
        "before_anchor_error_max_mm": float(before * 1e3),
        "calibrate_seconds": seconds,
        **pretension(robot, config, args.seed),
        "note": "lock-step flight in simulated time",
        "poses": len(samples),
        "residual_rms_mm": calibration.residual_rms * 1e3,
        "condition": calibration.condition,
        "unidentifiable": calibration.unidentifiable,
        "homing_offset_error_max_mm": float(np.abs(homed - true_offsets).max() * 1e3),
        "runs": runs,
    }
    return report(result, args.json)


def report(result: dict, as_json: bool) -> int:
    if as_json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
