"""Plant physics of the simulated robot (DESIGN §12).

A 6-DOF rigid platform on elastic, unilateral cables, each spooled by a drum driven by
the paper's Assumption 1 actuator model, with friction, holding brakes, cable breakage,
encoders, model mismatch and disturbances; fixed-step, deterministic given a seed.
"""

from sim_bus.plant.actuator import ActuatorModel
from sim_bus.plant.config import (
    ActuatorModelConfig,
    CableConfig,
    DisturbanceConfig,
    EncoderConfig,
    FrictionConfig,
    MismatchConfig,
    PayloadConfig,
    PlantConfig,
    parse_plant_config,
)
from sim_bus.plant.core import Plant
from sim_bus.plant.statics import equilibrium_tensions

__all__ = [
    "ActuatorModel",
    "ActuatorModelConfig",
    "CableConfig",
    "DisturbanceConfig",
    "EncoderConfig",
    "FrictionConfig",
    "MismatchConfig",
    "PayloadConfig",
    "Plant",
    "PlantConfig",
    "equilibrium_tensions",
    "parse_plant_config",
]
