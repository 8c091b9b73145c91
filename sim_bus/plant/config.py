"""Plant configuration: a validated pydantic model whose errors name the key.

Everything the simulator may differ in from the controller's model lives here:
integration step, cable elasticity, the actuator model of the paper's Assumption 1,
friction, the encoders, the model mismatch and the disturbance wrench.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from pydantic import Field, field_validator, model_validator

from cdpr import ConfigError, Robot
from cdpr.description import (
    FiniteFloat,
    NonNegativeFloat,
    PositiveFloat,
    StrictModel,
    Vec3,
    validate_section,
)
from sim_bus.plant.actuator import ActuatorModel
from sim_bus.plant.fixture import FixtureConfig

Wrench = tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
Coefficients = list[NonNegativeFloat]


class CableConfig(StrictModel):
    """Elastic unilateral cable: t = EA ε + damping dε/dt while taut, ε = (L - l) / l,
    with L the geometric length and l the unstretched length paid out by the drum."""

    stiffness: PositiveFloat = 1e5  # EA, N per unit strain
    damping: NonNegativeFloat = 100.0  # N s per unit strain rate


class ActuatorModelConfig(StrictModel):
    """Assumption 1 of the paper, in its general form (ascending derivative order):

    f + c[0] f' + c[1] f'' + ... + k[0] l' + k[1] l'' + ... = f_c + c_tilde[0] f_c' + ...

    i.e. c = (c_2, c_3, ...), k = (k_0, k_1, ...), c_tilde = (c~_2, ...) in the paper's
    names.  The default is a first-order electrical lag of 2 ms; k = None takes the
    back-EMF k0 of each actuator from the robot description, k = [k0] exactly.
    """

    c: Coefficients = Field(default_factory=lambda: [2e-3])
    """Coefficients of f', f'', ... (s, s^2, ...); the default is a 2 ms first-order lag."""
    k: Coefficients | None = None
    """Coefficients of l', l'', ... (N s/m, N s^2/m, ...); null: [k0] of each actuator."""
    c_tilde: Coefficients = Field(default_factory=list)
    """Coefficients of f_c', f_c'', ... (s, s^2, ...); empty: none."""

    @field_validator("c")
    @classmethod
    def _hurwitz(cls, v: list[float]) -> list[float]:
        poly = _trim([1.0, *v])
        if len(poly) > 1:
            roots = np.roots(poly[::-1])
            if np.any(roots.real >= 0.0):
                raise ValueError(
                    f"1 + c[0] s + c[1] s^2 + ... must have all roots in the left half plane "
                    f"(a stable actuator); roots {np.round(roots, 6).tolist()}"
                )
        return v

    @model_validator(mode="after")
    def _proper(self) -> ActuatorModelConfig:
        C, K, Ct = self.coefficients(0.0)
        if len(Ct) > len(C):
            raise ValueError(
                f"c_tilde has {len(Ct) - 1} non-zero coefficients but c has {len(C) - 1}: "
                "f_c may not enter with a higher derivative than f (improper model)"
            )
        if len(K) > len(C) + 1:
            raise ValueError(
                f"k has {len(K)} coefficients but at most len(c) + 2 = {len(C) + 1} are "
                "allowed (the paper's k_0 ... k_n go with c_2 ... c_n)"
            )
        if self.k is not None:  # else K(s) = k0 s, always realisable
            self.model(0.0)
        return self

    def coefficients(self, k0: float) -> tuple[list[float], list[float], list[float]]:
        """Polynomials in s, ascending, trailing zeros dropped: C(s) = 1 + c_2 s + ...,
        K(s)/s = k_0 + k_1 s + ... (with this actuator's k0 when k is None), and
        C~(s) = 1 + c~_2 s + ..."""
        K = [k0] if self.k is None else list(self.k)
        return _trim([1.0, *self.c]), _trim(K), _trim([1.0, *self.c_tilde])


    def model(self, k0: float) -> ActuatorModel:
        """The realised actuator whose back-EMF constant is k0 (ValueError if the model
        is not passive at high frequency)."""
        return ActuatorModel.realise(*self.coefficients(k0))


def _trim(poly: list[float]) -> list[float]:
    out = list(poly)
    while len(out) > 1 and out[-1] == 0.0:
        out.pop()
    return out if out else [0.0]


