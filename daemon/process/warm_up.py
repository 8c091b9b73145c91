"""Numba's kernels compiled before the first path arrives, in a process of their own.

The path timing and the trajectory validation run compiled kernels (cdpr.wrench_margin,
cdpr.interference, cdpr.compiled_model, cdpr.trajectory.compiled_curve) that numba
compiles at their first call and keeps in its on-disk cache (cdpr.compiled_cache).  In
a fresh install, or after an upgrade whose sources changed the cache's key, the first
path a client sends was timed in ~14 s on this 2-vCPU host, most of it compiling, where
a warm cache takes 0.3 s.  The companion therefore starts this module once per cache
(`start`), at idle priority, to time and validate a short path on the daemon's robot:
the cache is then warm for the companion's own first path, and a `warm` file in the
keyed cache directory says so.

`python -m daemon.process.warm_up CONFIG`: exits 0 once the kernels are cached.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

MARKER = "warm"  # in the keyed cache directory, once a warm-up finished there


def _marker() -> Path:
    from cdpr.compiled_cache import key_numba_cache

    return key_numba_cache() / MARKER


def is_warm() -> bool:
    """True once a warm-up finished in this cache (the kernels load, not compile)."""
    return _marker().exists()


def start(config_path: str | Path) -> subprocess.Popen[bytes] | None:
    """The warm-up of the kernels for the daemon config at `config_path`, started in
    the background; None when this cache was warmed before, the config is not a file,
    or CDPRD_WARM_UP=0 (a host whose cache is compiled at install, or a test suite that
    starts a daemon a second: the kernels are then compiled at the first path)."""
    if os.environ.get("CDPRD_WARM_UP") == "0":
        return None
    if not Path(config_path).is_file() or is_warm():
        return None
    argv = [sys.executable, "-m", __name__, str(config_path)]
    devnull = subprocess.DEVNULL
    return subprocess.Popen(argv, stdin=devnull, stdout=devnull, stderr=devnull)


def warm(config_path: str | Path) -> None:
    """Time a 2 cm path from the robot's home as the daemon times one and validate it
    as the daemon validates a client's: every kernel either runs is compiled, and the
    cache keeps it; then the marker."""
    import numpy as np

    from cdpr.path import Path as PosePath
    from cdpr.path import PathPoint
    from cdpr.pose import Pose
    from daemon.config import load_config
    from daemon.service.planner import path_timer, validate_as_the_daemon

    config = load_config(config_path)
    home = config.robot.home
    nearby = Pose(home.position + np.array([0.02, 0.0, 0.0]), home.quaternion)
    timed = path_timer(config)(PosePath((PathPoint(home), PathPoint(nearby))))
    validate_as_the_daemon(timed, config)
    marker = _marker()
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()


if __name__ == "__main__":
    os.nice(19)  # idle priority: it must cost the daemon nothing it needs
    warm(sys.argv[1])
