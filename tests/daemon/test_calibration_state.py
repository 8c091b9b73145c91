"""The stored offsets carry a checksum and the robot's identity: an edited file, another
robot's, one from before the robot file or the drives changed, and a schema 1 file (which
cannot be checked) are refused naming the key and asking for homing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from daemon.config import DaemonConfig, load_config
from daemon.service.calibration_state import (
    StateFileError,
    load_state,
    new_state,
    robot_identity,
    save_state,
    state_path,
)
from tests.conftest import ROBOTS
from tests.daemon_stack import DRIVER_CONFIGS, config_for

OFFSETS = [0.01 * k for k in range(8)]


def stored(tmp_path: Path, config: DaemonConfig) -> Path:
    robot = config.robot
    path = state_path(tmp_path, robot.name)
    save_state(path, new_state(robot.name, robot_identity(robot, config.drives), OFFSETS, "home"))
    return path


def load(path: Path, config: DaemonConfig):
    robot = config.robot
    return load_state(path, robot.name, robot.n_cables, robot_identity(robot, config.drives))


def test_a_saved_state_loads_back(tmp_path: Path) -> None:
    config = config_for("cia402")
    state = load(stored(tmp_path, config), config)
    assert state.offsets == tuple(OFFSETS) and state.method == "home"
    assert json.loads(stored(tmp_path, config).read_text())["checksum"].startswith("sha256:")


def edited(data: dict) -> None:
    data["offsets"][2] += 0.3


def schema_1(data: dict) -> None:
    for key in ("identity", "checksum"):
        data.pop(key)
    data["schema"] = 1


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        (edited, "checksum: does not match the content (edited or damaged); home again"),
        (
            schema_1,
            "schema: 1, written before state files carried a checksum and the robot's "
            "identity: it cannot be checked; home again (cdprd home)",
        ),
    ],
)
def test_an_edited_or_unchecked_file_is_refused(change, problem: str, tmp_path: Path) -> None:
    config = config_for("cia402")
    path = stored(tmp_path, config)
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    with pytest.raises(StateFileError) as refused:
        load(path, config)
    assert str(refused.value).startswith(f"{path}: {problem}")


def anchor_moved(data: dict) -> None:
    robot = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    robot["cables"][0]["anchor"][2] += 0.05
    data["robot"] = robot


@pytest.mark.parametrize(
    "other",
    [
        lambda data: data["drives"].update(gear_ratio=10.0),  # a re-geared drive
        lambda data: data["drives"].update(nodes=[2, 1, 3, 4, 5, 6, 7, 8]),  # nodes swapped
        anchor_moved,  # a robot file with another geometry (another robot of this name)
    ],
)
def test_the_offsets_of_another_robot_or_other_drives_are_refused(other, tmp_path: Path) -> None:
    path = stored(tmp_path, config_for("cia402"))
    changed = load_config(DRIVER_CONFIGS["cia402"], other)
    with pytest.raises(StateFileError) as refused:
        load(path, changed)
    assert str(refused.value).startswith(f"{path}: identity: the offsets of another robot")
    assert str(refused.value).endswith("home again (cdprd home) to find the offsets afresh")