class FrictionConfig(StrictModel):
    """Drum friction in cable coordinates; breaks Assumption 1 on purpose (the paper warns)."""

    coulomb: NonNegativeFloat = 0.0  # N
    viscous: NonNegativeFloat = 0.0  # N s/m


class EncoderConfig(StrictModel):
    """What a drive reports: length sampled `latency_steps` plant steps ago, plus
    Gaussian noise, quantised to counts (None: ideal); velocity as the drive computes
    it, the difference of two such samples `velocity_window_steps` steps apart."""

    counts_per_metre: PositiveFloat | None = 1e5  # quantisation; null: none (ideal)
    noise_std: NonNegativeFloat = 0.0  # m
    latency_steps: Annotated[int, Field(ge=0, le=10_000)] = 0  # plant steps a report lags
    velocity_window_steps: Annotated[int, Field(ge=1, le=10_000)] = 2
    """Plant steps between the two length samples whose difference gives the rate."""


class PayloadConfig(StrictModel):
    """A point mass carried by the platform (kg, at `position`: m, platform frame from p)."""

    mass: PositiveFloat  # kg
    position: Vec3 = (0.0, 0.0, 0.0)  # m, platform frame, from p


class MismatchConfig(StrictModel):
    """How the simulated ("true") robot differs from the controller's model, the robot file.

    The truth is the file's robot with these errors applied (`apply`), not a second robot
    description: the errors are what calibration must find, every default is "as the
    file says" (so an unset mismatch simulates the file exactly), and the true robot is
    built and validated by cdpr like the file's.  Per cable lists run in cable order.

    anchor_offsets / attachment_offsets: m, added to each anchor (world frame) and each
    platform attachment (platform frame).  drum_radius_scale: true drum radius / the
    file's, one for all or one per cable (the drives turn torque into force and counts
    into length with the true radius).  encoder_offsets: m per drive, how far the length
    the daemon reads is off the true drum length (an incremental encoder, e.g. an ODrive,
    counts from wherever it powered up): the simulated drive's motor position zero lies
    that much further in; with a drum radius error the reading also scales about that
    zero.  payload: a point mass added to the platform.  The cable stiffness EA of the
    plant is `cable.stiffness` (the file's `cable_stiffness` is only the controller's
    belief).
    """

    mass_scale: PositiveFloat = 1.0  # true platform mass / the file's
    inertia_scale: PositiveFloat = 1.0  # true platform inertia / the file's
    center_of_mass_offset: Vec3 = (0.0, 0.0, 0.0)  # m, platform frame
    m0_scale: PositiveFloat = 1.0  # true m0 / the file's, every actuator
    k0_scale: NonNegativeFloat = 1.0  # true k0 / the file's, every actuator
    anchor_offsets: list[Vec3] | None = None  # m, one per cable, world frame
    anchor_error_std: NonNegativeFloat = 0.0  # m, random per anchor coordinate (seeded)
    attachment_offsets: list[Vec3] | None = None  # m, one per cable, platform frame
    drum_radius_scale: PositiveFloat | list[PositiveFloat] = 1.0
    """True drum radius / the file's: one for every cable, or one per cable."""
    encoder_offsets: list[FiniteFloat] | None = None  # m, one per drive
    payload: PayloadConfig | None = None  # a point mass added to the platform; null: none

    def apply(self, robot: Robot, rng: np.random.Generator) -> Robot:
        """The true robot: `robot`'s description with these errors, built by cdpr."""
        spec = robot.spec.model_dump(exclude_none=True)
        platform = spec["platform"]
        platform["mass"] *= self.mass_scale
        platform["inertia"] = (np.array(platform["inertia"]) * self.inertia_scale).tolist()
        platform["center_of_mass"] = (
            np.array(platform["center_of_mass"]) + self.center_of_mass_offset
        ).tolist()
        if self.payload is not None:
            _add_point_mass(platform, self.payload.mass, np.array(self.payload.position))
        for actuator in [spec["actuator"]] + [c["actuator"] for c in spec["cables"]]:
            if "m0" in actuator:
                actuator["m0"] *= self.m0_scale
            if "k0" in actuator:
                actuator["k0"] *= self.k0_scale
        n = robot.n_cables
        offsets = np.zeros((n, 3)) + self._per_cable("anchor_offsets", n, (0.0, 0.0, 0.0))
        if self.anchor_error_std > 0.0:
            offsets += rng.normal(0.0, self.anchor_error_std, (n, 3))
        moved = self._per_cable("attachment_offsets", n, (0.0, 0.0, 0.0))
        radius_scales = self._per_cable("drum_radius_scale", n, self.drum_radius_scale)
        for k, (cable, offset) in enumerate(zip(spec["cables"], offsets, strict=True)):
            cable["anchor"] = (np.array(cable["anchor"]) + offset).tolist()
            cable["attachment"] = (np.array(cable["attachment"]) + moved[k]).tolist()
            if radius_scales[k] != 1.0:
                cable["actuator"]["drum_radius"] = robot.actuators[k].drum_radius * radius_scales[k]
        return Robot.from_dict(spec, source=f"{robot.name} with plant mismatch")

    def encoder_offsets_for(self, n: int) -> list[float]:
        """encoder_offsets for n drives (zeros when unset); ConfigError on a wrong count."""
        return [float(x) for x in self._per_cable("encoder_offsets", n, 0.0)]

    def _per_cable(self, key: str, n: int, default: Any) -> list[Any]:
        """The list `key` (one entry per cable), or `default` for every cable when unset
        or a single value; ConfigError naming the key on a wrong count."""
        value = getattr(self, key)
        if not isinstance(value, list):
            return [default if value is None else value] * n
        if len(value) != n:
            raise ConfigError(f"mismatch.{key}: {len(value)} entries for {n} cables")
        return list(value)


