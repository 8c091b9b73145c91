"""Lock-step runner: timing of controller calls, zero-order hold, delay, recording."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cdpr import Robot
from sim_bus.plant import Plant, PlantConfig, equilibrium_tensions
from sim_bus.plant.rig import SingleActuatorRig
from tests.conftest import load_robot
from tuning.lockstep import Recording, run_lockstep


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot("reference8")


def test_controller_sees_the_drives_at_the_control_rate(robot: Robot) -> None:
    plant = Plant(robot)
    hold = plant.commands.copy()
    calls = []

    def controller(t, lengths, rates):
        calls.append((t, lengths.copy(), rates.copy()))
        return hold

    rec = run_lockstep(plant, controller, 0.1, 250)
    assert [c[0] for c in calls] == pytest.approx(np.arange(25) * 4e-3, abs=1e-12)
    assert plant.time == pytest.approx(0.1)
    np.testing.assert_array_equal(rec.t, [c[0] for c in calls])
    np.testing.assert_array_equal(rec.measured_lengths, [c[1] for c in calls])
    np.testing.assert_array_equal(rec.measured_rates, [c[2] for c in calls])
    assert rec.position.shape == (25, 3)
    assert rec.quaternion.shape == (25, 4)
    assert rec.tensions.shape == rec.lengths.shape == rec.commands.shape == (25, 8)


def test_commands_are_held_over_the_cycle(robot: Robot) -> None:
    """Lock-step equals setting the commands and stepping by hand (zero-order hold)."""
    hold = -equilibrium_tensions(robot, robot.home)

    def commands(k: int) -> np.ndarray:
        return hold + 5.0 * math.sin(0.3 * k) * np.arange(8)

    plant = Plant(robot)
    rec = run_lockstep(plant, lambda t, *_: commands(round(t * 200)), 0.2, 200)
    by_hand = Plant(robot)
    for k in range(40):
        by_hand.set_commands(commands(k))
        np.testing.assert_array_equal(by_hand.pose.position, rec.position[k])
        for _ in range(5):
            by_hand.step()
    np.testing.assert_array_equal(by_hand.pose.position, plant.pose.position)


@pytest.mark.parametrize("delay", [0, 1, 3])
def test_whole_cycles_of_latency_shift_the_applied_commands(robot: Robot, delay: int) -> None:
    plant = Plant(robot)
    initial = plant.commands.copy()
    hold = -equilibrium_tensions(robot, robot.home)
    rec = run_lockstep(plant, lambda t, *_: hold + 1000.0 * t, 0.02, 500, latency=delay * 2e-3)
    np.testing.assert_array_equal(rec.applied[:delay], np.tile(initial, (delay, 1)))
    np.testing.assert_allclose(rec.applied[delay:], rec.commands[: len(rec) - delay])


def test_a_fraction_of_a_cycle_of_latency_splits_the_hold(robot: Robot) -> None:
    """Commands due 3 ms after their 5 ms cycle starts: the plant holds the previous
    ones for 3 of the cycle's 5 steps, then the new ones (seen through plant.step)."""
    plant = Plant(robot)
    hold = -equilibrium_tensions(robot, robot.home)
    held: list[np.ndarray] = []
    step = plant.step

    def recording_step() -> None:
        held.append(plant.commands.copy())
        step()

    plant.step = recording_step  # type: ignore[method-assign]
    rec = run_lockstep(plant, lambda t, *_: hold + 1000.0 * t, 0.02, 200, latency=3e-3)
    held_arr = np.array(held).reshape(len(rec), 5, -1)
    np.testing.assert_allclose(held_arr[1:, :3], held_arr[:-1, 3:4].repeat(3, axis=1))
    np.testing.assert_allclose(held_arr[:, 3:], np.repeat(rec.commands[:, None], 2, axis=1))


def test_bad_timing_is_refused(robot: Robot) -> None:
    plant = Plant(robot)
    with pytest.raises(ValueError, match="not a whole number"):
        run_lockstep(plant, lambda *_: plant.commands, 0.1, 300)
    for latency in (-2e-3, 1.5e-3, float("nan")):
        with pytest.raises(ValueError, match="latency must be a whole number"):
            run_lockstep(plant, lambda *_: plant.commands, 0.1, 500, latency=latency)


def test_recording_round_trip(robot: Robot, tmp_path) -> None:
    plant = Plant(robot)
    rec = run_lockstep(plant, lambda *_: plant.commands, 0.05, 100)
    rec.save(tmp_path / "run.npz")
    again = Recording.load(tmp_path / "run.npz")
    assert set(again.series) == set(rec.series)
    for name in rec.series:
        np.testing.assert_array_equal(again[name], rec[name])
    assert again.pose(3) == rec.pose(3)
    with pytest.raises(AttributeError, match="no series 'nope'"):
        _ = rec.nope


def test_single_actuator_rig_in_lock_step(robot: Robot) -> None:
    """A PD (per unit mass, with the equilibrium command as feed-forward) on one
    actuator with a cable to a 5 kg load: the tuning set-up of the paper's §4."""
    rig = SingleActuatorRig(robot.actuators[0], 5.0, PlantConfig())
    target = rig.equilibrium["length"] + 0.01
    m = robot.m0[0] + 5.0

    def pd(_t, lengths, rates):
        return [rig.equilibrium["command"] - m * (100 * (lengths[0] - target) + 20 * rates[0])]

    rec = run_lockstep(rig, pd, 2.0, 500)
    assert abs(rec.lengths[-1, 0] - target) < 2e-5  # 10 um encoder counts
    assert rec.tensions.min() > 0.0  # the cable stayed taut
    assert set(rec.series) >= {"load_position", "load_velocity", "forces", "applied"}
