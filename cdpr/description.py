"""Robot description: the YAML/dict schema, validated with errors that name the key.

pydantic does the validation (types, ranges, unknown keys) because it reports the
path of every bad key; the model code never sees an unvalidated value.  Validation is
strict (validate_section): a number must be a number (an integer will do for a float,
a boolean never), a string a string, a flag true or false; nothing is converted.
"""

from __future__ import annotations

import json
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

from cdpr import strict_yaml
from cdpr.trusted_file import UnreadableFileError, read_trusted, show_path

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
Section = TypeVar("Section", bound=BaseModel)


CONFIG_MAX_BYTES = 1 << 20  # a config or robot file larger than this is refused unread
AXIS_TOLERANCE = 1e-6  # |norm - 1| of a pulley axis that is normalised rather than refused
DEFAULT_CABLE_DIAMETER = 0.004  # m: a cable whose robot file gives none (Dyneema 3-4 mm)


class ConfigError(ValueError):
    """A configuration problem: one line per problem, 'WHERE: KEY: problem', where WHERE
    is the file (or the source of the data) and KEY the key path."""

    def within(self, where: str) -> ConfigError:
        """The same problems, each line prefixed with `where` (the file or key they are in)."""
        return ConfigError("\n".join(f"{where}: {line}" for line in str(self).splitlines()))


