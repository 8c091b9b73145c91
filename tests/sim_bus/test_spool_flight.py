"""Spool buildup on the bus: the simulated drives wind the true drum
(cdpr.spool), the host's driver converts with the robot file's; flown in lock-step over
CAN frames (tuning.can_lockstep) with the controller, in simulated time."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scipy.optimize import brentq

from cdpr import Pose, Robot
from cdpr.controller import ParallelController, static_tensions
from cdpr.trajectory import Trajectory, Waypoint
from drivers.factory import protocol_driver
from sim_bus.plant import PlantConfig
from sim_bus.virtual_robot import VirtualRobot
from tests.conftest import ROBOTS
from tests.daemon_stack import config_for
from tuning.can_lockstep import LockstepLink, bring_up, run_cycles

SPOOL = {"cable_diameter": 0.002, "turns_per_layer": 12, "wound_at_zero": 6.0}


def reference8(spool: dict | None) -> Robot:
    data = yaml.safe_load((ROBOTS / "reference8.yaml").read_text())
    if spool is not None:
        data["actuator"]["spool"] = spool
    return Robot.from_dict(data, "reference8")


def fly(model: Robot, truth: Robot, protocol: str) -> tuple[np.ndarray, float, float, str]:
    """Bring the drives up over CAN in lock-step, then fly a 2 s lift and turn from home
    and hold 0.5 s: (the lengths the host read at rest minus the true drum lengths, RMS
    position error of the true platform in mm, the largest relative error of the force a
    drive produced against the command, the fault or "")."""
    config = config_for(protocol)
    drives, spec = config.drives, config.controller
    sim = VirtualRobot(truth, drives, PlantConfig())
    driver = protocol_driver(drives, drives.scalings_for(model))
    link = LockstepLink(sim, driver)
    controller = ParallelController(model, spec)
    period = 1.0 / spec.rate_hz
    home = model.home
    forces = (-static_tensions(model, controller.tension, home)).tolist()
    bring_up(link, forces, period)
    read = np.array([f.length for f in driver.feedback]) - sim.plant.drum_lengths
    target = Pose.from_rotvec(home.position + np.array([0.3, -0.25, 0.35]), (0.0, 0.1, 0.15))
    trajectory = Trajectory([Waypoint(0.0, home), Waypoint(2.0, target)])
    controller.reset(home)
    controller.follow(trajectory)
    start, errors, fault, force_errors = link.t, [], [], []

    commanded: list[np.ndarray] = []

    def cycle(t: float) -> list[float] | None:
        lengths = [f.length for f in driver.feedback]
        rates = [f.rate for f in driver.feedback]
        out = controller.step(t - start, lengths, rates)
        if not out.feasible:
            fault.append(out.reason)
            return None
        reference = trajectory.sample(t - start).pose.position
        errors.append(float(np.linalg.norm(sim.plant.pose.position - reference)))
        produced = np.array([drive.force for drive in sim.drives])  # the last commands'
        if errors[1:]:
            force_errors.append(float(np.max(np.abs(produced / commanded[0] - 1.0))))
        commanded[:] = [out.commands]
        return out.commands.tolist()

    run_cycles(link, period, cycle, 2.5)
    rms = math.sqrt(float(np.mean(np.square(errors)))) * 1e3 if errors else math.inf
    return read, rms, max(force_errors, default=math.inf), "; ".join(fault)


@pytest.mark.parametrize("protocol", ["cia402", "odrive"])
def test_a_spool_in_the_truth_and_the_file_flies_like_a_constant_drum(protocol: str) -> None:
    plain, spooled = reference8(None), reference8(SPOOL)
    read, rms_plain, _, fault = fly(plain, plain, protocol)
    assert not fault and np.abs(read).max() < 3e-5
    read, rms_spooled, force_error, fault = fly(spooled, spooled, protocol)
    assert not fault, fault
    assert np.abs(read).max() < 3e-5  # the drives' counts only
    assert force_error < 2e-3  # torque per mille / float32, at the radius wound on now
    print(f"{protocol}: RMS {rms_plain:.4f} mm constant drums, {rms_spooled:.4f} mm with spools")
    assert rms_spooled < 1.2 * rms_plain + 0.01


def test_a_daemon_without_the_spool_reads_the_constant_drums_lengths() -> None:
    """The truth winds on in layers, the file says nothing: the lengths the host reads are
    the drum angles x the file's radius, off by centimetres (computed here from the wound
    length w(φ) = b φ + g φ² / 4 by root finding), and the flight fails."""
    truth = reference8(SPOOL)
    read, _, _, fault = fly(reference8(None), truth, "cia402")
    b = 0.05 - 0.001
    g = 0.002 / (math.pi * 12)

    def angle(wound: float) -> float:
        return brentq(lambda phi: b * phi + g * phi * phi / 4 - wound, 0.0, 1e4)

    sim = VirtualRobot(truth, config_for("cia402").drives, PlantConfig())
    drums = sim.plant.drum_lengths
    offset = 0.0  # drives.length_offset: the cable length at motor position 0
    expected = [offset + 0.05 * (angle(6.0 - offset) - angle(6.0 - ell)) - ell for ell in drums]
    np.testing.assert_allclose(read, expected, atol=3e-5)
    assert np.abs(read).min() > 0.03
    assert fault
