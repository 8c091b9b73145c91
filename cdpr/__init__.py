"""cdpr: the pure model and control mathematics of a cable-driven parallel robot.

No I/O, no asyncio, no CAN, no zenoh: everything here runs unchanged in offline
lock-step simulation and inside the daemon.
"""

from cdpr.description import ConfigError
from cdpr.forward_kinematics import FKResult
from cdpr.pose import Pose, liediff, retract
from cdpr.robot import Robot

__all__ = ["ConfigError", "FKResult", "Pose", "Robot", "liediff", "retract"]
