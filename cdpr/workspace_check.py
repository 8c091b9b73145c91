"""Where the robot may go beyond its pose limits: the wrench that holds the platform at rest
inside the wrenches the cables can give, by a margin, and no cable touching another or
running through the platform's body.

One implementation for trajectory validation (every sampled reference, with the
platform's current mass and centre of mass: the payload estimate) and for the workspace
map (`cdprd workspace`, tuning.workspace_map): cdpr.wrench_margin and cdpr.interference
on batches of poses, a few microseconds a pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.dynamics import PlatformInertia
from cdpr.interference import Interference
from cdpr.reference import cable_segments
from cdpr.robot import Robot
from cdpr.trajectory.limits import BatchRefusal
from cdpr.wrench_margin import WrenchMargin, rest_wrenches, wrench_length

Array = NDArray[np.float64]


class Placed(NamedTuple):
    """The cables at a batch of poses: lengths (N x n), Jacobians (N x n x 6), where each
    free segment starts and ends (N x n x 3, world), and the rotations (N x 3 x 3)."""

    lengths: Array
    jacobians: Array
    starts: Array
    ends: Array
    rotations: Array


def place(robot: Robot, positions: ArrayLike, rotations: ArrayLike) -> Placed:
    """The cables at poses (positions N x 3; rotations N x 3 x 3, or one for all)."""
    P = np.asarray(positions, dtype=float)
    R = np.asarray(rotations, dtype=float)
    lengths, u, starts, ends = cable_segments(robot, P, R)
    r = ends - P[:, None, :]
    if R.ndim == 2:  # one rotation: the segments were cheaper with it; now one per pose
        R = np.broadcast_to(R, (len(P), 3, 3))
    return Placed(lengths, np.concatenate([u, np.cross(r, u)], axis=2), starts, ends, R)


@dataclass(frozen=True)
class WorkspaceCheck:
    """The capacity `margin` (N) every pose must keep and whether cables may not
    interfere, for `robot` with `platform` (its mass and centre of mass: the robot
    file's, or the payload estimate's)."""

    robot: Robot
    margin: float
    interference: bool
    platform: PlatformInertia
    wrenches: WrenchMargin
    touches: Interference

    @classmethod
    def of(cls, robot: Robot, margin: float = 0.0, interference: bool = True) -> WorkspaceCheck:
        """The check with the controller's tension range [t_min, force_max]."""
        g = robot.geometry
        return cls(
            robot,
            margin,
            interference,
            robot.platform,
            WrenchMargin(robot.t_min, robot.force_max, wrench_length(g.attachments)),
            Interference(robot.cable_diameter, robot.body.points, g.attachments, g.anchors),
        )

    def carrying(self, mass: float, center_of_mass: ArrayLike) -> WorkspaceCheck:
        """The same check for a platform of `mass` (kg, payload included) with its centre
        of mass at `center_of_mass` (platform frame, m)."""
        p = self.robot.platform
        com = tuple(float(c) for c in np.asarray(center_of_mass, dtype=float))
        platform = PlatformInertia(mass, com, p.inertia, p.gravity)
        return WorkspaceCheck(
            self.robot, self.margin, self.interference, platform, self.wrenches, self.touches
        )

    def margins(self, placed: Placed, payload: float = 0.0, parallel: bool = False) -> Array:
        """The capacity margin (N) at each pose, with `payload` (kg) more at the centre of
        mass; on this thread (the daemon), or on every core (`parallel`: the map)."""
        needed = rest_wrenches(self.platform, placed.rotations, payload, self._com)
        return self.wrenches.margins(placed.jacobians, needed, parallel=parallel)

    def first_refusal(
        self, positions: ArrayLike, rotations: ArrayLike, jacobians: ArrayLike | None = None
    ) -> BatchRefusal | None:
        """The first of the poses whose cables touch or whose margin falls short, else None
        (`jacobians`: Lambda at the poses where the caller has them, N x n x 6, with the
        rotations N x 3 x 3)."""
        if jacobians is None or self.interference:
            placed = place(self.robot, positions, rotations)
            jacobians, rotations = placed.jacobians, placed.rotations
        touching = (
            self.touches.any(placed.starts, placed.ends, placed.rotations, parallel=False)
            if self.interference
            else np.zeros(len(jacobians), np.bool_)
        )
        needed = rest_wrenches(self.platform, rotations, 0.0, self._com)
        short = self.wrenches.short_of(jacobians, needed, self.margin)
        bad = np.flatnonzero(touching | short)
        if not len(bad):
            return None
        i = int(bad[0])
        if touching[i]:
            found = self.touches.first(placed.starts[i], placed.ends[i], placed.rotations[i])
            assert found is not None
            return BatchRefusal(i, "workspace.interference", self.touches.describe(found))
        return BatchRefusal(i, "workspace.margin", self._short(jacobians[i], rotations[i]))

    @property
    def _com(self) -> tuple[float, float, float]:
        return self.platform.center_of_mass

    def _short(self, jacobian: Array, rotation: Array) -> str:
        needed = rest_wrenches(self.platform, rotation[None])[0]
        found = self.wrenches.margin(jacobian, needed)
        bounds = ", ".join(
            f"cable {k} at {'force_max' if up else 't_min'}"
            for k, up in zip(found.at_limit, found.upper, strict=True)
        )
        where = (
            f"{found.value:.1f} N inside" if found.value >= 0 else f"{-found.value:.1f} N outside"
        )
        return (
            f"the wrench holding the {self.platform.mass:g} kg platform at rest lies {where} "
            f"what the cables can give ({bounds}), less than workspace.margin {self.margin:g} N"
        )
