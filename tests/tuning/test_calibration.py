"""Geometric self-calibration: tuning.calibration on lengths and forces
computed from a true robot that is not the robot file (anchors 20 mm off, attachments
2 mm off, drum radii and EA wrong, encoders counting from an unknown zero)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cdpr import Pose, Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import static_tensions, tension_solver
from daemon.cli.calibrate_cmd import CalibrationError, _solve
from sim_bus.plant.config import MismatchConfig, PlantConfig
from tuning.calibration import (
    Sample,
    candidate_poses,
    corrected_robot,
    identify,
    rest_samples,
    rigid_complement,
    select_poses,
)
from tuning.calibration_flight import best_fit, fly_poses, home

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "reference8.yaml"
EA_FACTOR = 0.6
RADIUS_SCALE = [1.002, 0.999, 1.0, 0.998, 1.001, 1.0, 0.9995, 1.0005]  # mean 1: the gauge


def make_truth(rng: np.random.Generator) -> tuple[Robot, Robot, np.ndarray]:
    """(file, truth, true offsets: drum length at motor position zero)."""
    robot = Robot.from_yaml(ROBOT)
    moves = rng.normal(size=(8, 3))
    moves = 0.02 * moves / np.linalg.norm(moves, axis=1)[:, None]
    mismatch = MismatchConfig(
        anchor_offsets=moves.tolist(),
        attachment_offsets=rng.uniform(-0.002, 0.002, (8, 3)).tolist(),
        drum_radius_scale=RADIUS_SCALE,
    )
    return robot, mismatch.apply(robot, rng), rng.uniform(-0.15, 0.15, 8)


def measure(robot: Robot, true: Robot, zero: np.ndarray, poses: list, used: np.ndarray) -> list:
    """The drives' readings (with offsets `used`, the file's drum radii) and forces at
    rest at each true pose, the cables carrying the true robot's static tensions."""
    solver = tension_solver(true, ControllerSpec())
    scale = np.array(RADIUS_SCALE)
    stiffness = robot.actuators[0].cable_stiffness * EA_FACTOR
    samples = []
    for pose in poses:
        tensions = static_tensions(true, solver, pose)
        drum = true.cable_lengths(pose) / (1.0 + tensions / stiffness)
        samples.append(Sample(used + (drum - zero) / scale, -tensions))
    return samples


def test_calibration_finds_the_true_robot_in_the_anchors_frame() -> None:
    rng = np.random.default_rng(3)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    used = zero + rng.uniform(-0.02, 0.02, 8)  # homed with the wrong anchors
    calibration = identify(robot, used, measure(robot, true, zero, poses, used))

    assert calibration.unidentifiable == []
    assert calibration.residual_rms < 1e-7
    # the true anchors in the calibration's gauge: their best rigid fit onto the file's
    R, t = best_fit(np.asarray(true.geometry.anchors), np.asarray(robot.geometry.anchors))
    in_gauge = np.asarray(true.geometry.anchors) @ R.T + t
    assert np.abs(calibration.anchors - in_gauge).max() < 1e-5
    assert np.abs(calibration.offsets - zero).max() < 1e-5
    assert np.abs(calibration.drum_radius_scale - RADIUS_SCALE).max() < 1e-6
    assert calibration.stiffness_scale == pytest.approx(EA_FACTOR, rel=1e-4)
    # gravity in that frame: the world's -z turned by R
    assert np.allclose(calibration.gravity, R @ np.array([0.0, 0.0, -9.81]), atol=1e-4)
    corrected = Robot.from_dict(corrected_robot(robot, calibration))
    assert corrected.actuators[0].cable_stiffness == pytest.approx(6e4, rel=1e-4)


def test_the_gauge_is_fixed_as_documented() -> None:
    """The anchor corrections have no rigid-motion component (the world frame is the
    file's anchor frame in the least-squares sense), the attachment corrections neither
    (the platform frame), and the drum radius scales keep a mean of 1 (the scale)."""
    rng = np.random.default_rng(4)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 24, candidate_poses(robot, 200, rng))
    calibration = identify(robot, zero, measure(robot, true, zero, poses, zero))
    for found, file in (
        (calibration.anchors, robot.geometry.anchors),
        (calibration.attachments, robot.geometry.attachments),
    ):
        file = np.asarray(file)
        change = (found - file).reshape(-1)
        basis = rigid_complement(file)
        assert np.linalg.norm(change - basis @ (basis.T @ change)) < 1e-9
    assert np.mean(calibration.drum_radius_scale) == pytest.approx(1.0, abs=1e-12)


def test_too_few_poses_name_the_parameters_that_are_not_identifiable() -> None:
    rng = np.random.default_rng(5)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 6, candidate_poses(robot, 100, rng))
    samples = measure(robot, true, zero, poses, zero)
    calibration = identify(robot, zero, samples)
    # 6 poses x 2 redundant lengths = 12 equations for 52 parameters: 40 combinations
    assert len(calibration.unidentifiable) == 52 - 12
    text = " ".join(calibration.unidentifiable)
    assert "anchors of cables" in text and "attachments of cables" in text
    with pytest.raises(CalibrationError, match=r"6 poses do not identify every parameter \(40"):
        _solve(robot, zero, samples)


