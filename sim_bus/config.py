"""The simulator's view of a daemon config file: robot, drives, can and sim sections.

The simulator reads the same file as the daemon (so both sides of the bus agree on the
robot, node ids and scaling) but never imports the daemon; sections it does not use
are ignored here and validated by the daemon.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, NamedTuple

from pydantic import Field, model_validator

from cdpr import ConfigError, Robot
from cdpr.description import (
    NonNegativeFloat,
    PositiveFloat,
    StrictModel,
    load_yaml,
    show_path,
    validate_section,
)
from drivers.config import CanConfig, CanFile, DrivesConfig, can_buses, parse_drives
from sim_bus.bus.frame_faults import FrameFaultConfig
from sim_bus.plant import PlantConfig


class RigConfig(StrictModel):
    """`sim.rig`: simulate ONE winch on the bench instead of the robot (`cdprd tune`):
    cable `drive`'s true actuator (sim.plant's mismatch applied) and drive, with a cable
    `cable_length` m long to a hanging mass `load_mass` kg (0: no load, the free drum),
    or clamped at its end (`clamped`, pretensioned to `preload` N).  The rig is
    sim_bus.plant.rig.SingleActuatorRig behind the same virtual drive as on the robot."""

    drive: Annotated[int, Field(ge=0)] = 0  # the cable whose actuator and drive are simulated
    load_mass: NonNegativeFloat = 0.0  # kg hanging from the cable; 0: the free drum
    clamped: bool = False  # the cable's end is clamped instead of loaded
    cable_length: PositiveFloat = 2.0  # m, from the drum to the load or the clamp
    preload: PositiveFloat = 100.0  # N, the clamped cable's pretension

    @model_validator(mode="after")
    def _one_load(self) -> RigConfig:
        if self.clamped and self.load_mass:
            raise ValueError("give either load_mass or clamped: true, not both")
        return self


class SimConfig(StrictModel):
    """`sim:` section: the simulated robot, its drives and its bus.

    plant: the simulated robot's physics (sim_bus.plant.PlantConfig).
    frame_faults: faults injected into the bus's frames (sim_bus.bus.frame_faults).
    serve_socketcand: "127.0.0.1:PORT" to serve the bus to other processes in the
      socketcand protocol (`python -m sim_bus`); null: not served.
    wake_period: seconds between the simulator's own wake-ups; null: the plant step
      (see `wake`).
    rig: one winch on the bench instead of the robot (RigConfig); null: the robot.
    """

    plant: PlantConfig = PlantConfig()
    frame_faults: FrameFaultConfig = FrameFaultConfig()
    serve_socketcand: str | None = None
    wake_period: PositiveFloat | None = None
    rig: RigConfig | None = None
    # the true robot: a robot file (relative to the config file) or an inline description,
    # in place of the daemon's `robot:` (see true_base); plant.mismatch applies on top
    robot: str | dict[str, Any] | None = None

    @model_validator(mode="after")
    def _wake_not_below_step(self) -> SimConfig:
        if self.wake_period is not None and self.wake_period < self.plant.step:
            raise ValueError(
                f"wake_period ({self.wake_period} s) is shorter than plant.step "
                f"({self.plant.step} s)"
            )
        return self

    def wake(self, drives: DrivesConfig) -> float:
        """The runner's wake-up period.  The plant integrates in plant.step steps either
        way, catching up at every wake-up and every frame; wake-ups only time what the
        drives do on their own (heartbeats, watchdogs, streamed feedback), so a longer
        period saves CPU (each wake-up is a few system calls: costly in user-mode Linux).
        It may not exceed the interval of streamed feedback (ConfigError)."""
        period = self.wake_period or self.plant.step
        if drives.streamed and period > 1.0 / drives.feedback_rate_hz + 1e-12:
            raise ConfigError(
                f"sim.wake_period ({period} s) exceeds the interval of the drives' streamed "
                f"feedback (1 / drives.feedback_rate_hz = {1.0 / drives.feedback_rate_hz:g} s)"
            )
        return period


def true_base(sim: SimConfig, robot: Robot, base: Path, source: str = "config") -> Robot:
    """The robot the simulator builds its truth on: `sim.robot` (a file relative to `base`,
    the config's directory, or inline) with as many cables as the daemon's `robot`, or
    `robot` itself when unset (the truth is then the daemon's file with plant.mismatch).
    A calibrated robot file stays the daemon's while the simulated truth stays put."""
    if sim.robot is None:
        return robot
    true = Robot.from_reference(sim.robot, base, source, "sim.robot")
    if true.n_cables != robot.n_cables:
        raise ConfigError(
            f"{source}: sim.robot: the true robot has {true.n_cables} cables, the robot "
            f"{robot.n_cables}"
        )
    return true


class SimSetup(NamedTuple):
    robot: Robot  # the simulated robot before plant.mismatch (true_base)
    drives: DrivesConfig
    buses: list[CanConfig]  # the `can:` section's buses, one or several
    sim: SimConfig


def parse_sim(data: Any, source: str = "config", key: str = "sim") -> SimConfig:
    """Validate a `sim:` section; ConfigError names the key and the problem."""
    return validate_section(SimConfig, {} if data is None else data, source, key)


def load_sim_setup(path: str | Path) -> SimSetup:
    """Read the simulator's sections of a daemon config file (ConfigError names the key)."""
    path = Path(path)
    source = show_path(path)
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level")
    for key in ("robot", "drives"):
        if key not in data:
            raise ConfigError(f"{source}: missing section {key!r}")
    robot = Robot.from_reference(data["robot"], path.resolve().parent, source)
    drives = parse_drives(data["drives"], source)
    can = validate_section(CanFile, {k: v for k, v in data.items() if k == "can"}, source).can
    sim = parse_sim(data.get("sim"), source)
    robot = true_base(sim, robot, path.resolve().parent, source)
    return SimSetup(robot, drives, can_buses(can, drives, source), sim)
