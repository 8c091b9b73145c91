"""Coulomb friction in the winches, in cable coordinates: a force of the robot file's
`friction` (N) against each drum's motion, which the winch's motor must add to move it
(as it adds k0 l' against the back-EMF; Assumption 1 of the paper leaves friction out).

Its direction is sgn(l'), softened below SPEED_FLOOR: tanh(l' / SPEED_FLOOR), so that a
drum at rest, or noise on its speed, asks for no force and the force turns smoothly
where the motion does.  `cdprd tune` identifies the friction with the same softened sign
(tuning.identify), the controller compensates it along the reference's cable rates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

SPEED_FLOOR = 5e-3  # m/s: below it the friction's sign is softened (tanh), noise is no motion


def friction_direction(speed: ArrayLike) -> NDArray[np.float64]:
    """sgn(speed), softened: tanh(speed / SPEED_FLOOR), per cable (speeds in m/s)."""
    return np.tanh(np.asarray(speed, dtype=float) / SPEED_FLOOR)
