"""The standard trajectory set (tuning.scenarios) flies through the daemon too: each
trajectory keeps the trajectory limits of the reference configs, which the daemon
checks before it accepts one."""

from __future__ import annotations

import pytest

from cdpr.trajectory.limits import validate
from daemon.config import load_config
from tests.daemon_stack import DRIVER_CONFIGS
from tuning.scenarios import STANDARD_SET


@pytest.mark.parametrize("protocol", sorted(DRIVER_CONFIGS))
@pytest.mark.parametrize("name", sorted(STANDARD_SET))
def test_the_standard_set_keeps_the_reference_configs_limits(name: str, protocol: str) -> None:
    config = load_config(DRIVER_CONFIGS[protocol])
    validate(STANDARD_SET[name](config.robot), config.robot, config.trajectory)
