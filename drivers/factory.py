"""The host-side driver a `drives:` config asks for."""

from __future__ import annotations

from collections.abc import Sequence

from cdpr import Robot
from drivers.base import ActuatorDriver, Scaling
from drivers.config import DrivesConfig
from drivers.multibus import BusDrives, MultiBusDriver


def make_driver(config: DrivesConfig, robot: Robot) -> ActuatorDriver:
    """The configured protocol's driver for `robot`'s cables (drum radii from the robot);
    with drives on several buses, one per bus behind a MultiBusDriver."""
    scalings = config.scalings_for(robot)
    names = list(dict.fromkeys(config.bus_names()))
    if len(names) == 1:
        return protocol_driver(config, scalings)
    parts = []
    for name in names:
        cables, drives = config.on_bus(name)
        parts.append(
            BusDrives(name, cables, protocol_driver(drives, [scalings[i] for i in cables]))
        )
    return MultiBusDriver(parts, config.nodes)


def protocol_driver(config: DrivesConfig, scalings: Sequence[Scaling]) -> ActuatorDriver:
    """The driver of the configured protocol for all of `config`'s drives, on one bus."""
    if config.protocol == "cia402":
        from drivers.cia402.host import Cia402Driver

        return Cia402Driver(config, scalings)
    from drivers.odrive.host import OdriveDriver

    return OdriveDriver(config, scalings)
