"""Geometric self-calibration: tuning.calibration on lengths and forces
computed from a true robot that is not the robot file (anchors 20 mm off, attachments
2 mm off, drum radii and EA wrong, encoders counting from an unknown zero)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr import Pose, Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import static_tensions, tension_solver
from daemon.cli import main
from daemon.cli.calibrate_cmd import CalibrationError, _solve
from sim_bus.plant.config import MismatchConfig, PlantConfig
from tuning.calibration import (
    AnchorDistance,
    Calibration,
    Sample,
    candidate_poses,
    corrected_robot,
    identify,
    rest_samples,
    rigid_complement,
    scale_cost,
    scaled,
    select_poses,
    survey,
)
from tuning.calibration_flight import best_fit, fly_poses, home, model_frame

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "reference8.yaml"
EA_FACTOR = 0.6
RADIUS_SCALE = [1.002, 0.999, 1.0, 0.998, 1.001, 1.0, 0.9995, 1.0005]  # mean 1: the gauge


def make_truth(
    rng: np.random.Generator, radius_scale: list[float] = RADIUS_SCALE
) -> tuple[Robot, Robot, np.ndarray]:
    """(file, truth, true offsets: drum length at motor position zero); the true drum
    radii `radius_scale` x the file's."""
    robot = Robot.from_yaml(ROBOT)
    moves = rng.normal(size=(8, 3))
    moves = 0.02 * moves / np.linalg.norm(moves, axis=1)[:, None]
    mismatch = MismatchConfig(
        anchor_offsets=moves.tolist(),
        attachment_offsets=rng.uniform(-0.002, 0.002, (8, 3)).tolist(),
        drum_radius_scale=radius_scale,
    )
    return robot, mismatch.apply(robot, rng), rng.uniform(-0.15, 0.15, 8)


def measure(robot: Robot, true: Robot, zero: np.ndarray, poses: list, used: np.ndarray) -> list:
    """The drives' readings (with offsets `used`, the file's drum radii) and forces at
    rest at each true pose, the cables carrying the true robot's static tensions."""
    solver = tension_solver(true, ControllerSpec())
    scale = drum_scale(robot, true)
    stiffness = robot.actuators[0].cable_stiffness * EA_FACTOR
    samples = []
    for pose in poses:
        tensions = static_tensions(true, solver, pose)
        drum = true.cable_lengths(pose) / (1.0 + tensions / stiffness)
        samples.append(Sample(used + (drum - zero) / scale, -tensions))
    return samples


def drum_scale(robot: Robot, true: Robot) -> np.ndarray:
    """Each true drum radius / the file's."""
    return np.array(
        [
            t.drum_radius / f.drum_radius
            for t, f in zip(true.actuators, robot.actuators, strict=True)
        ]
    )


def in_anchor_gauge(robot: Robot, true: Robot) -> np.ndarray:
    """The true anchors in the calibration's gauge: their best rigid fit onto the file's."""
    R, t = best_fit(np.asarray(true.geometry.anchors), np.asarray(robot.geometry.anchors))
    return np.asarray(true.geometry.anchors) @ R.T + t


def goto_errors(
    robot: Robot, true: Robot, zero: np.ndarray, calibration: Calibration, reach: float
) -> np.ndarray:
    """Where gotos `reach` m from home along +-x, +-y, +-z land at rest with the corrected
    robot file and offsets, m from their targets (the true platform in the calibration's
    frame): the controller holds the lengths the corrected model has at the target under
    its static tensions, read through the true drums (`measure`'s encoders)."""
    model = Robot.from_dict(corrected_robot(robot, calibration))
    frame = model_frame(true, model)
    solver = tension_solver(model, ControllerSpec())
    compliance = 1.0 / (robot.actuators[0].cable_stiffness * EA_FACTOR)
    errors = []
    for step in np.vstack([np.eye(3), -np.eye(3)]) * reach:
        target = Pose(robot.home.position + step)
        tensions = static_tensions(model, solver, target)
        read = model.cable_lengths(target) / (1.0 + model.compliance * tensions)
        counts = (read - calibration.offsets) / calibration.drum_radius_scale  # file radii
        drums = zero + counts * drum_scale(robot, true)
        landed = true.forward_kinematics(drums * (1.0 + compliance * tensions), true.home).pose
        errors.append(np.linalg.norm(frame.to_model(landed).position - target.position))
    return np.array(errors)


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


