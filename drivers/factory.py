"""The host-side driver a `drives:` config asks for."""

from __future__ import annotations

from cdpr import Robot
from drivers.base import ActuatorDriver
from drivers.config import DrivesConfig


def make_driver(config: DrivesConfig, robot: Robot) -> ActuatorDriver:
    """The configured protocol's driver for `robot`'s cables (drum radii from the robot)."""
    scalings = config.scalings_for(robot)
    if config.protocol == "cia402":
        from drivers.cia402.host import Cia402Driver

        return Cia402Driver(config, scalings)
    from drivers.odrive.host import OdriveDriver

    return OdriveDriver(config, scalings)
