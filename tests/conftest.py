"""Shared fixtures: the example robots and a random-pose strategy inside their workspaces."""

from __future__ import annotations

import os
from pathlib import Path

# isort: off
import daemon  # noqa: F401  first: its one BLAS thread is set before numpy loads

# isort: on
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot

ROOT = Path(__file__).resolve().parent.parent
# the daemons the tests start compile no kernels ahead (daemon.process.warm_up): a suite
# starts hundreds, each a few seconds long, and a warm-up each would be a CPU-bound
# process beside every flight; tests/daemon/test_warm_up.py turns it on for its own
os.environ.setdefault("CDPRD_WARM_UP", "0")
ROBOTS = ROOT / "config" / "robots"

# Deterministic in CI: the same examples every run, no wall-clock deadline on a busy machine.
settings.register_profile(
    "cdprd", derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("cdprd")


def load_robot(name: str) -> Robot:
    return Robot.from_yaml(ROBOTS / f"{name}.yaml")


@pytest.fixture(scope="session", params=["reference8", "suspended6"])
def robot(request: pytest.FixtureRequest) -> Robot:
    """Each example robot in turn (the second one exercises the pulley model)."""
    return load_robot(request.param)


@pytest.fixture(scope="session")
def reference8() -> Robot:
    return load_robot("reference8")


OFFSET8 = ROOT / "tests" / "data" / "robots" / "reference8-offset.yaml"


@pytest.fixture(scope="session")
def offset8() -> Robot:
    """reference8 with its crossed pairs routed clear of each other (the interference
    tests' robot: tests/data/robots/reference8-offset.yaml)."""
    return Robot.from_yaml(OFFSET8)


def workspace_poses(reach: float = 0.3, tilt: float = 0.2) -> st.SearchStrategy:
    """Offsets (dp, rotvec) from home within `reach` metres and `tilt` radians."""
    coord = st.floats(-reach, reach, allow_nan=False)
    angle = st.floats(-tilt, tilt, allow_nan=False)
    return st.tuples(st.tuples(coord, coord, coord), st.tuples(angle, angle, angle))


def pose_near_home(robot: Robot, offset: tuple) -> Pose:
    dp, rv = offset
    return Pose.from_rotvec(robot.home.position + np.array(dp), rv)


def twists(scale: float = 1.0) -> st.SearchStrategy:
    return st.lists(st.floats(-scale, scale, allow_nan=False), min_size=6, max_size=6).map(np.array)


HOST_TIMING_RERUNS = 1


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked host_timing flies in real time with several threads or processes on
    a shared host (the canopen harness, the daemon as processes, the UML guest): a
    hypervisor's stall or a starved thread can brake it where the daemon did nothing
    wrong.  Such a test runs again once when it fails (pytest-rerunfailures); a defect
    fails both runs, and the rerun shows in the summary ("1 rerun")."""
    for item in items:
        if item.get_closest_marker("host_timing") is not None:
            item.add_marker(pytest.mark.flaky(reruns=HOST_TIMING_RERUNS))
