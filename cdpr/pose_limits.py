"""Pose limits: a box for the platform reference point and for every corner of its body,
a largest rotation from home, and the environment the body and the cables must not cross.

One implementation for both uses (DESIGN §9, §7, §18): the daemon's runtime check brakes
when the MEASURED pose leaves them, and trajectory validation keeps every sampled
REFERENCE inside the same limits shrunk by a margin (`shrunk`), so that an accepted
trajectory, followed within the tracking-error bounds, never trips the runtime check.
The body and the environment are cdpr.body's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cdpr.body import Environment, PlatformBody, crossed
from cdpr.pose import Pose

BoolArray = NDArray[np.bool_]

ROUNDING = 1e-9  # m or rad kept in addition to any margin: rounding of the checks themselves
# how far inside each bound a batch screen (`clear`) wants a sample, in m, rad or relative
# to the bound: batch arithmetic rounds differently from the scalar check, by ~1e-15
SCREEN_MARGIN = 1e-9


class PoseViolation(NamedTuple):
    """Which limit a pose breaks: `limit` is "workspace_min", "workspace_max" or
    "tilt_max" (the config key), or "environment" (a plane or box of the config crossed);
    `value` the coordinate (m), the rotation angle (rad) or a corner's distance from a
    plane (m), `detail` one readable line with the part, the value and the bound."""

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
    tilt_max (rad); with a `body`, every corner of it inside the same box, `turn` x its
    distance from the reference point further in, and clear of the `environment` (its
    obstacles grown by margin[0], plus `turn` x that distance: cdpr.body).  `margin` (m,
    rad) says how far inside the configured limits these are, for the messages."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    home: tuple[float, float, float, float]
    tilt_max: float
    margin: tuple[float, float] = (0.0, 0.0)
    body: PlatformBody | None = None
    environment: Environment = field(default_factory=Environment)
    turn: float = 0.0

    def violation(self, pose: Pose) -> PoseViolation | None:
        """The first limit `pose` breaks (the box, axis by axis, then the tilt, then the
        body's corners in the box, then the environment), else None."""
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
        body = self.body
        if body is None:
            return None
        # every corner lies within reach of p: only near a face need they be placed
        reach = body.reach * (1.0 + self.turn)
        px, py, pz = pose.position_tuple
        (lx, ly, lz), (hx, hy, hz) = self.lower, self.upper
        inside = (
            lx + reach <= px <= hx - reach
            and ly + reach <= py <= hy - reach
            and lz + reach <= pz <= hz - reach
        )
        if self.environment.empty or not self.environment.near(
            pose.position_tuple, self.margin[0] + reach
        ):
            return None if inside else self._body_violation(pose, body, False)
        return self._body_violation(pose, body, True)

    def clear(self, positions: NDArray[np.float64], quaternions: NDArray[np.float64]) -> BoolArray:
        """Which poses (positions N x 3, unit quaternions N x 4) certainly pass
        `violation`, by its own quick tests (the reference point, or every corner the
        body's reach allows, inside the box; the tilt), SCREEN_MARGIN m or rad inside
        each bound.  False means only that `violation` must decide (near a face, near an
        obstacle)."""
        reach = 0.0 if self.body is None else self.body.reach * (1.0 + self.turn)
        inside = np.all(
            (positions >= np.add(self.lower, reach + SCREEN_MARGIN))
            & (positions <= np.subtract(self.upper, reach + SCREEN_MARGIN)),
            axis=1,
        )
        cosine = np.minimum(1.0, np.abs(quaternions @ np.asarray(self.home, dtype=float)))
        inside &= 2.0 * np.arccos(cosine) <= self.tilt_max - SCREEN_MARGIN
        if self.body is not None and not self.environment.empty:
            near = self.environment.near
            for i in np.flatnonzero(inside).tolist():
                inside[i] = not near(positions[i].tolist(), self.margin[0] + reach)
        return inside

    def _body_violation(
        self, pose: Pose, body: PlatformBody, environment: bool
    ) -> PoseViolation | None:
        corners = body.placed(pose)  # scalar: the common case is a few corners near a face
        turn = self.turn
        for k, (point, radius) in enumerate(zip(corners, body.radius_list, strict=True)):
            for axis in range(3):
                v = point[axis]
                lo, hi = self.lower[axis] + turn * radius, self.upper[axis] - turn * radius
                if not lo <= v <= hi:
                    side = "workspace_min" if not lo <= v else "workspace_max"
                    detail = (
                        f"{body.name(k)} at {'xyz'[axis]} = {v:.4f} m outside "
                        f"[{lo:.4f}, {hi:.4f}] m"
                    )
                    return PoseViolation(side, v, detail + self._within(0, "m", body))
        if not environment:
            return None
        hit = crossed(body, self.environment, pose, corners, self.margin[0], turn)
        if hit is None:
            return None
        return PoseViolation("environment", hit.value, hit.detail + self._within(0, "m", body))

    def _within(self, which: int, unit: str, body: PlatformBody | None = None) -> str:
        margin = self.margin[which]
        turn = ""
        if body is not None and self.turn:
            turn = f" + {self.turn:.4g} rad x the corner's distance from p"
        return (
            f" (the configured limit less a margin of {margin:.4g} {unit}{turn})" if margin else ""
        )

    def shrunk(self, position: float, orientation: float, turn: float | None = None) -> PoseLimits:
        """These limits moved inwards by `position` (m, every face of the box, every
        obstacle grown by it) and `orientation` (rad, off tilt_max), plus ROUNDING; the
        body's corners by `turn` (rad, default `orientation`) x their distance from the
        reference point further.  A pose within `position` and `orientation` of one
        inside the result is inside these limits (box: per axis; tilt: the triangle
        inequality of the rotation angle; a corner: moved by at most position + turn x
        its radius).  The result may be empty (lower > upper or tilt_max < 0): check
        that a known pose lies inside it."""
        dp, dr = position + ROUNDING, orientation + ROUNDING
        dt = (orientation if turn is None else turn) + ROUNDING
        return replace(
            self,
            lower=(self.lower[0] + dp, self.lower[1] + dp, self.lower[2] + dp),
            upper=(self.upper[0] - dp, self.upper[1] - dp, self.upper[2] - dp),
            tilt_max=self.tilt_max - dr,
            margin=(self.margin[0] + dp, self.margin[1] + dr),
            turn=self.turn + dt,
        )

    def widened_to(self, pose: Pose) -> PoseLimits:
        """The smallest limits holding both these and `pose` (its reference point and,
        with a body, its corners): for a transition from the current reference, which may
        not go further out than where it starts (enabled next to a wall, say) but must
        not be refused for starting there.  The environment is not widened: a start
        across an obstacle is refused."""
        p = np.array(pose.position_tuple)
        lower, upper = np.minimum(self.lower, p), np.maximum(self.upper, p)
        if self.body is not None:
            slack = self.turn * self.body.radii[:, None]
            world = self.body.world(pose.rotation, pose.position)
            lower = np.minimum(lower, (world - slack).min(axis=0))
            upper = np.maximum(upper, (world + slack).max(axis=0))
        return replace(
            self,
            lower=tuple(lower.tolist()),
            upper=tuple(upper.tolist()),
            tilt_max=max(self.tilt_max, tilt(pose, self.home)),
        )
