"""Reference trajectories for the controller (DESIGN §7).

Waypoints become a C² pose reference (`Trajectory`), sampled once per control cycle;
`parse_trajectory` reads the interface form (JSON / YAML), `validate` checks a whole
trajectory against rate, pose, cable-length and wrench limits before it runs, and `approach`
/ `goto` build jump-free transitions from the current reference.
"""

from cdpr.trajectory.core import (
    SCHEMA_VERSION,
    Reference,
    Samples,
    Trajectory,
    TrajectoryError,
    Waypoint,
)
from cdpr.trajectory.limits import (
    LengthLimits,
    Screened,
    TrajectoryLimits,
    WrenchCheck,
    cable_speed_bounds,
    check_start_delay,
    check_target,
    sampled_pose_limits,
    tracked_length_limits,
    validate,
    validation_steps,
)
from cdpr.trajectory.parse import parse_trajectory
from cdpr.trajectory.transitions import (
    approach,
    approach_steps,
    goto,
    goto_steps,
    run_steps,
    stop_steps,
)

__all__ = [
    "SCHEMA_VERSION",
    "LengthLimits",
    "Reference",
    "Samples",
    "Screened",
    "Trajectory",
    "TrajectoryError",
    "TrajectoryLimits",
    "Waypoint",
    "WrenchCheck",
    "approach",
    "approach_steps",
    "cable_speed_bounds",
    "check_start_delay",
    "check_target",
    "goto",
    "goto_steps",
    "parse_trajectory",
    "run_steps",
    "sampled_pose_limits",
    "stop_steps",
    "tracked_length_limits",
    "validate",
    "validation_steps",
]
