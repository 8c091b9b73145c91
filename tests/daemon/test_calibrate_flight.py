"""A successful calibration flown through the daemon as separate processes:
the simulator (`python -m sim_bus`, the true robot from sim.robot, a file
of its own) keeps running while the daemon (`cdprd run`) is homed, calibrates, and is
restarted on each corrected robot file, as a user would; then the true platform (the
simulator's --truth-log) is where the calibrated daemon flies it."""

from __future__ import annotations

import json
import math
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr import Pose, Robot
from tests import processes
from tests.conftest import ROBOTS
from tests.loopback import free_port
from tests.processes import cdprd
from tuning.calibration_flight import best_fit, model_frame

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)

EA_FACTOR = 0.6  # the true cables' EA / the file's


def true_robot(tmp_path: Path, move: float, rng: np.random.Generator) -> Path:
    """reference8 with every anchor `move` m off the file in a random direction and the
    cables' EA EA_FACTOR x the file's, as a robot file (the simulator's sim.robot)."""
    data = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    for cable in data["cables"]:
        direction = rng.normal(size=3)
        moved = np.array(cable["anchor"]) + move * direction / np.linalg.norm(direction)
        cable["anchor"] = moved.tolist()
    data["actuator"]["cable_stiffness"] *= EA_FACTOR
    path = tmp_path / "true.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


