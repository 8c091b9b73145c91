"""`cdprd plan`: a path or G-code timed within the cables' tensions, validated as the
daemon validates a client's trajectory, printed and saved as a trajectory `cdprd send`
takes (read back with the daemon's own parser); a path the cables cannot hold and bad
input are refused naming the place, the line or the option."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cdpr.trajectory import parse_trajectory
from daemon.cli import main
from tests.conftest import ROBOTS

CONFIG = str(ROBOTS.parent / "reference8-cia402.yaml")
SQUARE = """; a square in millimetres, climbing on its third side
G21 G90
G1 X100 F6000
G1 Y100
G1 X0 Z1300
G4 P200
G0 Y0 Z1250
"""


def test_gcode_is_timed_validated_and_saved_for_send(tmp_path: Path, capsys) -> None:
    program, output = tmp_path / "square.gcode", tmp_path / "square.json"
    program.write_text(SQUARE)
    args = ["plan", str(program), "--config", CONFIG, "--blend", "0.02"]
    assert main([*args, "--output", str(output), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["accepted"] and summary["refusal"] is None
    assert summary["poses"] == 5 and summary["saved"] == str(output)
    assert 0.09 < summary["peak_linear_speed"] < 1.0  # F6000 caps the G1 sides at 0.1 m/s
    saved = parse_trajectory(json.loads(output.read_text()))
    assert saved.duration == pytest.approx(summary["duration_s"])
    end = saved.sample(saved.end_time).pose.position
    assert end.tolist() == pytest.approx([0.0, 0.0, 1.25])


def test_a_path_file_prints_its_timing(tmp_path: Path, capsys) -> None:
    path = tmp_path / "path.json"
    q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    poses = [{"position": [0, 0, 1.25], "quaternion": q}, {"position": [0.2, 0.1, 1.3]}]
    path.write_text(json.dumps({"poses": poses}))
    assert main(["plan", str(path), "--config", CONFIG]) == 0
    out = capsys.readouterr().out
    assert "2 poses, timed to" in out and "validation: accepted" in out


def test_a_path_the_cables_cannot_hold_is_refused_naming_where(tmp_path: Path, capsys) -> None:
    path = tmp_path / "path.json"
    q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    poses = [{"position": [0, 0, 1.25], "quaternion": q}, {"position": [2.2, 2.2, 2.3]}]
    path.write_text(json.dumps({"poses": poses}))
    assert main(["plan", str(path), "--config", CONFIG]) == 1
    err = capsys.readouterr().err
    assert "path_infeasible: motion 0: no speed holds every cable within its tensions" in err


@pytest.mark.parametrize(
    ("program", "options", "problem"),
    [
        ("G1 X10\nM3", [], "line 2: M3 is not supported"),
        ("G1 X10", ["--margin", "-1"], "--margin: -1 must be a number >= 0"),
        ("G1 X10", ["--blend", "nan"], "--blend: nan must be a number >= 0"),
    ],
)
def test_bad_input_is_named(program, options, problem, tmp_path: Path, capsys) -> None:
    file = tmp_path / "bad.gcode"
    file.write_text(program)
    assert main(["plan", str(file), "--config", CONFIG, *options]) == 2
    assert problem in capsys.readouterr().err
