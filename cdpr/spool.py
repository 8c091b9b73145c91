"""Spool buildup: a drum's radius grows as the cable winds on in layers.

A drum whose cable centre line lies at radius R on the first layer (the robot file's
drum_radius) winds N turns per layer (turns_per_layer, or drum_width / cable_diameter),
each layer one cable diameter d further out.  Continuous approximation: the radius grows
linearly with the wound angle φ, by d per N turns, centred so that the wound length w
equals the layered drum's at every completed layer:

    r(φ) = b + g φ / 2,   b = R - d / 2,   g = d / (π N)
    w(φ) = b φ + g φ² / 4,   hence   r(w)² = b² + g w   and   φ(w) = 2 (r(w) - b) / g.

Within a layer the wound length differs from the layered drum's by at most π N d / 4, the
radius by at most d / 2 (tests/cdpr/test_spool.py checks both against the exact layered
sum).  The wound length follows the cable length l the drum has paid out (m):
w = wound_at_zero - l.  An empty drum (w < 0, beyond what a file allows: wound_at_zero is
at least length_max) keeps the radius b, so that a wild reading still converts.
Unset, a drum has the constant radius R (drivers.base.Scaling).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cdpr.description import ActuatorSpec


@dataclass(frozen=True)
class Spool:
    """One drum's buildup: first-layer radius `radius` (m), `cable_diameter` (m),
    `turns_per_layer`, and `wound_at_zero`, the cable wound on (m) at cable length 0."""

    radius: float
    cable_diameter: float
    turns_per_layer: float
    wound_at_zero: float

    def __post_init__(self) -> None:
        for name in ("radius", "cable_diameter", "turns_per_layer", "wound_at_zero"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"spool {name} must be a positive finite number, not {value}")
        if self.cable_diameter >= 2.0 * self.radius:
            raise ValueError(
                f"spool cable_diameter ({self.cable_diameter} m) must be below twice the drum "
                f"radius ({self.radius} m)"
            )

    @property
    def bare(self) -> float:
        """b = R - d / 2: the continuous radius at an empty drum (m)."""
        return self.radius - 0.5 * self.cable_diameter

    @property
    def growth(self) -> float:
        """g = d / (π N): r² grows by g per metre wound (m)."""
        return self.cable_diameter / (math.pi * self.turns_per_layer)

    def radius_at(self, length: float) -> float:
        """The effective radius (m) at cable length `length` (m paid out)."""
        wound = self.wound_at_zero - length
        b = self.bare
        return math.sqrt(b * b + self.growth * wound) if wound > 0.0 else b

    def angle(self, length: float) -> float:
        """The wound angle φ (rad) at cable length `length`."""
        wound = self.wound_at_zero - length
        b = self.bare
        if wound <= 0.0:
            return wound / b
        return 2.0 * (math.sqrt(b * b + self.growth * wound) - b) / self.growth

    def length(self, angle: float) -> float:
        """The cable length (m) at wound angle `angle` (rad): the inverse of `angle`."""
        b = self.bare
        if angle <= 0.0:
            return self.wound_at_zero - b * angle
        return self.wound_at_zero - angle * (b + 0.25 * self.growth * angle)


def drum_spool(actuator: ActuatorSpec) -> Spool | None:
    """The Spool of a winch of the robot file (None: no spool: key, a constant radius)."""
    spec = actuator.spool
    if spec is None:
        return None
    return Spool(actuator.drum_radius, spec.cable_diameter, spec.turns, spec.wound_at_zero)