class Bench:
    """The daemon processes (`cdprd run --sim`, the truth from sim.robot) a user restarts
    on each corrected file, and at the end the simulator as a process of its own."""

    def __init__(self, tmp_path: Path, move: float, seed: int, drum_scale: float = 1.0) -> None:
        rng = np.random.default_rng(seed)
        self.tmp = tmp_path
        self.zenoh = free_port()
        self.true_file = true_robot(tmp_path, move, rng)
        self.true = Robot.from_yaml(self.true_file)
        self.file = Robot.from_yaml(ROBOTS / "reference8.yaml")
        turn = 2.0 * math.pi * self.file.actuators[0].drum_radius
        self.encoder_offsets = rng.uniform(-turn / 2, turn / 2, 8)
        self.sim_file, self.data = processes.simulator_configs(tmp_path, self.zenoh)
        self.data["sim"]["robot"] = str(self.true_file)
        self.data["sim"]["plant"] = {
            "cable": {"stiffness": self.true.actuators[0].cable_stiffness},
            "encoder": {"counts_per_metre": 1.0e5, "noise_std": 0.0},
            "mismatch": {
                "encoder_offsets": self.encoder_offsets.tolist(),
                "drum_radius_scale": drum_scale,
            },
        }
        self.data["zenoh"]["state_rate_hz"] = 250.0  # the states calibrate averages
        # three processes and TCP relays beside other work at the end: patient drives
        self.data["drives"]["watchdog_timeout"] = 0.5
        self.data["state_dir"] = str(tmp_path / "state")
        self.data["realtime"] = {"lock_memory": False}
        self.sim_file.write_text(yaml.safe_dump(self.data))
        self.sim: subprocess.Popen | None = None
        self.daemon: subprocess.Popen | None = None
        self.connection = ("--connect", f"tcp/127.0.0.1:{self.zenoh}")

    def start(self, robot_file: Path) -> None:
        """`cdprd run --sim` on `robot_file` (the simulated truth: sim.robot), once it
        answers (idle, or braked on lengths that fit no pose before homing)."""
        self.stop()
        data = {**self.data, "robot": str(robot_file)}
        self.config = self.tmp / "cdprd.yaml"
        self.config.write_text(yaml.safe_dump(data))
        self._run(self.config, "--sim", robot_file=robot_file)

    def start_on_simulator(self, robot_file: Path) -> None:
        """The simulator as its own process (its true pose in --truth-log) and a daemon
        on `robot_file` driving it over socketcand."""
        self.stop()
        self.truth_log = self.tmp / "truth.jsonl"
        self.sim, port, channel = processes.serve_simulator(
            self.sim_file, "--truth-log", str(self.truth_log)
        )
        data = {**self.data, "robot": str(robot_file)}
        self.config = processes.daemon_config(self.tmp, data, port, channel, stale_cycles=200)
        self._run(self.config, robot_file=robot_file)

    def _run(self, config: Path, *options: str, robot_file: Path) -> None:
        log = self.tmp / f"daemon-{robot_file.stem}.log"
        self.daemon = processes.start_daemon(config, *options, log=log)
        self.client = processes.connect(self.zenoh, self.daemon)
        end = time.monotonic() + 20.0
        while (status := self.client.status())["state"] not in ("idle", "braked"):
            assert time.monotonic() < end, status
            time.sleep(0.1)

    def enable(self) -> None:
        if self.client.status()["state"] == "braked":
            assert cdprd("reset", *self.connection).returncode == 0
        run = cdprd("enable", *self.connection)
        assert run.returncode == 0, run.stdout + run.stderr
        processes.wait_status(self.client, "hold", 10.0)

    def scale_distance(self) -> tuple[str, str]:
        """`--scale-distance` as a user measures it: the true anchors of cables 0 and 5."""
        anchors = np.asarray(self.true.geometry.anchors)
        return "--scale-distance", f"0,5,{float(np.linalg.norm(anchors[0] - anchors[5]))!r}"

    def calibrate(self, output: Path, *options: str) -> dict:
        run = cdprd(
            "calibrate", "--config", str(self.config), "--json",
            "--output", str(output), *options, *self.connection, timeout=900.0,
        )  # fmt: skip
        assert run.returncode == 0, run.stderr[-3000:]
        return json.loads(run.stdout)

    def stop(self) -> None:
        if self.daemon is not None:
            self.client.close()
            processes.finish(self.daemon)
            self.daemon = None
        if self.sim is not None:
            processes.finish(self.sim)
            self.sim = None

    def true_offsets(self) -> np.ndarray:
        """The length at each drive's motor zero (daemon's drives.length_offset is 0)."""
        return -self.encoder_offsets

    def anchor_errors(self, robot: Robot) -> np.ndarray:
        """|anchor - truth| per cable in the calibration's gauge (the file's anchor frame)."""
        true = np.asarray(self.true.geometry.anchors)
        R, t = best_fit(true, np.asarray(self.file.geometry.anchors))
        return np.linalg.norm(np.asarray(robot.geometry.anchors) - (true @ R.T + t), axis=1)

    def true_pose(self) -> Pose:
        record = processes.truth(self.truth_log)[-1]
        q = record["quaternion"]
        return Pose(record["position"], (q["w"], q["x"], q["y"], q["z"]))