def test_rest_samples_average_the_end_of_each_stretch_at_rest() -> None:
    t = np.arange(0.0, 3.0, 0.01)
    moving = (t > 1.0) & (t < 1.5)
    twists = np.zeros((len(t), 6))
    twists[moving, 0] = 0.1
    lengths = np.where(t[:, None] < 1.25, 2.0, 2.5) * np.ones((len(t), 8))
    forces = -100.0 * np.ones((len(t), 8))
    samples = rest_samples(t, lengths, forces, twists)
    assert [s.lengths[0] for s in samples] == [2.0, 2.5]
    assert all(math.isclose(s.forces[3], -100.0) for s in samples)


def test_calibrate_from_a_recording_writes_a_new_robot_file_and_stores_the_offsets(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A telemetry MCAP with the platform at rest at 30 poses (1 s each, moving in
    between): `cdprd calibrate --from-recording` finds the truth, writes it beside
    nothing it overwrites, and stores the offsets as the daemon's state."""
    import json

    import yaml

    from daemon.cli import main
    from daemon.process.recording import CycleRecord, TelemetryRecorder

    rng = np.random.default_rng(6)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    used = np.zeros(8)  # drives.length_offset, nothing stored: the offsets in force
    samples = measure(robot, true, zero, poses, used)
    recording = tmp_path / "run.mcap"
    with TelemetryRecorder(recording) as recorder:
        t = 0.0
        for sample in samples:
            for k in range(120):  # 1 s at rest, 0.2 s on the way to the next pose
                twist = [0.0] * 6 if k < 100 else [0.2, 0, 0, 0, 0, 0]
                lengths, forces = sample.lengths, sample.forces
                record = CycleRecord(
                    t, (0, 0, 1), (1, 0, 0, 0), twist, lengths, -forces, forces, "hold"
                )
                recorder.record(record)
                t += 0.01
    config = yaml.safe_load((ROBOT.parents[1] / "reference8-cia402.yaml").read_text())
    config["robot"] = str(ROBOT)
    config["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(config))
    output = tmp_path / "calibrated.yaml"
    code = main(["calibrate", "--config", str(path), "--from-recording", str(recording),
                 "--output", str(output), "--json"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["poses"] == 30 and report["unidentifiable"] == []
    corrected = Robot.from_yaml(output)
    R, t = best_fit(np.asarray(true.geometry.anchors), np.asarray(robot.geometry.anchors))
    in_gauge = np.asarray(true.geometry.anchors) @ R.T + t
    assert np.abs(np.asarray(corrected.geometry.anchors) - in_gauge).max() < 1e-5
    state = json.loads((tmp_path / "state" / "reference8.calibration.json").read_text())
    assert np.abs(np.array(state["offsets"]) - zero).max() < 1e-5
    assert state["method"] == f"calibrate (robot file {output})"


def _anchors_off_flight() -> tuple[Robot, PlantConfig, list[Pose], np.ndarray]:
    """reference8, its anchors 20 mm off in the simulated truth: the robot file, the
    truth, 3 poses, the homed offsets."""
    robot = Robot.from_yaml(ROBOT)
    rng = np.random.default_rng(16)
    moves = rng.normal(size=(8, 3))
    config = PlantConfig.model_validate(
        {
            "cable": {"stiffness": 6e4},
            "mismatch": {"anchor_offsets": (0.02 * moves / np.linalg.norm(moves, axis=1)[:, None])
                         .tolist()},
        }
    )
    poses = select_poses(robot, 3, candidate_poses(robot, 40, rng, reach=(0.3, 0.3, 0.22)))
    return robot, config, poses, home(robot, config, robot.home, np.zeros(8))


def test_the_calibration_flight_flies_with_the_files_platform() -> None:
    """Anchors 20 mm off look like a payload to the online estimate (cdpr.payload): free,
    it ran to adaptation.com_max within a few poses and braked the flight; frozen at the
    file's platform (as `cdprd calibrate` does) the flight records every pose."""
    robot, config, poses, offsets = _anchors_off_flight()
    samples, fault = fly_poses(robot, robot, ControllerSpec(), config, offsets, poses, robot.home)
    assert fault == "" and len(samples) == 3


def test_the_calibration_flight_holds_the_wrench_observer_out_of_the_loop() -> None:
    """The external wrench observer held (as `cdprd calibrate` does), the flight records
    exactly what it does without one: the geometry error left to the integral action,
    for the fit to see (taking in cycles, the observer compensated it: anchors twice as
    far off in bench/calibration.py)."""
    robot, config, poses, offsets = _anchors_off_flight()
    spec = ControllerSpec()
    without = spec.model_copy(
        update={"disturbance_observer": spec.disturbance_observer.model_copy(
            update={"enabled": False})}
    )  # fmt: skip
    held, fault = fly_poses(robot, robot, spec, config, offsets, poses, robot.home)
    off, fault_off = fly_poses(robot, robot, without, config, offsets, poses, robot.home)
    assert fault == fault_off == "" and len(held) == len(off) == 3
    for a, b in zip(held, off, strict=True):
        assert np.array_equal(a.lengths, b.lengths) and np.array_equal(a.forces, b.forces)
