"""Pose limits: a box for the platform reference point and a largest rotation from home.

One implementation for both uses (DESIGN §9, §7): the daemon's runtime check brakes when
the MEASURED pose leaves them, and trajectory validation keeps every sampled REFERENCE
inside the same limits shrunk by a margin (`shrunk`), so that an accepted trajectory,
followed within the tracking-error bounds, never trips the runtime check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

from cdpr.pose import Pose

ROUNDING = 1e-9  # m or rad kept in addition to any margin: rounding of the checks themselves


class PoseViolation(NamedTuple):
    """Which limit a pose breaks: `limit` is "workspace_min", "workspace_max" or
    "tilt_max" (the config key), `value` the coordinate (m) or the rotation angle (rad),
    `detail` one readable line with the value and the bound."""

    limit: str
    value: float
    detail: str


def tilt(pose: Pose, home: tuple[float, float, float, float]) -> float:
    """The rotation angle (rad, in [0, π]) between the pose's orientation and `home`
    (a unit quaternion w, x, y, z): 2 acos |<q, q_home>|."""
    w, x, y, z = pose.quaternion_tuple
    hw, hx, hy, hz = home
    return 2.0 * math.acos(min(1.0, abs(w * hw + x * hx + y * hy + z * hz)))


@dataclass(frozen=True)
class PoseLimits:
    """lower <= position <= upper per axis (m, world frame) and tilt from `home` <=
    tilt_max (rad).  `margin` (m, rad) says how far inside the configured limits these
    are, for the messages."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    home: tuple[float, float, float, float]
    tilt_max: float
    margin: tuple[float, float] = (0.0, 0.0)

    def violation(self, pose: Pose) -> PoseViolation | None:
        """The first limit `pose` breaks (the box, axis by axis, then the tilt), else None."""
        for axis, (p, lo, hi) in enumerate(
            zip(pose.position_tuple, self.lower, self.upper, strict=True)
        ):
            if not lo <= p <= hi:
                side = "workspace_min" if not lo <= p else "workspace_max"
                detail = f"position {'xyz'[axis]} = {p:.4f} m outside [{lo:.4f}, {hi:.4f}] m"
                return PoseViolation(side, p, detail + self._within(0, "m"))
        angle = tilt(pose, self.home)
        if not angle <= self.tilt_max:
            detail = (
                f"rotation {math.degrees(angle):.2f} deg from home exceeds "
                f"{math.degrees(self.tilt_max):.2f} deg"
            )
            return PoseViolation("tilt_max", angle, detail + self._within(1, "rad"))
        return None

    def _within(self, which: int, unit: str) -> str:
        margin = self.margin[which]
        return f" (the configured limit less a margin of {margin:.4g} {unit})" if margin else ""

    def shrunk(self, position: float, orientation: float) -> PoseLimits:
        """These limits moved inwards by `position` (m, every face of the box) and
        `orientation` (rad, off tilt_max), plus ROUNDING.  A pose within `position` and
        `orientation` of one inside the result is inside these limits (box: per axis;
        tilt: the triangle inequality of the rotation angle).  The result may be empty
        (lower > upper or tilt_max < 0): check that a known pose lies inside it."""
        dp, dr = position + ROUNDING, orientation + ROUNDING
        return PoseLimits(
            (self.lower[0] + dp, self.lower[1] + dp, self.lower[2] + dp),
            (self.upper[0] - dp, self.upper[1] - dp, self.upper[2] - dp),
            self.home,
            self.tilt_max - dr,
            (self.margin[0] + dp, self.margin[1] + dr),
        )

    def widened_to(self, pose: Pose) -> PoseLimits:
        """The smallest limits holding both these and `pose`: for a transition from the
        current reference, which may not go further out than where it starts (enabled
        next to a wall, say) but must not be refused for starting there."""
        p = pose.position_tuple
        return replace(
            self,
            lower=(min(self.lower[0], p[0]), min(self.lower[1], p[1]), min(self.lower[2], p[2])),
            upper=(max(self.upper[0], p[0]), max(self.upper[1], p[1]), max(self.upper[2], p[2])),
            tilt_max=max(self.tilt_max, tilt(pose, self.home)),
        )
