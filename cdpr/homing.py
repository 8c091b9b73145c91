"""Homing: each cable's length offset from the platform resting at a known pose (DESIGN
§15 step 3).

A drive reports length = offset + motor position x metres per increment; an incremental
encoder's position starts anywhere at power-up, so the offset is found where the lengths
are known: at a docking pose, the drums have paid out the model's geometric lengths
shortened by the cables' stretch under the static tensions there (cdpr.stretch's model,
L = l (1 + s t / EA)).  Pure: lengths in, offsets out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.pose import Pose
from cdpr.robot import Robot

Array = NDArray[np.float64]


def homed_offsets(
    robot: Robot,
    pose: Pose,
    tensions: ArrayLike,
    compliance_scale: float,
    lengths: ArrayLike,
    offsets: ArrayLike,
) -> Array:
    """The offsets (m, the length at motor position 0) that make `lengths`, read with
    `offsets`, equal the drum lengths of `robot` at rest at `pose` under `tensions` (N),
    the file's compliance scaled by `compliance_scale`."""
    stretch = np.asarray(tensions, dtype=float) * compliance_scale
    drum = robot.drum_lengths(robot.cable_lengths(pose), stretch)
    return np.asarray(offsets, dtype=float) + drum - np.asarray(lengths, dtype=float)
