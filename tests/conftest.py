"""Shared fixtures: the example robots and a random-pose strategy inside their workspaces."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from types import ModuleType

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
MEMORY_DIR = Path("/dev/shm")  # tmpfs: files here never reach the disk
_MEMORY_BASETEMP = pytest.StashKey[str]()  # the directory pytest_configure made there


def pytest_configure(config: pytest.Config) -> None:
    """Each test's tmp_path in memory where the host has a tmpfs (unless --basetemp
    says otherwise): the daemons the tests start write logs, state files and recordings
    there, and on this project's virtual machine a write reaching its disk can hold a
    CPU for tens of milliseconds, which a real-time flight beside it (a simulator's
    SYNC answers) does not survive.  Under pytest-xdist the workers take the
    controller's directory; it is removed at the end of the run."""
    if config.option.basetemp or os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if MEMORY_DIR.is_dir() and os.access(MEMORY_DIR, os.W_OK):
        config.option.basetemp = tempfile.mkdtemp(prefix="cdprd-pytest-", dir=MEMORY_DIR)
        config.stash[_MEMORY_BASETEMP] = config.option.basetemp


def pytest_unconfigure(config: pytest.Config) -> None:
    made = config.stash.get(_MEMORY_BASETEMP, None)
    if made is not None:
        shutil.rmtree(made, ignore_errors=True)


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
FLIGHT_HARNESSES = frozenset(  # what flies the robot in real time, by qualified name
    {
        "tests.daemon_stack.Stack",
        "tests.daemon_stack.flight_priority",
        "tests.processes",
        "tests.processes.serve_simulator",
        "tests.processes.start_daemon",
        "tests.processes.enabled_sim",
        "tests.canopen_robot.CanopenRobot",
        "daemon.cli.simulated.InProcessSimulator",
        "daemon.cli.simulated.ProcessSimulator",
        "tests.host_steal",
        "tests.host_steal.StealMeter",
        "tests.host_steal.FreezeWatch",
    }
)
FLIGHTS = pytest.mark.xdist_group("flights")


def qualified_name(value: object) -> str | None:
    """A module's name, or a class's or function's module and qualified name."""
    if isinstance(value, ModuleType):
        return value.__name__
    module, name = getattr(value, "__module__", None), getattr(value, "__qualname__", None)
    return f"{module}.{name}" if isinstance(module, str) and isinstance(name, str) else None


def flies(module: ModuleType) -> bool:
    """The test module flies the robot in real time: it holds one of FLIGHT_HARNESSES."""
    return any(qualified_name(value) in FLIGHT_HARNESSES for value in vars(module).values())


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's, which reads the xdist_group marks
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked host_timing flies in real time with several threads or processes on
    a shared host (the canopen harness, the daemon as processes, the UML guest): a
    hypervisor's stall or a starved thread can brake it where the daemon did nothing
    wrong.  Such a test runs again once when it fails (pytest-rerunfailures); a defect
    fails both runs, and the rerun shows in the summary ("1 rerun").

    Under pytest-xdist (`-n auto`, `--dist loadgroup` from pyproject's addopts) the tests
    of a module that flies (`flies`) and those marked host_timing run in one group: on
    one worker, one at a time, as in a plain run, for two flights side by side starve
    each other's threads and brake.  The group also keeps the fixed ports some take
    (7447 and 7448 in tests/daemon/test_ros2_router.py) to one test at a time."""
    for item in items:
        timing = item.get_closest_marker("host_timing") is not None
        if timing:
            item.add_marker(pytest.mark.flaky(reruns=HOST_TIMING_RERUNS))
        module = getattr(item, "module", None)
        if timing or (module is not None and flies(module)):
            item.add_marker(FLIGHTS)
