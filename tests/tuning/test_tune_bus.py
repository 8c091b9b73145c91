"""`cdprd tune` in real time on a bus: as a process against `python -m sim_bus` (sim.rig:
one winch whose true m0, k0 and lag are 30 % off the robot file) as a separate process
over socketcand, it identifies m0 and k0 within 10 % and the force lag within 50 %
(real-time jitter and the bus's delays are in the data: the lag, 2.6 ms, about a period,
is what a loaded host disturbs most; 1 % in simulated time, bench/tune.py), and a
slack cable during the experiment brakes the drive over the bus (Set_Input_Pos after
the last torque command) and says why; `--sim` does the same against the in-process
simulator."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import yaml

from daemon.cli import main
from drivers.odrive.codec import Cmd
from tests.host_steal import StealMeter
from tests.processes import (
    ROOT,
    daemon_config,
    finish,
    patient_watchdogs,
    serve_simulator,
)

CONFIG = ROOT / "config" / "reference8-odrive.yaml"
DRIVE = 3
NODE = 3  # reference8-odrive: node = cable
TRUE = {"m0": 1.9 * 1.3, "k0": 20.0 * 0.7, "lag": 2.6e-3}
TIMEOUT = 120.0


def configs(tmp_path: Path, load_mass: float) -> tuple[Path, dict]:
    """The simulator's config (the rig of cable DRIVE under `load_mass`) and the data of
    the tune's (no rig: the winch is on the bus)."""
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    patient_watchdogs(data)  # as the other process tests: a loaded 2-CPU host
    # a 0.25 ms plant step: the simulator applies a command from the start of the step it
    # arrives in, which would shorten the lag it shows by half a step on average
    data["sim"]["plant"].update(
        step=2.5e-4,
        actuator={"c": [TRUE["lag"]]},
        mismatch={"m0_scale": 1.3, "k0_scale": 0.7},
    )
    sim = tmp_path / "sim.yaml"
    sim.write_text(
        yaml.safe_dump(
            {**data, "sim": {**data["sim"], "rig": {"drive": DRIVE, "load_mass": load_mass}}}
        )
    )
    return sim, data


def tune(config: Path, *options: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "daemon.cli",
            "tune",
            "--config",
            str(config),
            "--drive",
            str(DRIVE),
            "--json",
            *options,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@contextlib.contextmanager
def listening(port: int, channel: str) -> Iterator[list[can.Message]]:
    """Every frame on the simulator's bus while the block runs (a third client)."""
    bus = can.Bus(interface="socketcand", channel=channel, host="127.0.0.1", port=port)
    frames: list[can.Message] = []
    stop = threading.Event()

    def read() -> None:
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is not None:
                frames.append(msg)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        yield frames
    finally:
        stop.set()
        reader.join(2.0)
        bus.shutdown()


def check_identified(meter: StealMeter, model: dict, lag_tolerance: float) -> None:
    """m0 and k0 within 10 % of TRUE, the lag within `lag_tolerance`: a real-time
    experiment's figures, judged unless the hypervisor took the host's CPUs meanwhile
    (tests.host_steal: measured here with 4-8 % stolen, lag +60 % and +131 %, k0 -14 %
    and -20 %)."""
    for name, true in TRUE.items():
        tolerance = lag_tolerance if name == "lag" else 0.10
        meter.check(
            model[name] == pytest.approx(true, rel=tolerance),
            f"the identified {name}",
            f"{model[name]:.4g}, the true {true:.4g} +-{tolerance:.0%}",
        )


@pytest.mark.slow  # real-time experiments, 10-20 s each
@pytest.mark.host_timing
def test_tune_identifies_a_winch_over_the_bus_in_real_time(tmp_path: Path) -> None:
    sim_config, data = configs(tmp_path, 0.0)
    sim, port, channel = serve_simulator(sim_config)
    try:
        with StealMeter() as meter:
            proc = tune(daemon_config(tmp_path, data, port, channel), "--duration", "8")
            out, err = proc.communicate(timeout=TIMEOUT)
    finally:
        finish(sim)
    assert proc.returncode == 0, err
    report = json.loads(out)
    print(json.dumps({"model": report["model"], "experiment": report["experiment"]}))
    experiment = report["experiment"]
    assert experiment["frames"] > 8000  # the winch really talked over the bus
    assert 0.0 < experiment["transit"] < experiment["latency"]
    check_identified(meter, report["model"], lag_tolerance=0.5)  # 3.56 ms beside the suite
    assert report["gains"]["ok"]


@pytest.mark.slow  # over 4.5 s
def test_a_slack_cable_over_the_bus_brakes_and_says_why(tmp_path: Path) -> None:
    sim_config, data = configs(tmp_path, 5.0)
    sim, port, channel = serve_simulator(sim_config, "--fault-input")
    try:
        with listening(port, channel) as frames:
            proc = tune(daemon_config(tmp_path, data, port, channel), "--load-mass", "5")
            lines = []
            for line in proc.stderr:  # progress: the snap once the drive follows torque
                lines.append(line)
                if line.startswith("enabled"):
                    sim.stdin.write("snap:0\n")
                    sim.stdin.flush()
                    break
            out, err = proc.communicate(timeout=TIMEOUT)
    finally:
        finish(sim)
    assert proc.returncode == 3, "".join(lines) + err
    report = json.loads(out)
    assert report["abort"] == "slack_cable"
    assert "slack cable: the drum accelerated" in err
    ids = [m.arbitration_id for m in frames]
    torque, hold = (NODE << 5) | Cmd.SET_INPUT_TORQUE, (NODE << 5) | Cmd.SET_INPUT_POS
    assert torque in ids, "no torque command went out"
    last_torque = len(ids) - 1 - ids[::-1].index(torque)
    assert hold in ids[last_torque:], "no position hold after the last torque command"


@pytest.mark.slow  # real-time experiments, 10-20 s each
@pytest.mark.host_timing
def test_tune_sim_runs_in_real_time_on_the_in_process_simulator(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim_config, _ = configs(tmp_path, 0.0)  # --sim makes the rig of the request
    args = ["tune", "--config", str(sim_config), "--sim", "--drive", str(DRIVE), "--json"]
    with StealMeter() as meter:
        assert main([*args, "--duration", "4"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["experiment"]["frames"] > 4000
    assert report["experiment"]["latency"] > 0.0  # real time: commands after their samples
    # the simulator shares the cycle's loop and interpreter, so the loop's jitter is in the
    # data as over the bus: the lag within the same 50 % (-7 % and +16 % measured on a
    # loaded 2-CPU host, +28 % in CI)
    check_identified(meter, report["model"], lag_tolerance=0.5)
