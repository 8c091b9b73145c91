"""The `environment:` config section: what the platform's body and the cables must not
cross (DESIGN §18, cdpr.body), beyond the workspace box.

    environment:
      planes:   # the free side is the one `normal` points to
        - {name: floor, point: [0.0, 0.0, 0.0], normal: [0.0, 0.0, 1.0]}
      boxes:    # axis-aligned obstacles, world frame
        - {name: table, min: [0.6, -0.4, 0.0], max: [1.4, 0.4, 0.75]}

Every anchor must lie on the free side of every plane (a cable runs from it) and
outside every box; the home pose is checked with everything else (check_geometry).
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from cdpr import ConfigError, Robot
from cdpr.body import Box, Environment, Plane
from cdpr.description import StrictModel, Vec3, check_box

Name = Annotated[str, Field(min_length=1, max_length=64)]
ON_PLANE = 1e-9  # m: an anchor this far behind a plane is on it (a floor-mounted winch)


class PlaneSpec(StrictModel):
    """A plane through `point` (m) whose free side is the one `normal` points to."""

    name: Name | None = None  # what messages call it; null: "plane <index>"
    point: Vec3  # m, world frame: a point on the plane
    normal: Vec3  # points to the free side (normalised when loaded)

    @field_validator("normal")
    @classmethod
    def _direction(cls, v: Vec3) -> Vec3:
        n = math.hypot(*v)
        if not n > 1e-9:
            raise ValueError("normal must be a non-zero vector")
        return (v[0] / n, v[1] / n, v[2] / n)


class BoxSpec(StrictModel):
    """An axis-aligned obstacle from `min` to `max` (m, world frame)."""

    name: Name | None = None  # what messages call it; null: "box <index>"
    min: Vec3  # m, world frame: the lowest corner
    max: Vec3  # m, world frame: the highest corner

    @model_validator(mode="after")
    def _ordered(self) -> BoxSpec:
        check_box(self.min, self.max)
        return self


class EnvironmentConfig(StrictModel):
    """The `environment:` section (every key optional)."""

    planes: tuple[PlaneSpec, ...] = Field((), max_length=32)  # floors and walls (below)
    boxes: tuple[BoxSpec, ...] = Field((), max_length=32)  # axis-aligned obstacles (below)


def environment_of(robot: Robot, section: EnvironmentConfig) -> Environment:
    """The environment (cdpr.body) of `section` with the robot's anchors; ConfigError
    ("environment.KEY: problem") if an anchor lies behind a plane or inside a box."""
    anchors = robot.geometry.anchors
    planes = []
    for i, spec in enumerate(section.planes):
        name = spec.name or f"plane {i}"
        offset = float(np.dot(spec.normal, spec.point))
        plane = Plane(name, spec.normal, offset)
        behind = anchors.dot(spec.normal) - offset
        if np.any(behind < -ON_PLANE):
            k = int(np.argmin(behind))
            raise ConfigError(
                f"environment.planes.{i}: cable {k}'s anchor {anchors[k].tolist()} lies "
                f"{-behind[k]:.4g} m behind plane '{name}': its cable would cross it"
            )
        planes.append(plane)
    boxes = []
    for i, spec in enumerate(section.boxes):
        box = Box(spec.name or f"box {i}", spec.min, spec.max)
        inside = np.all((anchors >= box.lower) & (anchors <= box.upper), axis=1)
        if np.any(inside):
            k = int(np.argmax(inside))
            raise ConfigError(
                f"environment.boxes.{i}: cable {k}'s anchor {anchors[k].tolist()} lies inside "
                f"box '{box.name}'"
            )
        boxes.append(box)
    as_tuples = tuple((float(x), float(y), float(z)) for x, y, z in anchors.tolist())
    return Environment(tuple(planes), tuple(boxes), as_tuples)
