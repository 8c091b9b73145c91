"""The loop calibrate flies about each pose while it averages (daemon.cli.calibrate_cmd):
within the trajectory limits' jerk, which the daemon's validation holds it to."""

from __future__ import annotations

import pytest

from cdpr.trajectory import TrajectoryError, validate
from daemon.cli.calibrate_cmd import DITHER, dither_amplitude, dither_loop
from daemon.config import load_config
from tests.processes import CONFIG


@pytest.mark.parametrize("average", [0.05, 0.3, 0.75, 2.0])
def test_the_dither_loop_keeps_the_jerk_limit_the_config_sets(average: float) -> None:
    config = load_config(CONFIG)
    limits, robot = config.trajectory, config.robot
    assert limits.linear_jerk is not None  # the reference config bounds it
    amplitude = dither_amplitude(average, limits.linear_jerk)
    validate(dither_loop(robot.home, average, amplitude), robot, limits)
    # the full amplitude once the loop is slow enough: 2.0 s and 0.75 s are
    assert (amplitude == DITHER) == (average >= 0.75)
    assert amplitude > 0.0
    if amplitude < DITHER:  # the full loop would have been refused, and silently skipped
        with pytest.raises(TrajectoryError, match="linear_jerk"):
            validate(dither_loop(robot.home, average, DITHER), robot, limits)


def test_without_a_jerk_limit_the_dither_is_full() -> None:
    assert dither_amplitude(0.05, None) == DITHER