def fly_calibration(
    tmp_path: Path,
    move: float,
    rounds: list[tuple[str, ...]],
    anchors_within: float,
    offsets_within: float,
    reached_within: float,
    drum_scale: float = 1.0,
) -> None:
    """Home, calibrate in `rounds` (each restarting the daemon on the last file; with the
    scale measured between two true anchors where the drums are `drum_scale` x the file's,
    else without), check the written file and offsets against the truth (EA within 10 %),
    then fly the true platform with the corrected file to two poses 0.3 m from home, each
    reached within `reached_within`."""
    bench = Bench(tmp_path, move, seed=16, drum_scale=drum_scale)
    scale = bench.scale_distance() if drum_scale != 1.0 else ("--no-scale",)
    try:
        bench.start(ROBOTS / "reference8.yaml")
        homed = cdprd("home", *bench.connection)
        assert homed.returncode == 0, homed.stderr
        model = ROBOTS / "reference8.yaml"
        for k, options in enumerate(rounds):
            if k:
                bench.start(model)  # the offsets stored by the last calibration apply
            bench.enable()
            model = tmp_path / f"calibrated-{k + 1}.yaml"
            report = bench.calibrate(model, *scale, *options)
        corrected = Robot.from_yaml(model)
        anchor = bench.anchor_errors(corrected)
        offset = np.abs(np.array(report["offsets"]) - bench.true_offsets())
        ea = corrected.actuators[0].cable_stiffness / bench.true.actuators[0].cable_stiffness
        before = bench.anchor_errors(bench.file).max()
        print(
            f"residual RMS {report['residual_rms_mm'] * 1e3:.2f} um, {report['seconds']:.0f} s; "
            f"anchors {anchor.max() * 1e3:.3f} mm (before {before * 1e3:.1f}), offsets "
            f"{offset.max() * 1e3:.3f} mm, EA {ea:.4f} x true"
        )
        assert anchor.max() < anchors_within
        assert offset.max() < offsets_within
        assert abs(ea - 1.0) < 0.1
        # restarted on the corrected file, the daemon flies the true platform where told
        bench.start_on_simulator(model)
        bench.enable()
        frame = model_frame(bench.true, corrected)
        for direction in ([0.2, -0.15, 0.1], [-0.2, 0.1, -0.15]):
            target = corrected.home.position + 0.3 * np.array(direction) / np.linalg.norm(direction)
            went = cdprd("goto", *map(str, target), "--wait", *bench.connection)
            assert went.returncode == 0, went.stderr
            time.sleep(1.0)  # settled
            reached = frame.to_model(bench.true_pose()).position
            off = np.linalg.norm(reached - target)
            print(f"goto {target}: the true platform {off * 1e3:.3f} mm off")
            assert off < reached_within
    finally:
        bench.stop()


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.timeout(900)
def test_calibration_through_the_daemon_finds_the_true_robot(tmp_path: Path) -> None:
    """The issue's case: every anchor 20 mm off, the drums 1.01 x the file's (without a
    scale reference the written robot would be 1 % small: anchors ~25 mm off), encoder
    zeros anywhere within a drum turn, EA 0.6 x: home, calibrate close to home (30 poses),
    restart on that file, calibrate over the workspace (80 poses), each round given the
    distance between two anchors; anchors within 0.3 mm, offsets within 0.2 mm, EA within
    10 %, and the true platform within 0.3 mm of where the calibrated daemon sends it,
    0.3 m from home."""
    rounds = [("--poses", "30", "--reach", "0.3", "0.3", "0.22"), ("--poses", "80")]
    fly_calibration(tmp_path, 0.02, rounds, 0.3e-3, 0.2e-3, 0.3e-3, drum_scale=1.01)


# m: how far the true platform may end from a goto's target on the one round's file.  The
# anchors it leaves (up to 1.5 mm) move the platform about as far: CI's run left them
# 1.01 mm off and one goto ended 0.92 mm from its target (the other 0.08 mm).
REACHED_ONE_ROUND = 1.5e-3


@pytest.mark.host_timing  # three real-time processes for minutes: a host's stall brakes them
@pytest.mark.timeout(600)
def test_a_calibration_through_the_daemon_in_one_round(tmp_path: Path) -> None:
    """The same path, shorter: anchors 5 mm off (encoder zeros and EA as the issue's
    case), one round of 30 poses; a round this short leaves anchors and offsets within
    1.5 mm and 0.6 mm (the issue's bounds need the slow test's two rounds).  What it
    leaves is noise far more than the wrench observer's hold: these 30 poses turn a
    length error of 1 um per sample into about 0.7 mm of anchor error (predicted_std
    5 mm at 10 um), and the averaged samples are 0.32-0.38 um RMS off the true robot
    (its pose fitted), held or not (largely the 15 um counts' rounding left); so the
    same run gave 0.34-0.76 mm held (4 runs), 0.39-0.55 mm not (3), 1.10 mm in CI, and
    random length errors of that size alone give 0.26-0.74 mm (10-90 % of 16 fits)."""
    fly_calibration(tmp_path, 0.005, [("--poses", "30")], 1.5e-3, 0.6e-3, REACHED_ONE_ROUND)