def test_a_common_drum_error_is_invisible_without_a_scale_and_found_with_one() -> None:
    """Every drum 1 % larger than the file says (and the anchors 20 mm off, the drums'
    differences, EA 0.6 x): the lengths fit perfectly all the same, with the robot 1 %
    too small, as scale_cost predicts; one anchor distance measured (0.2 mm off, a
    laser meter's error) scales it back within 0.3 mm everywhere."""
    rng = np.random.default_rng(7)
    robot, true, zero = make_truth(rng, [1.01 * s for s in RADIUS_SCALE])
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    calibration = identify(robot, zero, measure(robot, true, zero, poses, zero))
    assert calibration.unidentifiable == [] and calibration.residual_rms < 1e-7
    truth = in_anchor_gauge(robot, true)
    blind_anchors = np.linalg.norm(calibration.anchors - truth, axis=1).max()
    blind_gotos = goto_errors(robot, true, zero, calibration, 0.3).max()
    anchors_cost, goto_cost = scale_cost(robot, 0.01, 0.3)
    assert blind_anchors == pytest.approx(anchors_cost, rel=0.05)  # 24.4 mm
    assert blind_gotos == pytest.approx(goto_cost, rel=0.05)  # 3.0 mm

    measured = float(np.linalg.norm(truth[0] - truth[5])) + 2e-4
    found = scaled(calibration, AnchorDistance(0, 5, measured))
    assert np.linalg.norm(found.anchors - truth, axis=1).max() < 3e-4
    assert goto_errors(robot, true, zero, found, 0.3).max() < 3e-4
    assert np.abs(found.offsets - zero).max() < 3e-4
    assert np.abs(found.drum_radius_scale - drum_scale(robot, true)).max() < 1e-4


def test_scale_cost_follows_the_robot() -> None:
    """reference8's anchors lie 2.46 m from their centroid, its home at that centroid:
    1 % costs 24.6 mm at the anchors and 3 mm 0.3 m from home; home moved 0.5 m
    from it, the goto's cost grows by 1 % of that."""
    robot = Robot.from_yaml(ROBOT)
    anchors, goto = scale_cost(robot, 0.01, 0.3)
    assert anchors == pytest.approx(0.01 * math.sqrt(1.5**2 + 1.5**2 + 1.25**2))
    assert goto == pytest.approx(0.003)
    spec = robot.spec.model_dump(exclude_none=True, mode="json")
    spec["home"]["position"] = [0.5, 0.0, 1.25]
    assert scale_cost(Robot.from_dict(spec), 0.01, 0.3)[1] == pytest.approx(0.008)


def test_a_survey_says_what_the_poses_identify_without_fitting() -> None:
    """6 poses give 12 equations beyond their own poses: rank 12 of 52, the other 40
    named; 2 poses (too few lengths to fit even the offsets first) rank 4; 30 poses
    identify all 52."""
    rng = np.random.default_rng(5)
    robot, true, zero = make_truth(rng)
    candidates = candidate_poses(robot, 300, rng)
    two = survey(robot, zero, measure(robot, true, zero, candidates[:2], zero))
    assert (two.poses, two.parameters, two.rank, len(two.unidentifiable)) == (2, 52, 4, 48)
    few = survey(robot, zero, measure(robot, true, zero, select_poses(robot, 6, candidates), zero))
    assert (few.poses, few.parameters, few.rank) == (6, 52, 12)
    assert len(few.unidentifiable) == 40 and "anchors of cables" in few.unidentifiable[0]
    enough = measure(robot, true, zero, select_poses(robot, 30, candidates), zero)
    full = survey(robot, zero, enough)
    assert (full.rank, full.unidentifiable) == (52, []) and 1.0 < full.condition < 1e6


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


def write_recording(path: Path, samples: list[Sample]) -> None:
    """A telemetry MCAP with the platform at rest at each sample's pose for 1 s, moving
    for 0.2 s in between."""
    from daemon.process.recording import CycleRecord, TelemetryRecorder

    with TelemetryRecorder(path) as recorder:
        t = 0.0
        for sample in samples:
            for k in range(120):
                twist = [0.0] * 6 if k < 100 else [0.2, 0, 0, 0, 0, 0]
                lengths, forces = sample.lengths, sample.forces
                record = CycleRecord(
                    t, (0, 0, 1), (1, 0, 0, 0), twist, lengths, -forces, forces, "hold"
                )
                recorder.record(record)
                t += 0.01


