"""What the control cycle asks of a procedure that moves the robot from inside it.

Most procedures move the robot from outside the cycle: identify-payload and the
calibration flights fly gotos through the planner, home samples the feedback between
cycles.  One needs the cycle itself: pretension (daemon.service.pretension_run) winds
slack cables in and tensions them with forces of its own in the PRETENSION state, then
hands the robot over to the position loop.  The service (daemon.service.service) holds
such a procedure as `procedure` and drives it through this protocol alone, so the cycle
knows when to call a procedure, never what a procedure does.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class CycleProcedure(Protocol):
    """A procedure the control cycle drives."""

    @property
    def winding(self) -> bool:
        """Its cables may move as no pose explains (slack ones being wound in): the
        cycle judges their lengths with TrustedLengths.track, not check."""

    def cycle(self, t: float, lengths: list[float], rates: list[float]) -> None:
        """One cycle at cycle time `t` (s) in the procedure's own safety state, on the
        plausible `lengths` and `rates`: its commands go out, or it brakes."""

    def before_step(self, t: float) -> None:
        """Before the controller's step at `t`, once the position loop runs: what the
        procedure still hands over to the controller."""

    def after_commands(self, commands: np.ndarray) -> None:
        """The controller's force commands (N) of a cycle went out."""

    def end(self, why: str) -> None:
        """The robot stopped under the procedure (a brake or a disable, `why`): whoever
        waits for it is woken."""
