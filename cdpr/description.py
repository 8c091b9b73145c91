"""Robot description: the YAML/dict schema, validated with errors that name the key.

pydantic does the validation (types, ranges, unknown keys) because it reports the
path of every bad key; the model code never sees an unvalidated value.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
Section = TypeVar("Section", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration problem; the message names the key path and the problem."""


class StrictModel(BaseModel):
    """Config sections: unknown keys are errors, values immutable once validated."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class QuaternionSpec(StrictModel):
    """Quaternion as an object with named keys (never a bare array at interfaces)."""

    w: FiniteFloat = 1.0
    x: FiniteFloat = 0.0
    y: FiniteFloat = 0.0
    z: FiniteFloat = 0.0

    @model_validator(mode="after")
    def _unit(self) -> QuaternionSpec:
        norm = math.sqrt(self.w**2 + self.x**2 + self.y**2 + self.z**2)
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"quaternion norm is {norm:.9g}; a unit quaternion is required")
        return self

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.w, self.x, self.y, self.z)


class PoseSpec(StrictModel):
    position: Vec3
    quaternion: QuaternionSpec = QuaternionSpec()


class PulleySpec(StrictModel):
    """Standard pulley model: the cable runs along `axis` into a pulley of `radius`
    that swivels about that axis through the anchor point, then leaves tangentially."""

    radius: PositiveFloat
    axis: Vec3 = (0.0, 0.0, 1.0)

    @field_validator("axis")
    @classmethod
    def _normalise_axis(cls, v: Vec3) -> Vec3:
        n = math.sqrt(sum(c * c for c in v))
        if n < 1e-9:
            raise ValueError("pulley axis must be a non-zero vector")
        return (v[0] / n, v[1] / n, v[2] / n)


class ActuatorOverrides(StrictModel):
    """Per-cable overrides of the actuator defaults (every field optional)."""

    m0: PositiveFloat | None = None
    k0: NonNegativeFloat | None = None
    drum_radius: PositiveFloat | None = None
    force_max: PositiveFloat | None = None
    length_min: NonNegativeFloat | None = None
    length_max: PositiveFloat | None = None
    t_min: NonNegativeFloat | None = None
    cable_stiffness: PositiveFloat | None = None


class ActuatorSpec(StrictModel):
    """One winch in cable-length coordinates.

    m0: effective no-load mass (drum + gear + rotor inertia / r^2), kg.
    k0: back-EMF / viscous coefficient, N s/m.  force_max: |command force| limit, N.
    t_min: minimum cable tension kept by the tension distribution, N.
    cable_stiffness: EA of the cable (N per unit strain) for the stretch correction of
    the encoder lengths, l_geometric = l_drum (1 + t / EA); None: inextensible.
    """

    m0: PositiveFloat
    k0: NonNegativeFloat
    drum_radius: PositiveFloat
    force_max: PositiveFloat
    length_min: NonNegativeFloat
    length_max: PositiveFloat
    t_min: NonNegativeFloat
    cable_stiffness: PositiveFloat | None = None

    @model_validator(mode="after")
    def _ranges(self) -> ActuatorSpec:
        if self.length_min >= self.length_max:
            raise ValueError(
                f"length_min ({self.length_min}) must be below length_max ({self.length_max})"
            )
        if self.t_min >= self.force_max:
            raise ValueError(f"t_min ({self.t_min}) must be below force_max ({self.force_max})")
        return self


class CableSpec(StrictModel):
    anchor: Vec3
    attachment: Vec3
    pulley: PulleySpec | None = None
    actuator: ActuatorOverrides = ActuatorOverrides()


class PlatformSpec(StrictModel):
    """Rigid platform: mass (kg), centre of mass from p in the platform frame (m), and the
    3x3 inertia about the centre of mass in the platform frame (kg m^2)."""

    mass: PositiveFloat
    center_of_mass: Vec3 = (0.0, 0.0, 0.0)
    inertia: tuple[Vec3, Vec3, Vec3]

    @field_validator("inertia")
    @classmethod
    def _spd(cls, v: tuple[Vec3, Vec3, Vec3]) -> tuple[Vec3, Vec3, Vec3]:
        inertia = np.array(v, dtype=float)
        if not np.allclose(inertia, inertia.T, rtol=0.0, atol=1e-12 * max(1.0, abs(inertia).max())):
            raise ValueError("inertia must be a symmetric 3x3 matrix")
        eig = np.linalg.eigvalsh(inertia)
        if eig[0] <= 0.0:
            raise ValueError(f"inertia must be positive definite (eigenvalues {eig.tolist()})")
        if eig[0] + eig[1] < eig[2] * (1 - 1e-9):
            raise ValueError(
                f"inertia violates the triangle inequality (eigenvalues {eig.tolist()})"
            )
        return v


class ForwardKinematicsSpec(StrictModel):
    """Gauss-Newton / Levenberg-Marquardt settings for Y(l)."""

    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 50
    step_tolerance: PositiveFloat = 1e-8
    max_residual: PositiveFloat = 2e-3


class RobotSpec(StrictModel):
    name: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")]
    gravity: Vec3 = (0.0, 0.0, -9.81)
    platform: PlatformSpec
    actuator: ActuatorSpec
    cables: Annotated[list[CableSpec], Field(min_length=6, max_length=64)]
    home: PoseSpec
    forward_kinematics: ForwardKinematicsSpec = ForwardKinematicsSpec()

    @model_validator(mode="before")
    @classmethod
    def _merge_actuator_overrides(cls, data: Any) -> Any:
        """Check each cable's merged actuator (defaults + overrides) is itself valid."""
        if not isinstance(data, dict):
            return data
        defaults = data.get("actuator")
        cables = data.get("cables")
        if isinstance(defaults, dict) and isinstance(cables, list):
            for i, cable in enumerate(cables):
                if isinstance(cable, dict) and isinstance(cable.get("actuator"), dict):
                    overrides = {k: v for k, v in cable["actuator"].items() if v is not None}
                    merged = {**defaults, **overrides}
                    try:
                        ActuatorSpec.model_validate(merged)
                    except ValidationError as exc:
                        raise ValueError(
                            f"cables.{i}.actuator (merged with defaults): {_first_message(exc)}"
                        ) from None
        return data

    def actuator_of(self, index: int) -> ActuatorSpec:
        """The actuator parameters of cable `index` (defaults with its overrides)."""
        overrides = self.cables[index].actuator.model_dump(exclude_none=True)
        return self.actuator.model_copy(update=overrides)


def _first_message(exc: ValidationError) -> str:
    return format_validation_error(exc).splitlines()[0]


def format_validation_error(exc: ValidationError, root: str = "") -> str:
    """One line per problem: 'key.path: message (got value)'."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"])
        key = ".".join(p for p in (root, loc) if p)
        msg = err["msg"].removeprefix("Value error, ")
        got = err.get("input")
        shown = "" if isinstance(got, dict | list) or got is None else f" (got {got!r})"
        lines.append(f"{key}: {msg}{shown}" if key else f"{msg}{shown}")
    return "\n".join(lines)


def validate_section(model: type[Section], data: Any, source: str) -> Section:
    """Validate a plain dict (from YAML or JSON) as `model`; ConfigError names every bad key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source} is invalid:\n{format_validation_error(exc)}") from None


def parse_robot(data: Any, source: str = "robot") -> RobotSpec:
    """Validate a robot description; raises ConfigError naming every bad key."""
    return validate_section(RobotSpec, data, source)


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file; ConfigError (naming the file and line) when it does not parse."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