def write_config(tmp_path: Path) -> Path:
    """The reference8 CiA 402 config with a state directory under `tmp_path`."""
    config = yaml.safe_load((ROBOT.parents[1] / "reference8-cia402.yaml").read_text())
    config["robot"] = str(ROBOT)
    config["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_calibrate_from_a_recording_writes_a_new_robot_file_and_stores_the_offsets(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A telemetry MCAP with the platform at rest at 30 poses (1 s each, moving in
    between): `cdprd calibrate --from-recording --no-scale` finds the truth (its drums'
    mean radius the file's), writes it beside nothing it overwrites, stores the offsets
    as the daemon's state, and says what the scale it was not given costs."""
    rng = np.random.default_rng(6)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    used = np.zeros(8)  # drives.length_offset, nothing stored: the offsets in force
    recording = tmp_path / "run.mcap"
    write_recording(recording, measure(robot, true, zero, poses, used))
    path = write_config(tmp_path)
    output = tmp_path / "calibrated.yaml"
    code = main(["calibrate", "--config", str(path), "--from-recording", str(recording),
                 "--no-scale", "--output", str(output), "--json"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["poses"] == 30 and report["unidentifiable"] == []
    assert report["scale"]["reference"] is None
    assert report["scale"]["cost_anchors_mm"] == pytest.approx(24.62, abs=0.01)
    assert report["scale"]["cost_goto_mm"] == pytest.approx(3.0)
    corrected = Robot.from_yaml(output)
    truth = in_anchor_gauge(robot, true)
    assert np.abs(np.asarray(corrected.geometry.anchors) - truth).max() < 1e-5
    state = json.loads((tmp_path / "state" / "reference8.calibration.json").read_text())
    assert np.abs(np.array(state["offsets"]) - zero).max() < 1e-5
    assert state["method"] == f"calibrate (robot file {output})"


def test_calibrate_with_a_measured_distance_finds_drums_one_percent_off(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The drums 1.01 x the file's: `cdprd calibrate --scale-distance 0,5,METRES` (the
    anchors' true distance) writes a robot file whose anchors, drums and offsets are the
    truth's, and prints the scale it applied."""
    rng = np.random.default_rng(8)
    robot, true, zero = make_truth(rng, [1.01 * s for s in RADIUS_SCALE])
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    recording = tmp_path / "run.mcap"
    write_recording(recording, measure(robot, true, zero, poses, np.zeros(8)))
    truth = in_anchor_gauge(robot, true)
    measured = float(np.linalg.norm(truth[0] - truth[5]))
    output = tmp_path / "calibrated.yaml"
    code = main(["calibrate", "--config", str(write_config(tmp_path)), "--from-recording",
                 str(recording), "--scale-distance", f"0,5,{measured!r}",
                 "--output", str(output)])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"scale: anchors of cables 0 and 5 measured {measured:.4f} m, fitted " in out
    assert "the fit scaled x1.0" in out
    corrected = Robot.from_yaml(output)
    assert np.abs(np.asarray(corrected.geometry.anchors) - truth).max() < 3e-4
    radii = [a.drum_radius for a in corrected.actuators]
    assert np.allclose(radii, [a.drum_radius for a in true.actuators], rtol=1e-4)
    state = json.loads((tmp_path / "state" / "reference8.calibration.json").read_text())
    assert np.abs(np.array(state["offsets"]) - zero).max() < 3e-4


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ((), "usage error: a scale reference is needed: give --scale-distance A,B,METRES"),
        ((), "or --no-scale to calibrate without one"),
        ((), "on reference8 a 1% drum radius error leaves the anchors up to 24.6 mm off and a "
             "goto 0.3 m from home up to 3.0 mm off"),
        (("--scale-distance", "0,8,4.9"), "cable 8: reference8 has cables 0 to 7"),
        (("--scale-distance", "0,5,4924"), "the anchors of cables 0 and 5 are 4.9244 m apart in "
                                           "the robot file, 4924.0000 m measured"),
        (("--scale-distance", "0,5"), "argument --scale-distance: '0,5': expected A,B,METRES"),
        (("--scale-distance", "3,3,2"), "'3,3,2': expected two different cables"),
        (("--scale-distance", "0,5,nan"), "'0,5,nan': the distance must be more than 0 m"),
        (("--no-scale", "--scale-distance", "0,5,4.9"), "not allowed with argument"),
        (("--no-scale", "--resume", "--from-recording", "x.mcap"),
         "usage error: --resume continues a flown round, not --from-recording"),
    ],
)  # fmt: skip
def test_calibrate_refuses_without_a_usable_scale_naming_the_flag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: tuple[str, ...], words: str
) -> None:
    code = _exit_code(["calibrate", "--config", str(write_config(tmp_path)), *options])
    assert code == 2
    assert words in " ".join(capsys.readouterr().err.split())


def _exit_code(argv: list[str]) -> int:
    """main's exit code, argparse's usage errors (SystemExit) included."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_resume_needs_a_round_and_a_new_round_never_throws_a_kept_one_away(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without a kept round --resume is refused naming the file; with one, a new round
    is refused, pointing to --resume (before anything is flown or asked of a daemon)."""
    from daemon.cli.calibration_round import CalibrationRound, save_round
    from daemon.cli.run_cmd import load_checked
    from daemon.service.calibration_state import robot_identity

    path = write_config(tmp_path)
    kept = tmp_path / "state" / "reference8.calibration-round.json"
    assert _exit_code(["calibrate", "--config", str(path), "--no-scale", "--resume"]) == 1
    assert f"error: no round to resume: {kept} does not exist" in capsys.readouterr().err
    config = load_checked(str(path))
    robot = config.robot
    calibration_round = CalibrationRound(
        robot.name, robot_identity(robot, config.drives), [0.0] * 8, [robot.home] * 3
    )
    calibration_round.recorded[0] = Sample(robot.cable_lengths(robot.home), -50.0 * np.ones(8))
    save_round(kept, calibration_round)
    assert _exit_code(["calibrate", "--config", str(path), "--no-scale"]) == 1
    assert (
        f"error: {kept} holds a round interrupted with 1 of 3 poses recorded: continue it "
        "with --resume, or remove the file to fly a new round"
    ) in capsys.readouterr().err
    assert kept.exists()


def test_resume_solves_a_round_flown_to_its_end_and_removes_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A round whose every pose was recorded (the command stopped before its solve):
    --resume solves it, no daemon needed, writes the robot file, and removes the round."""
    from daemon.cli.calibration_round import CalibrationRound, save_round
    from daemon.cli.run_cmd import load_checked
    from daemon.service.calibration_state import robot_identity

    rng = np.random.default_rng(9)
    robot, true, zero = make_truth(rng)
    poses = select_poses(robot, 30, candidate_poses(robot, 300, rng))
    path = write_config(tmp_path)
    config = load_checked(str(path))
    offsets = list(rng.uniform(-0.01, 0.01, 8))
    calibration_round = CalibrationRound(
        robot.name, robot_identity(robot, config.drives), offsets, poses
    )
    for k, sample in enumerate(measure(robot, true, zero, poses, np.array(offsets))):
        calibration_round.recorded[k] = sample
    kept = tmp_path / "state" / "reference8.calibration-round.json"
    save_round(kept, calibration_round)
    output = tmp_path / "calibrated.yaml"
    code = main(["calibrate", "--config", str(path), "--no-scale", "--resume", "--output",
                 str(output), "--json"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and (report["poses"], report["planned"]) == (30, 30)
    truth = in_anchor_gauge(robot, true)
    assert np.abs(np.asarray(Robot.from_yaml(output).geometry.anchors) - truth).max() < 1e-5
    assert not kept.exists()


def _anchors_off_flight() -> tuple[Robot, PlantConfig, list[Pose], np.ndarray]:
    """reference8, its anchors 20 mm off in the simulated truth: the robot file, the
    truth, 3 poses, the homed offsets."""
    robot = Robot.from_yaml(ROBOT)
    rng = np.random.default_rng(16)
    moves = rng.normal(size=(8, 3))
    config = PlantConfig.model_validate(
        {
            "cable": {"stiffness": 6e4},
            "mismatch": {
                "anchor_offsets": (0.02 * moves / np.linalg.norm(moves, axis=1)[:, None]).tolist()
            },
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


@pytest.mark.slow  # over 4.5 s
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
