"""Robot description validation: every bad input names its key and the problem."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.optimize import linprog

from cdpr import ConfigError, Robot
from cdpr.description import load_yaml
from tests.conftest import ROBOTS


@pytest.fixture()
def data() -> dict:
    return yaml.safe_load((ROBOTS / "reference8.yaml").read_text())


def error_of(d: dict) -> str:
    with pytest.raises(ConfigError) as info:
        Robot.from_dict(d)
    return str(info.value)


def test_example_robots_load(robot: Robot) -> None:
    assert robot.n_cables in (6, 8)
    assert robot.m0.shape == (robot.n_cables,)


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["platform"].pop("mass"), "platform.mass: Field required"),
        (lambda d: d["platform"].update(mass=-1), "platform.mass: Input should be greater than 0"),
        (lambda d: d["actuator"].update(m0=float("nan")), "actuator.m0: Input should be a finite"),
        (lambda d: d["cables"][3].update(anchor=[1, 2]), "cables.3.anchor"),
        (lambda d: d["cables"][2].update(anchr=[1, 2, 3]), "cables.2.anchr: Extra inputs"),
        (lambda d: d.update(colour="red"), "colour: Extra inputs are not permitted"),
        (lambda d: d["home"]["quaternion"].update(w=2.0), "home.quaternion: quaternion norm is 2"),
        (
            lambda d: d["platform"].update(inertia=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
            "platform.inertia: inertia must be positive definite",
        ),
        (
            lambda d: d["platform"].update(inertia=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]),
            "platform.inertia: inertia must be a symmetric",
        ),
        (lambda d: d["actuator"].update(t_min=700), "t_min (700.0) must be below force_max"),
        (lambda d: d["actuator"].update(length_min=5), "length_min (5.0) must be below length_max"),
        (
            lambda d: d["cables"][5].update(actuator={"force_max": 10}),
            "cables.5.actuator (merged with defaults): t_min (20.0) must be below force_max",
        ),
        (
            lambda d: d["cables"][0].update(pulley={"radius": 0.03, "axis": [0, 0, 0]}),
            "cables.0.pulley.axis: pulley axis must be a unit vector; its norm is 0",
        ),
        (lambda d: d.update(cables=d["cables"][:5]), "cables: List should have at least 6 items"),
        (
            lambda d: d["actuator"].pop("cable_stiffness"),
            "actuator: cable_damping (100.0 N s) needs cable_stiffness",
        ),
        (lambda d: d["actuator"].update(cable_damping=-1), "actuator.cable_damping: Input should"),
        (lambda d: d["actuator"].update(friction=float("nan")), "actuator.friction: Input should"),
        (lambda d: d.update(name="has space"), "name: String should match pattern"),
    ],
)
def test_bad_input_names_the_key(data: dict, mutate, expected: str) -> None:
    mutate(data)
    message = error_of(data)
    assert expected in message
    assert "Value error" not in message  # pydantic's prefix is noise to an operator


def test_per_cable_override_applies_to_that_cable_only(data: dict) -> None:
    data["cables"][2]["actuator"] = {"m0": 3.0, "force_max": 900.0}
    robot = Robot.from_dict(data)
    assert robot.m0[2] == 3.0 and robot.force_max[2] == 900.0
    assert robot.m0[1] == 1.9 and robot.force_max[1] == 600.0


def test_the_strain_lags_the_tension_by_damping_over_stiffness(data: dict) -> None:
    """The strain lag D / EA per cable: the defaults', a cable's own damping, none where the
    cable has no damping."""
    data["cables"][1]["actuator"] = {"cable_damping": 300.0}
    data["cables"][2]["actuator"] = {"cable_damping": 0.0}
    lag = Robot.from_dict(data).strain_lag
    np.testing.assert_allclose(lag, [1e-3, 3e-3, 0.0, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3], rtol=1e-12)
    data["actuator"].pop("cable_damping")
    del data["cables"][1]["actuator"]
    np.testing.assert_array_equal(Robot.from_dict(data).strain_lag, 0.0)


def test_home_outside_length_limits_is_rejected(data: dict) -> None:
    data["actuator"]["length_max"] = 2.0
    assert "home pose puts cable 0 length 2.3415 m outside [0.3000, 2.0000] m" in error_of(data)


def test_rank_deficient_geometry_is_rejected(data: dict) -> None:
    """Uncrossed (parallel) cables cannot resist a z-rotation at the symmetric home."""
    corners = {
        (1.5, 1.5): (0.2, 0.2),
        (-1.5, 1.5): (-0.2, 0.2),
        (-1.5, -1.5): (-0.2, -0.2),
        (1.5, -1.5): (0.2, -0.2),
    }
    for cable in data["cables"]:
        bx, by = corners[(cable["anchor"][0], cable["anchor"][1])]
        cable["attachment"] = [bx, by, cable["attachment"][2]]
    assert "Jacobian Lambda is rank deficient at the home pose" in error_of(data)


def test_yaml_errors_name_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nplatform: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: line 3, column 1: not valid YAML: .*line 2"):
        Robot.from_yaml(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        Robot.from_yaml(tmp_path / "missing.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping, got list"):
        Robot.from_yaml(tmp_path / "list.yaml")


def test_input_dict_is_not_modified(data: dict) -> None:
    before = copy.deepcopy(data)
    Robot.from_dict(data)
    assert data == before


def tension_margin(robot: Robot) -> float:
    """Largest s with t_min + s <= t <= force_max - s and -Lambda^T t = mu at home (LP)."""
    n = robot.n_cables
    Lam = robot.jacobian(robot.home)
    mu = robot.bias_wrench(robot.home, np.zeros(6))
    cost = np.zeros(n + 1)
    cost[-1] = -1.0
    A_ub = np.block([[-np.eye(n), np.ones((n, 1))], [np.eye(n), np.ones((n, 1))]])
    b_ub = np.concatenate([-robot.t_min, robot.force_max])
    A_eq = np.hstack([-Lam.T, np.zeros((6, 1))])
    res = linprog(cost, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=mu, bounds=[(None, None)] * (n + 1))
    assert res.status == 0, res.message
    return float(res.x[-1])


def test_home_is_well_inside_the_wrench_feasible_workspace(robot: Robot) -> None:
    """Static equilibrium at home with every tension at least 25 N inside its limits."""
    assert tension_margin(robot) > 25.0


def test_spec_round_trips_through_a_plain_dict(robot: Robot) -> None:
    """model_dump() output (unset overrides as None) builds the same robot again."""
    again = Robot.from_dict(robot.spec.model_dump())
    assert again.spec == robot.spec


@pytest.mark.parametrize(
    ("written", "read"),
    [
        ("8:20", "8:20"),  # YAML 1.1: the base-60 integer 500
        ("yes", "yes"),  # YAML 1.1: true
        ("off", "off"),  # YAML 1.1: false
        ("1_000", "1_000"),  # YAML 1.1: 1000
        ("2001-12-14", "2001-12-14"),  # YAML 1.1 (PyYAML): a date
        ("1e3", 1000.0),  # YAML 1.1 (PyYAML): a string
        ("0o17", 15),
        ("true", True),
        ("~", None),
    ],
)
def test_config_files_read_as_yaml_1_2_core(tmp_path: Path, written: str, read: object) -> None:
    (tmp_path / "c.yaml").write_text(f"value: {written}\n")
    value = load_yaml(tmp_path / "c.yaml")["value"]
    assert type(value) is type(read) and value == read


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("a: 1\na: 2\n", "line 2, column 1: duplicate key 'a'"),
        ("1: x\n", "line 1, column 1: the mapping key 1 is not a string: quote it"),
        ("a: !!binary aGk=\n", "the tag tag:yaml.org,2002:binary is not supported"),
        ("a: !!int 1.5\n", "'1.5' is not an integer"),
        ("a: &x [*x]\n", "an alias refers to a node that contains it"),
        (  # "billion laughs": nine nodes spelling out 10^8 values
            "a: &a [x, x, x, x, x, x, x, x, x, x]\n"
            + "".join(
                f"{k}: &{k} [{', '.join([f'*{j}'] * 10)}]\n"
                for j, k in zip("abcdefg", "bcdefgh", strict=True)
            ),
            "values once aliases are expanded",
        ),
    ],
)
def test_config_yaml_beyond_plain_data_is_refused(tmp_path: Path, text: str, problem: str) -> None:
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ConfigError, match=re.escape(problem)):
        load_yaml(tmp_path / "c.yaml")