def _add_point_mass(platform: dict[str, Any], mass: float, position: np.ndarray) -> None:
    """Add a point mass at `position` (platform frame) to the platform description (a
    dict as RobotSpec dumps it): mass, centre of mass and the inertia about it."""
    m, c = platform["mass"], np.array(platform["center_of_mass"])
    total = m + mass
    centre = (m * c + mass * position) / total
    inertia = np.array(platform["inertia"])
    for part, at in ((m, c - centre), (mass, position - centre)):
        inertia += part * (at.dot(at) * np.eye(3) - np.outer(at, at))
    platform.update(mass=total, center_of_mass=centre.tolist(), inertia=inertia.tolist())


class DisturbanceConfig(StrictModel):
    """External wrench (force, torque about p; world frame) acting for start <= t < end:
    constant with the defaults, a step with start > 0."""

    wrench: Wrench = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # N, N m: force, torque about p
    start: NonNegativeFloat = 0.0  # s of simulated time: when it begins
    end: Annotated[float, Field(gt=0.0)] = math.inf  # s of simulated time: when it ends


class PlantConfig(StrictModel):
    """The whole plant. `step` is the unit of Plant.step() and of the encoder history;
    it is integrated in `substeps` equal semi-implicit Euler substeps."""

    step: Annotated[float, Field(gt=0.0, le=0.1, allow_inf_nan=False)] = 1e-3
    """s: the plant step, the unit of the encoder's latency and velocity window."""
    substeps: Annotated[int, Field(ge=1, le=1000)] = 1  # semi-implicit Euler substeps per step
    seed: int = 0  # seeds the plant's random draws (anchor errors, encoder noise, force noise)
    cable: CableConfig = CableConfig()  # the cables' elasticity (below)
    actuator: ActuatorModelConfig = ActuatorModelConfig()  # the drives' force dynamics (below)
    friction: FrictionConfig = FrictionConfig()  # drum friction (below)
    encoder: EncoderConfig = EncoderConfig()  # what the drives report (below)
    mismatch: MismatchConfig = MismatchConfig()  # how the true robot differs from the file (below)
    disturbance: DisturbanceConfig = DisturbanceConfig()  # an external wrench (below)
    # relative standard deviation of the force a drive produces against its command,
    # drawn anew for every held command (drive current noise; `cdprd tune`'s noisy case)
    force_noise: Annotated[float, Field(ge=0.0, le=0.5)] = 0.0
    # the platform starts resting on a docking fixture, its cables slack (sim_bus.plant.fixture)
    fixture: FixtureConfig | None = None

    @property
    def substep(self) -> float:
        """The integration step h = step / substeps (s)."""
        return self.step / self.substeps


def parse_plant_config(data: Any, source: str = "plant") -> PlantConfig:
    """Validate a plain dict (e.g. from YAML); ConfigError names every bad key."""
    return validate_section(PlantConfig, data, source)
