"""Numba's on-disk cache in a directory named by the compiled modules' sources.

Numba keeps a compiled function while its own file is unchanged (modification time and
size), but the machine code it saved also holds what it called in other files: after an
edit of cdpr/wrench_margin.py, tuning/workspace_map.py's map pass went on running the
old margin kernel from its cache, silently (and an upgrade that leaves a cache directory
in place, as the systemd unit's NUMBA_CACHE_DIR does, could do the same).  Each module
that compiles calls `key_numba_cache()` before its first `@njit(cache=True)`: the cache
then lives in `cdprd-<digest>` under NUMBA_CACHE_DIR (else cdpr/__pycache__/numba, beside
the sources as numba's own default is: a read-only root with the source tree writable,
as the UML guest of the vcan tests has, still finds what the host compiled), the digest
taken over every file in SOURCES, so any edit starts a fresh cache.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# every file that compiles with numba (tests/cdpr/test_compiled_cache.py keeps it whole)
SOURCES = (
    "cdpr/command.py",
    "cdpr/compiled_linalg.py",
    "cdpr/compiled_model.py",
    "cdpr/forward_kinematics.py",
    "cdpr/kinematics.py",
    "cdpr/measurement.py",
    "cdpr/pose.py",  # its pose_difference is compiled from the kernel that calls it
    "cdpr/single_actuator.py",
    "cdpr/so3.py",  # so are its scalar functions
    "cdpr/stretch.py",
    "cdpr/tension.py",
    "cdpr/wrench_observer.py",
    "cdpr/wrench_margin.py",
    "cdpr/interference.py",
    "cdpr/path/jerk_estimate.py",
    "cdpr/path/reachability.py",
    "cdpr/path/time_law.py",
    "cdpr/trajectory/compiled_curve.py",
    "tuning/workspace_map.py",
)


def source_digest(root: Path = ROOT) -> str:
    """16 hex digits of a hash of the SOURCES under `root` (a missing one counts as empty)."""
    digest = hashlib.sha256()
    for name in SOURCES:
        path = root / name
        digest.update(name.encode() + b"\0")
        digest.update(path.read_bytes() if path.exists() else b"")
    return digest.hexdigest()[:16]


def cache_base() -> Path:
    """NUMBA_CACHE_DIR if set (the systemd unit sets /var/cache/cdprd), else
    cdpr/__pycache__/numba."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    beside_the_sources = Path(__file__).resolve().parent / "__pycache__" / "numba"
    return Path(configured) if configured else beside_the_sources


def key_numba_cache() -> Path:
    """Point numba's cache at cache_base() / cdprd-<source_digest()> (idempotent); the
    directory.  Numba falls back to its own locations if that one is not writable."""
    from numba.core import config

    path = cache_base() / f"cdprd-{source_digest()}"
    config.CACHE_DIR = str(path)
    return path
