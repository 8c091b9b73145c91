"""A simulated robot that is not the robot file (sim.plant.mismatch): the true geometry,
drum radii, encoder offsets at power-up and payload, and what the daemon then reads."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr import ConfigError, Robot
from daemon.cli.simulated import sim_section, simulated_robot
from daemon.config import load_config
from drivers.config import parse_drives
from sim_bus.config import load_sim_setup, parse_sim
from sim_bus.plant import Plant, PlantConfig
from sim_bus.virtual_robot import VirtualRobot
from tests.conftest import ROBOTS, load_robot
from tests.daemon_stack import Stack, config_for
from tests.processes import CONFIG

ODRIVES = parse_drives({"protocol": "odrive", "nodes": list(range(8))}, "config")


@pytest.fixture(scope="module")
def reference8() -> Robot:
    return load_robot("reference8")


def config(**mismatch: object) -> PlantConfig:
    return PlantConfig.model_validate({"mismatch": mismatch})


@pytest.mark.parametrize(
    ("mismatch", "expected"),
    [
        ({"attachment_offsets": [[0, 0, 0]] * 7}, "mismatch.attachment_offsets: 7 entries for 8"),
        ({"drum_radius_scale": [1.0] * 3}, "mismatch.drum_radius_scale: 3 entries for 8"),
        ({"encoder_offsets": [0.0] * 9}, "mismatch.encoder_offsets: 9 entries for 8"),
    ],
)
def test_per_cable_lists_must_match_the_cables(
    reference8: Robot, mismatch: dict, expected: str
) -> None:
    with pytest.raises(ConfigError, match=expected):
        VirtualRobot(reference8, ODRIVES, config(**mismatch))


@pytest.mark.parametrize(
    ("mismatch", "expected"),
    [
        ({"payload": {"mass": 0}}, "mismatch.payload.mass: Input should be greater than 0"),
        ({"payload": {"mas": 1}}, "mismatch.payload.mas: Extra inputs are not permitted"),
        ({"drum_radius_scale": -1}, "mismatch.drum_radius_scale: Input should be greater than 0"),
        ({"encoder_offsets": [0.1, "x"]}, "mismatch.encoder_offsets.1: Input should be a valid"),
    ],
)
def test_mismatch_errors_name_the_key(mismatch: dict, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        parse_sim({"plant": {"mismatch": mismatch}}, "config")


def test_attachments_drum_radii_and_payload_make_the_true_robot(reference8: Robot) -> None:
    moved = np.zeros((8, 3))
    moved[5] = [0.004, -0.003, 0.002]
    radii = [1.0] * 8
    radii[2] = 1.02
    payload = {"mass": 2.0, "position": [0.05, 0.0, -0.05]}
    true = Plant(
        reference8,
        config(attachment_offsets=moved.tolist(), drum_radius_scale=radii, payload=payload),
    ).robot
    np.testing.assert_allclose(
        true.geometry.attachments, reference8.geometry.attachments + moved, atol=1e-15
    )
    drum = [a.drum_radius for a in true.actuators]
    file_drum = [a.drum_radius for a in reference8.actuators]
    np.testing.assert_allclose(drum, np.array(file_drum) * radii)
    # payload: the mass, centre of mass and inertia of the platform and a point mass
    m, c = reference8.platform.mass, np.array(reference8.platform.center_of_mass)
    assert true.platform.mass == pytest.approx(m + 2.0)
    centre = (m * c + 2.0 * np.array(payload["position"])) / (m + 2.0)
    np.testing.assert_allclose(true.platform.center_of_mass, centre)
    # about the payload's own axis through the new centre (y): I_yy grows by sum m d^2
    a, b = c - centre, np.array(payload["position"]) - centre
    grown = m * (a[0] ** 2 + a[2] ** 2) + 2.0 * (b[0] ** 2 + b[2] ** 2)
    assert true.platform.inertia[1, 1] == pytest.approx(reference8.platform.inertia[1, 1] + grown)
    # unset, the truth is the file
    same = Plant(reference8).robot
    np.testing.assert_array_equal(same.geometry.attachments, reference8.geometry.attachments)
    assert [a.drum_radius for a in same.actuators] == [a.drum_radius for a in reference8.actuators]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("protocol", ["odrive", "cia402"])
def test_the_daemon_reads_the_true_robot_through_the_drives(protocol: str) -> None:
    """The daemon's measured lengths are the true drum lengths, off by exactly the
    configured encoder offsets and scaled by the drum radius error; the true geometry
    (moved anchors) is what the plant's cables span."""
    offsets = [0.0123, -0.02, 0.0, 0.031, -0.0007, 0.0, 0.017, -0.044]
    radii = [1.0, 1.0, 1.01, 1.0, 1.0, 0.98, 1.0, 1.0]
    anchors = np.zeros((8, 3))
    anchors[1] = [0.02, 0.0, -0.01]
    mismatch = {
        "encoder_offsets": offsets,
        "drum_radius_scale": radii,
        "anchor_offsets": anchors.tolist(),
    }

    async def scenario() -> None:
        config = config_for(protocol, sim={"plant": {"mismatch": mismatch}})
        async with Stack(config) as stack:
            driver = stack.service.driver
            await stack.until(lambda: all(math.isfinite(f.length) for f in driver.feedback), 5.0)
            plant = stack.plant
            measured = np.array([f.length for f in driver.feedback])
            truth = plant.drum_lengths  # at rest at the true home: it does not move
            offset = np.array(config.drives.scalings_for(config.robot)[0].length_offset)
            expected = offset + (truth - offset + offsets) / np.array(radii)
            np.testing.assert_allclose(measured, expected, atol=2e-5)
            # the plant's cables span the true anchors, not the file's
            true_lengths = plant.robot.cable_lengths(plant.pose)
            np.testing.assert_allclose(plant.cable_lengths, true_lengths, atol=1e-12)
            file_lengths = config.robot.cable_lengths(plant.pose)
            moved = np.abs(true_lengths - file_lengths)
            assert moved[1] > 5e-3 and np.delete(moved, 1).max() < 1e-12

    asyncio.run(asyncio.wait_for(scenario(), 45))


