"""`cdprd analyze`: modal masses, predicted modes, gain robustness; text, JSON and plots."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from cdpr import Pose
from daemon.cli import analyze_cmd
from tests.conftest import ROBOTS, load_robot
from tuning.workspace_analysis import SKIP_REASONS, modal_basis

REFERENCE8 = str(ROBOTS / "reference8.yaml")
SUSPENDED6 = str(ROBOTS / "suspended6.yaml")


def main(argv: list[str]) -> int:
    """`cdprd analyze ...` through the command's own parser (test_cdprd_runs_analyze
    checks that cdprd registers it), independent of the other commands' imports."""
    parser = argparse.ArgumentParser(prog="cdprd")
    analyze_cmd.add_parser(parser.add_subparsers(dest="command", required=True))
    return analyze_cmd.run(parser.parse_args(argv))


def analyze(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["analyze", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_cdprd_runs_analyze(capsys: pytest.CaptureFixture[str]) -> None:
    from daemon.cli import main as cdprd

    assert cdprd(["analyze", "--config", REFERENCE8, "--grid", "2"]) == 0
    assert "modal masses at home (Lemma 1, kg): 2.41" in capsys.readouterr().out


@pytest.fixture(scope="module")
def reference8_json() -> dict:
    """One JSON run on reference8 (2 x 2 x 2 grid), shared by the JSON tests."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["analyze", "--config", REFERENCE8, "--grid", "2", "--json"]) == 0
    (line,) = out.getvalue().splitlines()  # one object on one line
    return json.loads(line)


def test_text_names_home_modal_masses_and_the_largest_stable_mass(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, err = analyze(capsys, "--config", REFERENCE8, "--grid", "2")
    assert code == 0
    assert "modal masses at home (Lemma 1, kg): 2.41, 2.5, 4.28, 5.88, 9.47, 9.49" in out
    assert "robustness: largest stable mass 53.7 kg" in out
    assert "claim 1 (the gains cover every modal mass found, up to" in out and ": yes" in out
    assert "predicted modes at home" in out
    assert "latency tolerance: stable for masses 1.9 to" in out and "periods) after" in out
    assert err == ""  # stderr is no TTY under pytest: no progress bar


def test_json_has_the_documented_keys_and_agrees_with_the_model(reference8_json: dict) -> None:
    d = reference8_json
    assert set(d) == {
        "robot", "config", "controller", "rig", "home", "grid", "robustness",
        "latency_tolerance", "plots",
    }  # fmt: skip
    assert d["controller"]["law"] == "pid" and d["controller"]["gains"]["kp"] == 100.0
    assert set(d["rig"]) == {"m0", "k0", "cable_length", "cable_stiffness", "preload"}
    robot = load_robot("reference8")
    home = d["home"]
    assert home["feasible"] and home["quaternion"] == {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    assert home["modal_masses"] == pytest.approx(robot.modal_masses(robot.home).tolist())
    mode = home["modes"][0]
    assert set(mode) == {
        "mass", "stable", "frequency_hz", "damping", "resonance_hz", "resonance_damping",
        "settling_time", "overshoot", "poles",
    }  # fmt: skip
    assert mode["mass"] == pytest.approx(home["modal_masses"][0])
    assert all(m["stable"] for m in home["modes"])
    grid = d["grid"]
    assert grid["total"] == 8 and grid["analysed"] + sum(grid["skipped"].values()) == 8
    assert set(grid["skipped"]) == set(SKIP_REASONS)
    assert len(grid["points"]) == 8 and "poles" not in grid["points"][0]["modes"][0]
    rob = d["robustness"]
    assert rob["largest_stable_mass"] == pytest.approx(53.7, rel=2e-3)
    assert rob["covers_workspace"] is True
    assert rob["largest_modal_mass"] >= max(home["modal_masses"])
    assert rob["largest_modal_mass"] < rob["largest_stable_mass"]
    assert rob["m0"] == 1.9 and rob["sweep"][0]["mass"] == pytest.approx(1.9)


def test_latency_tolerance_is_the_edge_of_the_rigs_stability(reference8_json: dict) -> None:
    """At the reported latency every checked mass is stable; a little later the limiting
    one is not.  For reference8 at 500 Hz that is about one period: the heaviest modal
    masses put the cables' elastic mode lowest, where a delay's phase hurts most."""
    from tuning.workspace_analysis import rig_for

    lat = reference8_json["latency_tolerance"]
    assert set(lat) == {"seconds", "periods", "limiting_mass", "searched_to", "mass_range"}
    low, high = lat["mass_range"]
    assert low == pytest.approx(1.9)
    assert high == pytest.approx(reference8_json["robustness"]["largest_modal_mass"])
    assert 0.5 < lat["periods"] < 1.5 and lat["seconds"] == pytest.approx(lat["periods"] / 500)
    assert low <= lat["limiting_mass"] <= high
    rig = rig_for(load_robot("reference8"), analyze_cmd.load_config(REFERENCE8)[1])
    assert all(rig.stable(m, lat["seconds"]) for m in np.geomspace(low, high, 24))
    assert not rig.stable(lat["limiting_mass"], lat["seconds"] + 0.01 / 500)


def test_latency_line_says_when_the_scan_ended_or_nothing_was_stable() -> None:
    from types import SimpleNamespace

    from cdpr.control_spec import ControllerSpec
    from tuning.workspace_analysis import LatencyTolerance

    masses = np.array([24.7, 1.9])
    spec = ControllerSpec()
    line = analyze_cmd._latency_line
    whole = LatencyTolerance(masses, 0.008, None, 0.008)
    assert line(SimpleNamespace(latency=whole, spec=spec)).endswith(
        "up to 8 ms (4.00 periods) after its sample (the scan's end)"
    )
    none = LatencyTolerance(masses, None, 24.7, 0.0)
    assert line(SimpleNamespace(latency=none, spec=spec)) == (
        "latency tolerance: none, the 24.7 kg loop is unstable as it is"
    )


def test_grid_flags_the_infeasible_points(capsys: pytest.CaptureFixture[str]) -> None:
    """suspended6 cannot hold the corners of its grid box with t >= t_min: each one is
    skipped with the reason, and counted."""
    code, out, _ = analyze(capsys, "--config", SUSPENDED6, "--grid", "3", "--json")
    assert code == 0
    grid = json.loads(out)["grid"]
    skipped = [p for p in grid["points"] if not p["feasible"]]
    assert skipped and grid["skipped"]["tensions"] == len(skipped)
    assert grid["analysed"] == 27 - len(skipped) > 0
    for p in skipped:
        assert p["reason"] == "tensions" and "t_min" in p["detail"]
        assert p["modal_masses"] == [] and p["modes"] == []
    analysed = [p for p in grid["points"] if p["feasible"]]
    masses = np.concatenate([p["modal_masses"] for p in analysed])
    assert grid["modal_mass_range"] == pytest.approx([masses.min(), masses.max()])
    text = main(["analyze", "--config", SUSPENDED6, "--grid", "3"])
    assert text == 0
    assert f"{len(skipped)} skipped (rank 0, lengths 0, tensions {len(skipped)})" in (
        capsys.readouterr().out
    )


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
def test_plot_writes_non_empty_pngs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = analyze(capsys, "--config", REFERENCE8, "--grid", "2", "--plot", str(tmp_path))
    assert code == 0
    for name in ("modal_masses.png", "modes_vs_mass.png", "robot-3d.png", "workspace.png"):
        data = (tmp_path / name).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 10_000
        assert f"wrote {tmp_path / name}" in out


def test_a_daemon_config_gives_the_robot_and_its_controller_gains(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "r.yaml").write_text((ROBOTS / "reference8.yaml").read_text())
    (tmp_path / "cdprd.yaml").write_text(
        "robot: robots/r.yaml\ncontroller: {rate_hz: 250, pid: {kp: 64.0, kd: 16.0}}\n"
    )
    code, out, _ = analyze(capsys, "--config", str(tmp_path / "cdprd.yaml"), "--grid", "2")
    assert code == 0
    assert "controller pid kp 64 ki 0 kd 16 at 250 Hz" in out
    assert "modal masses at home (Lemma 1, kg): 2.41" in out


def test_a_missing_config_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = analyze(capsys, "--config", "/nonexistent/robot.yaml")
    assert code == 1 and out == ""
    assert err == "error: /nonexistent/robot.yaml: cannot read: No such file or directory\n"


def test_bad_configs_name_the_problem(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad_robot = tmp_path / "bad.yaml"
    bad_robot.write_text((ROBOTS / "reference8.yaml").read_text().replace("m0: 1.9", "m0: -1"))
    code, _, err = analyze(capsys, "--config", str(bad_robot))
    assert code == 1 and "actuator.m0: Input should be greater than 0" in err
    daemon = tmp_path / "cdprd.yaml"
    daemon.write_text("robot: 42\n")
    code, _, err = analyze(capsys, "--config", str(daemon))
    assert code == 1
    assert "robot: expected a mapping or a path to a robot file, got int" in err
    daemon.write_text(f"robot: {ROBOTS / 'reference8.yaml'}\ncontroller: {{pid: {{kp: -1}}}}\n")
    code, _, err = analyze(capsys, "--config", str(daemon))
    assert code == 1 and f"error: {daemon}: controller.pid.kp: Input should be greater" in err


def test_an_unwritable_plot_directory_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = analyze(capsys, "--config", REFERENCE8, "--grid", "2", "--plot", str(blocker))
    assert code == 1 and err.startswith(f"error: cannot write plots to {blocker}: ")


def test_bad_arguments_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["analyze", "--config", REFERENCE8, "--grid", "1"])
    assert exc.value.code == 2
    assert "--grid must be between 2 and 20, got 1" in capsys.readouterr().err


def test_progress_goes_to_stderr_only_when_asked(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = analyze(capsys, "--config", REFERENCE8, "--grid", "2", "--json", "--progress")
    assert code == 0
    assert json.loads(out)["grid"]["total"] == 8  # stdout stays one clean JSON object
    last = err.rsplit("\r", 1)[1]  # the line redrawn in place (daemon.cli.progress)
    assert err.startswith("\rgrid  [") and last.startswith("grid  [") and last.endswith("\n")
    assert "] 100%  8/8  " in last


def test_the_modal_basis_diagonalises_n() -> None:
    """Lemma 1: N sigma_i = sigma_i / m_i with m_i >= m0, and pi_i . sigma_j = delta_ij."""
    robot = load_robot("reference8")
    pose = Pose.from_rotvec(robot.home.position + np.array((0.3, -0.2, 0.1)), (0.1, 0.0, 0.2))
    basis = modal_basis(robot, pose)
    Lam = robot.jacobian(pose)
    N = np.linalg.solve(robot.mass_matrix(pose), Lam.T @ Lam)
    assert basis.masses == pytest.approx(robot.modal_masses(pose))
    assert np.all(basis.masses >= robot.m0.min())
    assert N @ basis.vectors == pytest.approx(basis.vectors / basis.masses, abs=1e-9)
    assert basis.duals @ basis.vectors == pytest.approx(np.eye(6), abs=1e-9)
