"""Spool buildup (cdpr.spool) and the drivers' scaling with it, against the layered drum
computed turn by turn, and the robot file's spool: key."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from cdpr import ConfigError, Robot
from cdpr.spool import Spool, drum_spool
from drivers.base import Scaling
from tests.conftest import ROBOTS

R, D, N = 0.05, 0.002, 12.0  # first-layer radius, cable diameter, turns per layer


def layered(angle: float) -> tuple[float, float]:
    """The exact layered drum: (wound length, radius) after winding `angle` rad from
    empty, layer i at radius R + i D for N turns."""
    per_layer = 2.0 * math.pi * N
    layers = math.floor(angle / per_layer)
    full = sum(per_layer * (R + i * D) for i in range(layers))
    radius = R + layers * D
    return full + (angle - layers * per_layer) * radius, radius


def test_the_continuous_drum_meets_the_layered_one_at_every_layer_and_stays_near_between() -> None:
    spool = Spool(R, D, N, wound_at_zero=10.0)
    per_layer = 2.0 * math.pi * N
    for layer in range(1, 6):  # a completed layer: the same wound length
        wound, _ = layered(layer * per_layer)
        assert spool.wound_at_zero - spool.length(layer * per_layer) == pytest.approx(
            wound, abs=1e-12
        )
        assert spool.angle(spool.wound_at_zero - wound) == pytest.approx(layer * per_layer)
    for angle in np.linspace(0.0, 5.5 * per_layer, 997):
        wound, radius = layered(float(angle))
        length = spool.length(float(angle))
        assert abs(spool.wound_at_zero - length - wound) <= math.pi * N * D / 4 + 1e-12
        assert abs(spool.radius_at(length) - radius) <= D / 2 + 1e-12
        assert spool.angle(length) == pytest.approx(angle, abs=1e-9)


def scaling(spool: Spool | None, direction: int = 1) -> Scaling:
    return Scaling(R, gear_ratio=5.0, counts_per_rev=4096, direction=direction,
                   length_offset=1.7, spool=spool)  # fmt: skip


@pytest.mark.parametrize("direction", [1, -1])
def test_scaling_pays_out_the_layered_drum_and_converts_torque_by_virtual_work(
    direction: int,
) -> None:
    """Motor positions to lengths: whole layers paid out from a layer boundary give the
    layered drum's length exactly; rates and torques agree with the derivative of the
    length (virtual work: torque x motor angle = force x length)."""
    per_layer = 2.0 * math.pi * N
    wound_at_offset, _ = layered(4 * per_layer)  # 4 full layers on at motor position 0
    spool = Spool(R, D, N, wound_at_zero=1.7 + wound_at_offset)
    s = scaling(spool, direction)
    counts_per_drum_turn = 5.0 * 4096
    assert s.length(0.0) == pytest.approx(1.7, abs=1e-12)
    for layers in range(1, 5):
        position = direction * layers * N * counts_per_drum_turn
        paid = wound_at_offset - layered((4 - layers) * per_layer)[0]
        assert s.length(position) == pytest.approx(1.7 + paid, abs=1e-9)
        assert s.position(s.length(position)) == pytest.approx(position, abs=1e-6)
    for position in direction * np.linspace(0.0, 3.9 * N * counts_per_drum_turn, 41):
        length, step = s.length(float(position)), 1.0
        slope = (s.length(position + step) - s.length(position - step)) / (2 * step)
        assert s.rate(1.0, length) == pytest.approx(slope, rel=1e-7)
        assert s.velocity(s.rate(3.0, length), length) == pytest.approx(3.0)
        motor_radians_per_count = 2.0 * math.pi / 4096
        torque = s.motor_torque(100.0, length)
        assert torque * motor_radians_per_count == pytest.approx(100.0 * slope, rel=1e-7)
        assert s.force(torque, length) == pytest.approx(100.0)
    # the radius grew: the same force takes more torque wound up than paid out
    paid_out = s.length(direction * 3 * N * counts_per_drum_turn)
    assert abs(s.motor_torque(100.0, 1.7)) > abs(s.motor_torque(100.0, paid_out))


def test_without_a_spool_the_scaling_is_the_constant_drum() -> None:
    s = scaling(None)
    assert s.length(20480.0) == pytest.approx(1.7 + 2.0 * math.pi * R)
    assert s.rate(4096.0) == s.rate(4096.0, 3.0) == pytest.approx(2.0 * math.pi * R / 5.0)
    assert s.motor_torque(100.0) == s.motor_torque(100.0, 0.5) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="a drum with a spool converts at a cable length"):
        scaling(Spool(R, D, N, 10.0)).motor_torque(1.0)


def robot_with(spool: dict, cable: dict | None = None) -> Robot:
    data = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    data["actuator"]["spool"] = spool
    if cable is not None:
        data["cables"][2]["actuator"] = {"spool": cable}
    return Robot.from_dict(data, "robot.yaml")


def test_the_robot_file_spool_default_and_per_cable() -> None:
    robot = robot_with(
        {"cable_diameter": 0.002, "drum_width": 0.024, "wound_at_zero": 6.0},
        {"cable_diameter": 0.001, "turns_per_layer": 30, "wound_at_zero": 5.0},
    )
    spools = [drum_spool(a) for a in robot.actuators]
    assert spools[0] == Spool(0.05, 0.002, 12.0, 6.0)
    assert spools[2] == Spool(0.05, 0.001, 30.0, 5.0)
    plain = Robot.from_yaml(ROBOTS / "reference8.yaml")
    assert [drum_spool(a) for a in plain.actuators] == [None] * 8


@pytest.mark.parametrize(
    ("spool", "cable", "expected"),
    [
        ({"cable_diameter": 0.002, "wound_at_zero": 6.0}, None,
         "robot.yaml: actuator.spool: give either turns_per_layer or drum_width"),
        ({"cable_diameter": 0.002, "turns_per_layer": 9, "drum_width": 0.02,
          "wound_at_zero": 6.0}, None, "give either turns_per_layer or drum_width"),
        ({"cable_diameter": 0.002, "drum_width": 0.001, "wound_at_zero": 6.0}, None,
         r"drum_width \(0.001 m\) is narrower than the cable_diameter"),
        ({"cable_diameter": 0.002, "turns_per_layer": 9, "wound_at_zero": 4.0}, None,
         r"spool.wound_at_zero \(4.0 m\) must be at least length_max \(4.2 m\)"),
        ({"cable_diameter": 0.1, "turns_per_layer": 9, "wound_at_zero": 6.0}, None,
         r"spool.cable_diameter \(0.1 m\) must be below twice the drum_radius"),
        ({"cable_diameter": -0.002, "turns_per_layer": 9, "wound_at_zero": 6.0}, None,
         "actuator.spool.cable_diameter: Input should be greater than 0"),
        ({"cable_diameter": 0.002, "turns_per_layer": 9, "wound_at_zero": 6.0},
         {"cable_diameter": 0.002, "turns_per_layer": 9, "wound_at_zero": 3.0},
         r"cables.2.actuator \(merged with defaults\): .*wound_at_zero \(3.0 m\) must be at "
         "least length_max"),
        ({"cable_diameter": 0.002, "turns_per_layer": 9, "wound_at_zero": 6.0, "layers": 3},
         None, "actuator.spool.layers: Extra inputs are not permitted"),
    ],
)  # fmt: skip
def test_spool_errors_name_the_key(spool: dict, cable: dict | None, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        robot_with(spool, cable)