def true_robot_file(tmp_path: Path, moved: np.ndarray) -> Path:
    """reference8 with its anchors moved by `moved` (n x 3), as a robot file."""
    data = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    for cable, move in zip(data["cables"], moved, strict=True):
        cable["anchor"] = (np.array(cable["anchor"]) + move).tolist()
    data["name"] = "reference8-true"
    path = tmp_path / "true.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.timeout(60)
def test_sim_robot_names_a_true_robot_file_apart_from_the_daemons(tmp_path: Path) -> None:
    """sim.robot: the plant spans the true file's anchors (with plant.mismatch on top),
    the daemon still holds its own robot file and reads the true drum lengths."""
    moved = np.zeros((8, 3))
    moved[3] = [0.015, -0.01, 0.005]
    path = true_robot_file(tmp_path, moved)
    offsets = [0.0, 0.01, 0.0, 0.0, 0.0, 0.0, -0.02, 0.0]

    async def scenario() -> None:
        sim = {"robot": str(path), "plant": {"mismatch": {"encoder_offsets": offsets}}}
        config = config_for("cia402", sim=sim)
        async with Stack(config) as stack:
            driver = stack.service.driver
            await stack.until(lambda: all(math.isfinite(f.length) for f in driver.feedback), 5.0)
            plant = stack.plant
            assert plant.robot.name == "reference8-true"
            np.testing.assert_allclose(
                plant.robot.geometry.anchors, config.robot.geometry.anchors + moved, atol=1e-12
            )
            assert stack.service.robot.name == "reference8"
            measured = np.array([f.length for f in driver.feedback])
            np.testing.assert_allclose(measured, plant.drum_lengths + offsets, atol=2e-5)

    asyncio.run(asyncio.wait_for(scenario(), 45))


def test_sim_robot_relative_to_the_config_file(tmp_path: Path) -> None:
    moved = np.full((8, 3), 0.01)
    true_robot_file(tmp_path, moved)
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROBOTS / "reference8.yaml")
    data["sim"]["robot"] = "true.yaml"
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    setup = load_sim_setup(path)
    assert setup.robot.name == "reference8-true"
    robot = load_config(path).robot
    np.testing.assert_allclose(setup.robot.geometry.anchors, robot.geometry.anchors + moved)


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("missing.yaml", r"cdprd.yaml: sim.robot: .*missing.yaml: cannot read"),
        (str(ROBOTS / "suspended6.yaml"), "sim.robot: the true robot has 6 cables, the robot 8"),
        (7, r"sim.robot: Input should be a valid string, or an object \(got 7\)"),
        ({"name": "x"}, "cdprd.yaml: sim.robot.platform: Field required"),
    ],
)
def test_sim_robot_errors_name_the_key(tmp_path: Path, value: object, expected: str) -> None:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROBOTS / "reference8.yaml")
    data["sim"]["robot"] = value
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=expected):
        load_sim_setup(path)
    with pytest.raises(ConfigError, match=expected):
        config = load_config(path)
        simulated_robot(config, sim_section(config))