class StrictModel(BaseModel):
    """Config sections: unknown keys are errors, values immutable once validated.
    Validate input with validate_section, which is strict (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class QuaternionSpec(StrictModel):
    """Quaternion as an object with named keys (never a bare array at interfaces)."""

    w: FiniteFloat = 1.0  # scalar part of the unit quaternion (w, x, y, z)
    x: FiniteFloat = 0.0  # x component of the vector part
    y: FiniteFloat = 0.0  # y component of the vector part
    z: FiniteFloat = 0.0  # z component of the vector part

    @model_validator(mode="after")
    def _unit(self) -> QuaternionSpec:
        norm = math.hypot(self.w, self.x, self.y, self.z)  # no overflow for huge parts
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"quaternion norm is {norm:.9g}; a unit quaternion is required")
        return self

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.w, self.x, self.y, self.z)


class PoseSpec(StrictModel):
    position: Vec3  # m, world frame: where the platform's reference point p is
    quaternion: QuaternionSpec = QuaternionSpec()  # orientation: platform frame to world frame


class PulleySpec(StrictModel):
    """Standard pulley model: the cable runs along `axis` into a pulley of `radius`
    that swivels about that axis through the anchor point, then leaves tangentially.
    `axis` is a unit vector: normalised within AXIS_TOLERANCE, refused beyond it (as a
    quaternion is), so that the file holds the direction that is used."""

    radius: PositiveFloat  # m, the pulley's radius
    axis: Vec3 = (0.0, 0.0, 1.0)  # unit vector, world frame: the swivel axis through the anchor

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, v: Vec3) -> Vec3:
        n = math.hypot(*v)
        if not abs(n - 1.0) <= AXIS_TOLERANCE:
            raise ValueError(f"pulley axis must be a unit vector; its norm is {n:.9g}")
        return (v[0] / n, v[1] / n, v[2] / n)


class SpoolSpec(StrictModel):
    """Spool buildup of a drum (cdpr.spool): the radius grows by a cable diameter per
    layer.  cable_diameter (m); turns_per_layer, or drum_width (m) for drum_width /
    cable_diameter turns (one of the two); wound_at_zero: the cable wound on the drum (m)
    at cable length 0, so wound_at_zero - l at length l (at least length_max: the drum
    never runs empty)."""

    cable_diameter: PositiveFloat  # m; each layer adds it to the radius
    turns_per_layer: PositiveFloat | None = None
    """Turns of cable per layer; null: drum_width / cable_diameter (give one of the two)."""
    drum_width: PositiveFloat | None = None
    """m, for drum_width / cable_diameter turns per layer; null: turns_per_layer is given."""
    wound_at_zero: PositiveFloat  # m of cable on the drum at cable length 0 (>= length_max)

    @model_validator(mode="after")
    def _one_width(self) -> SpoolSpec:
        if (self.turns_per_layer is None) == (self.drum_width is None):
            raise ValueError("give either turns_per_layer or drum_width (one of them)")
        if self.drum_width is not None and self.drum_width < self.cable_diameter:
            raise ValueError(
                f"drum_width ({self.drum_width} m) is narrower than the cable_diameter "
                f"({self.cable_diameter} m)"
            )
        return self

    @property
    def turns(self) -> float:
        """Turns per layer."""
        if self.turns_per_layer is not None:
            return self.turns_per_layer
        assert self.drum_width is not None
        return self.drum_width / self.cable_diameter


class ActuatorOverrides(StrictModel):
    """Per-cable overrides of the actuator defaults (every field optional)."""

    m0: PositiveFloat | None = None  # kg, this cable's m0; null: actuator.m0
    k0: NonNegativeFloat | None = None  # N s/m, this cable's k0; null: actuator.k0
    drum_radius: PositiveFloat | None = None  # m, this cable's; null: actuator.drum_radius
    force_max: PositiveFloat | None = None  # N, this cable's; null: actuator.force_max
    length_min: NonNegativeFloat | None = None  # m, this cable's; null: actuator.length_min
    length_max: PositiveFloat | None = None  # m, this cable's; null: actuator.length_max
    t_min: NonNegativeFloat | None = None  # N, this cable's; null: actuator.t_min
    cable_stiffness: PositiveFloat | None = None  # N, this cable's EA; null: actuator's
    cable_damping: NonNegativeFloat | None = None  # N s, this cable's; null: actuator's
    friction: NonNegativeFloat | None = None  # N, this winch's; null: actuator's
    cable_diameter: PositiveFloat | None = None  # m, this cable's; null: actuator's
    spool: SpoolSpec | None = None  # this cable's drum buildup; null: actuator.spool


class ActuatorSpec(StrictModel):
    """One winch in cable-length coordinates.

    m0: effective no-load mass (drum + gear + rotor inertia / r^2), kg.
    k0: back-EMF / viscous coefficient, N s/m.
    drum_radius: the drum's radius (m; with a spool, the first layer's, to the cable's
      centre line): the drives' torque and position convert to cable force and length by it.
    force_max: |command force| limit, N.
    length_min / length_max: the range (m) a cable's measured length must keep (outside
      it the daemon brakes); trajectories are validated inside it, less margins.
    t_min: minimum cable tension kept by the tension distribution, N.
    cable_stiffness: EA of the cable (N per unit strain) for the stretch correction of
      the encoder lengths, l_geometric = l_drum (1 + t / EA); None: inextensible.
    cable_damping: the cable's internal damping D (N s per unit strain rate: t = EA e +
      D e'), so its strain follows the tension with the lag D / EA (100 on EA 1e5: 1 ms);
      the payload estimate takes the stretch through it.  None: no lag.  Needs
      cable_stiffness.
    friction: the winch's Coulomb friction in cable coordinates (N, against the drum's
      motion; `cdprd tune` identifies it): the controller adds it along the reference's
      cable rates (cdpr.friction).  None: none.
    cable_diameter: the cable's diameter (m): two cables closer than the mean of their
      diameters interfere (cdpr.interference); None: the spool's, else 4 mm.
    spool: the drum's radius growing with the cable wound on (SpoolSpec); None: constant.
    """

    m0: PositiveFloat
    k0: NonNegativeFloat
    drum_radius: PositiveFloat
    force_max: PositiveFloat
    length_min: NonNegativeFloat
    length_max: PositiveFloat
    t_min: NonNegativeFloat
    cable_stiffness: PositiveFloat | None = None
    cable_damping: NonNegativeFloat | None = None
    friction: NonNegativeFloat | None = None
    cable_diameter: PositiveFloat | None = None
    spool: SpoolSpec | None = None

    @property
    def diameter(self) -> float:
        """The cable's diameter (m): its own, the spool's, else DEFAULT_CABLE_DIAMETER."""
        if self.cable_diameter is not None:
            return self.cable_diameter
        return DEFAULT_CABLE_DIAMETER if self.spool is None else self.spool.cable_diameter

    @model_validator(mode="after")
    def _ranges(self) -> ActuatorSpec:
        if self.length_min >= self.length_max:
            raise ValueError(
                f"length_min ({self.length_min}) must be below length_max ({self.length_max})"
            )
        if self.t_min >= self.force_max:
            raise ValueError(f"t_min ({self.t_min}) must be below force_max ({self.force_max})")
        if self.cable_damping is not None and self.cable_stiffness is None:
            raise ValueError(
                f"cable_damping ({self.cable_damping} N s) needs cable_stiffness: an "
                "inextensible cable has no strain to damp"
            )
        spool = self.spool
        if spool is not None and spool.wound_at_zero < self.length_max:
            raise ValueError(
                f"spool.wound_at_zero ({spool.wound_at_zero} m) must be at least length_max "
                f"({self.length_max} m): the drum would run empty"
            )
        if spool is not None and spool.cable_diameter >= 2.0 * self.drum_radius:
            raise ValueError(
                f"spool.cable_diameter ({spool.cable_diameter} m) must be below twice the "
                f"drum_radius ({self.drum_radius} m)"
            )
        return self


class CableSpec(StrictModel):
    anchor: Vec3  # m, world frame: where the cable leaves the frame (with a pulley: on its axis)
    attachment: Vec3  # m, platform frame, from p: where the cable meets the platform
    pulley: PulleySpec | None = None  # a pulley at the anchor (below); null: a point anchor
    actuator: ActuatorOverrides = ActuatorOverrides()  # overrides of the actuator defaults (below)


def check_box(low: Vec3, high: Vec3) -> None:
    """ValueError unless `low` lies below `high` on every axis (a box's min and max)."""
    if not all(lo < hi for lo, hi in zip(low, high, strict=True)):
        raise ValueError(f"min {list(low)} must lie below max {list(high)}")


class BodyBoxSpec(StrictModel):
    """A box in the platform frame (m): its lowest and highest corner."""

    min: Vec3  # m, platform frame: the lowest corner
    max: Vec3  # m, platform frame: the highest corner

    @model_validator(mode="after")
    def _ordered(self) -> BodyBoxSpec:
        check_box(self.min, self.max)
        return self

    def corners(self) -> list[Vec3]:
        return [
            (x, y, z)
            for x in (self.min[0], self.max[0])
            for y in (self.min[1], self.max[1])
            for z in (self.min[2], self.max[2])
        ]


class BodySpec(StrictModel):
    """The platform's bounding geometry (cdpr.body): a `box`, or the `vertices` of its
    convex hull (platform frame, m), one of the two.  The cables' attachment points
    belong to the body as well."""

    box: BodyBoxSpec | None = None  # a box (below); null: give vertices
    vertices: Annotated[list[Vec3], Field(min_length=1, max_length=256)] | None = None
    """Points (m, platform frame) whose convex hull is the body; null: give box."""

    @model_validator(mode="after")
    def _one_shape(self) -> BodySpec:
        if (self.box is None) == (self.vertices is None):
            raise ValueError("give either box or vertices (one of them)")
        return self

    def corners(self) -> list[Vec3]:
        return self.box.corners() if self.box is not None else list(self.vertices or ())


class PlatformSpec(StrictModel):
    """Rigid platform: mass (kg), centre of mass from p in the platform frame (m), the
    3x3 inertia about the centre of mass in the platform frame (kg m^2), and its `body`
    (BodySpec; default: the convex hull of the cables' attachment points), which the
    pose limits keep inside the workspace and clear of the environment."""

    mass: PositiveFloat  # kg
    center_of_mass: Vec3 = (0.0, 0.0, 0.0)  # m, platform frame, from the reference point p
    inertia: tuple[Vec3, Vec3, Vec3]  # kg m^2, 3x3 about the centre of mass, platform frame
    body: BodySpec | None = None  # its geometry (below); null: the attachments' convex hull

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

    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 50  # iterations before it fails
    step_tolerance: PositiveFloat = 1e-8  # m or rad: a shorter Gauss-Newton step ends it
    max_residual: PositiveFloat = 2e-3  # m: an RMS length error above it fails (no rigid pose)


class RobotSpec(StrictModel):
    name: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")]
    """The robot's name; the zenoh key prefix defaults to cdpr/<name>."""
    gravity: Vec3 = (0.0, 0.0, -9.81)  # m/s^2, world frame: the gravitational acceleration
    platform: PlatformSpec  # the platform's mass properties and body (below)
    actuator: ActuatorSpec  # every cable's winch parameters (below); a cable may override them
    cables: Annotated[list[CableSpec], Field(min_length=6, max_length=64)]
    """The cables (6 to 64), in cable order: the order of the drives' lists."""
    home: PoseSpec
    """The platform's resting pose (a docking fixture): where `cdprd home` and pretension
    work by default, the orientation safety.tilt_max is measured from, and the first guess
    of forward kinematics."""
    forward_kinematics: ForwardKinematicsSpec = ForwardKinematicsSpec()
    """Settings of the solver that finds the pose from the cable lengths (below)."""
    # named resting poses (docking fixtures) for `cdprd home --pose NAME`; "home" is `home`
    poses: dict[Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-]{1,64}$")], PoseSpec] = {}

    @model_validator(mode="after")
    def _merged_actuators_valid(self) -> RobotSpec:
        """Check each cable's merged actuator (defaults + overrides) is itself valid."""
        defaults = self.actuator.model_dump()
        for i, cable in enumerate(self.cables):
            overrides = cable.actuator.model_dump(exclude_none=True)
            if overrides:
                try:
                    ActuatorSpec.model_validate({**defaults, **overrides})
                except ValidationError as exc:
                    raise ValueError(
                        f"cables.{i}.actuator (merged with defaults): {_first_message(exc)}"
                    ) from None
        return self

    @model_validator(mode="after")
    def _home_not_renamed(self) -> RobotSpec:
        if "home" in self.poses:
            raise ValueError("poses.home: 'home' names the home pose (the home: key)")
        return self

    def actuator_of(self, index: int) -> ActuatorSpec:
        """The actuator parameters of cable `index` (defaults with its overrides)."""
        overrides = {k: v for k, v in self.cables[index].actuator if v is not None}
        return self.actuator.model_copy(update=overrides)


def _first_message(exc: ValidationError) -> str:
    return format_validation_error(exc).splitlines()[0]


# pydantic adds the member of a union that failed to the key path ("float", "list[...]",
# "function-after[...]"): noise to an operator, so such parts are left out of KEY
_UNION_MEMBERS = frozenset({"bool", "int", "float", "str", "none", "list", "dict", "tuple"})
_SHOULD = "Input should be "


def format_validation_error(exc: ValidationError, source: str = "", key: str = "") -> str:
    """One line per problem: 'SOURCE: KEY.PATH: message (got value)'; the members of a
    union that all failed on one key share a line ('a valid number, or a valid array')."""
    problems: list[list[str]] = []  # [path, message, shown value]
    for err in exc.errors():
        loc = [str(p) for p in err["loc"] if not _union_member(p)]
        path = ".".join(p for p in (key, *loc) if p)
        msg = " ".join(err["msg"].removeprefix("Value error, ").split())
        got = err.get("input")
        shown = "" if isinstance(got, dict | list) else f" (got {_show_value(got)})"
        last = problems[-1] if problems else ["", "", ""]
        if (last[0], last[2]) != (path, shown):
            problems.append([path, msg, shown])
        elif last[1].startswith(_SHOULD) and msg.startswith(_SHOULD):
            alternative = msg.removeprefix(_SHOULD)
            if alternative not in last[1]:
                last[1] += f", or {alternative}"
        elif msg != last[1]:
            problems.append([path, msg, shown])
    lines = [[source, path, msg + shown] for path, msg, shown in problems]
    return "\n".join(": ".join(part for part in line if part) for line in lines)


def _union_member(part: int | str) -> bool:
    return isinstance(part, str) and (
        "[" in part or part in _UNION_MEMBERS or part.startswith("constrained-")
    )


def _show_value(value: Any) -> str:
    """A value as the file spells it: null, true, false, a number, a quoted string."""
    if value is None or isinstance(value, bool):
        return json.dumps(value)
    return _clip(value)


def _clip(value: Any, limit: int = 80) -> str:
    """repr(value), shortened to about `limit` characters (a value may be a whole file)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 5]}...{text[-1]}"


def validate_section(model: type[Section], data: Any, source: str, key: str = "") -> Section:
    """Validate plain data (from YAML or JSON) as `model`, strictly: pydantic's strict
    JSON mode, where a list may fill a tuple and a string an enum, an integer a float,
    and nothing else converts.  ConfigError names every bad key: `source` is the file (or
    what the data came from), `key` the path of the section in it."""
    where = ": ".join(p for p in (source, key) if p)
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {_type_name(data)}")
    try:
        text = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: not plain data: {exc}") from None
    try:
        return model.model_validate_json(text, strict=True)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, key)) from None


def _type_name(value: Any) -> str:
    return "null" if value is None else type(value).__name__


def parse_robot(data: Any, source: str = "robot", key: str = "") -> RobotSpec:
    """Validate a robot description; raises ConfigError naming every bad key."""
    return validate_section(RobotSpec, data, source, key)


def load_yaml(path: str | Path, max_bytes: int = CONFIG_MAX_BYTES) -> Any:
    """Read a YAML file (strict_yaml: YAML 1.2 core types, bounded) of at most
    `max_bytes`; ConfigError naming the file, and the line where there is one."""
    path = Path(path)
    text = read_text(path, max_bytes)
    try:
        return strict_yaml.parse(text, max_nodes=max_bytes // 2)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{show_path(path)}: {strict_yaml.describe(exc)}") from None


def read_text(path: Path, max_bytes: int) -> str:
    """The UTF-8 text of the regular file at `path`, at most `max_bytes` long, read
    without blocking (cdpr.trusted_file); ConfigError otherwise (a directory, a device
    such as /dev/zero, a FIFO, too long, not UTF-8)."""
    try:
        data = read_trusted(path, max_bytes)
    except UnreadableFileError as exc:
        raise ConfigError(str(exc)) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{show_path(path)}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x} "
            f"at offset {exc.start})"
        ) from None
